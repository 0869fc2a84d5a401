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


def longest_wait(records, instant):
    """The longest time a call waited for its reply after ``instant`` (e.g. a crash): the outage a
    client saw. records are (index, sent, replied, ok) with wall-clock times; None if no reply came later."""
    waits = [replied - max(sent, instant) for _, sent, replied, _ in records if replied > instant]
    return max(waits) if waits else None
