"""Small statistics for benchmarks and reports."""


def percentile(values, q):
    """The q-th percentile (0..100) of values, by linear interpolation; None if empty."""
    data = sorted(values)
    if not data:
        return None
    pos = (len(data) - 1) * q / 100.0
    lo = int(pos)
    hi = min(lo + 1, len(data) - 1)
    return data[lo] + (data[hi] - data[lo]) * (pos - lo)


def median(values):
    return percentile(values, 50)
