"""Incremental checkpoints: the change between two states as a small delta, checked on both sides.

PBR checkpoints the server's whole state after each request; with a 1 MB state and a request that
changes 100 bytes, that is 1 MB between replicas per request. A :class:`DeltaEncoder` on the primary
sends, instead, what changed since its previous checkpoint (the backup applies checkpoints in order
and refuses a gap, so that previous state is the one the backup holds); a :class:`DeltaDecoder` on
the backup rebuilds the state. Any server gets it: the delta is computed here from the states its
getState returns, without a change to the server.

The format (little-endian): a header ``AFTD``, version, the base's length and CRC-32, the new
state's length and CRC-32, the number of runs; then each run: the start and end offsets in the
base that it replaces, the length of its data, and the data. Runs are in order and do not overlap.
The decoder checks the base it holds against the header before applying (a delta against another
base is refused, naming both), and the result against the new CRC (a corrupt delta is refused): a
refused delta changes nothing, and the backup asks for a full transfer (it joins again).

A server that knows what changed may say so itself (aft_msgs/GetStateDelta, offered beside its
getState; :class:`ServerChanges`): runs on the state of a version it named, with the new state's
length and CRC. The encoder applies them to the state it sent last and checks the result against
that CRC before anything leaves (:meth:`DeltaEncoder.next_changes`): changes that do not rebuild the
server's state are refused here, by name, and the backup never sees them.

The encoder finds changes by comparing blocks (C-speed slices of ``BLOCK`` bytes, then of ``FINE``
bytes inside a changed block), so a 1 MB state costs well under a millisecond when little changed.
"""
import struct
import zlib

MAGIC = b'AFTD'
VERSION = 1
_HEADER = struct.Struct('<4sBQIQII')    # magic, version, base len, base crc, new len, new crc, runs
_RUN = struct.Struct('<QQQ')            # base start, base end, data length
BLOCK = 4096
FINE = 64
MERGE_GAP = _RUN.size                   # runs closer than one run header are merged into one


class DeltaError(ValueError):
    """A delta that cannot be applied to the state held (names what is wrong)."""


def crc(data):
    return zlib.crc32(data) & 0xffffffff


def _common_prefix(a, b):
    """Length of the common prefix of two bytes: blocks, then FINE pieces, then bytes compared (slices of
    bytes compare with memcmp; memoryview slices compare ten times slower)."""
    limit, at = min(len(a), len(b)), 0
    for step in (BLOCK, FINE, 1):
        while at + step <= limit and a[at:at + step] == b[at:at + step]:
            at += step
    return at


def _common_suffix(a, b, limit):
    """Length of the common suffix of two bytes, at most limit."""
    limit, at = min(len(a), len(b), limit), 0
    for step in (BLOCK, FINE, 1):
        while at + step <= limit and a[len(a) - at - step:len(a) - at] == b[len(b) - at - step:len(b) - at]:
            at += step
    return at


def _changed_spans(old, new):
    """[(start, end)] where two states of equal length differ, at FINE granularity, merged."""
    spans = []
    size = len(old)
    for block in range(0, size, BLOCK):
        end = min(block + BLOCK, size)
        if old[block:end] == new[block:end]:
            continue
        for fine in range(block, end, FINE):
            stop = min(fine + FINE, end)
            if old[fine:stop] != new[fine:stop]:
                if spans and fine - spans[-1][1] <= MERGE_GAP:
                    spans[-1] = (spans[-1][0], stop)
                else:
                    spans.append((fine, stop))
    return spans


def encode(base, new, base_crc=None, new_crc=None):
    """The delta that turns base into new (bytes); the CRCs, if the caller knows them, are not computed
    again."""
    base, new = bytes(base), bytes(new)
    if len(base) == len(new):
        runs = [(start, end, new[start:end]) for start, end in _changed_spans(base, new)]
    else:
        prefix = _common_prefix(base, new)
        suffix = _common_suffix(base, new, min(len(base), len(new)) - prefix)
        runs = [(prefix, len(base) - suffix, new[prefix:len(new) - suffix])]
    return _pack(len(base), crc(base) if base_crc is None else base_crc, len(new),
                 crc(new) if new_crc is None else new_crc, runs)


def _pack(base_len, base_crc, new_len, new_crc, runs):
    parts = [_HEADER.pack(MAGIC, VERSION, base_len, base_crc, new_len, new_crc, len(runs))]
    for start, end, data in runs:
        parts.append(_RUN.pack(start, end, len(data)))
        parts.append(data)
    return b''.join(parts)


def rebuild(base, runs):
    """The state that runs [(start, end, data)] (in order, not overlapping, within base) turn base into;
    DeltaError names the first run that is not."""
    parts, previous = [], 0
    for index, (start, end, data) in enumerate(runs):
        if not start <= end <= len(base):
            raise DeltaError('run %d of %d (%d-%d) is out of the %d-byte state' % (index + 1, len(runs), start, end,
                                                                                 len(base)))
        if start < previous:
            raise DeltaError('run %d of %d (%d-%d) starts before the end of the previous run (%d): runs must be in '
                             'order and not overlap' % (index + 1, len(runs), start, end, previous))
        parts.append(base[previous:start])
        parts.append(bytes(data))
        previous = end
    parts.append(base[previous:])
    return b''.join(parts)


class ServerChanges(object):
    """A server's own answer to "what changed since version ``since``" (aft_msgs/GetStateDelta):
    either the whole state (``state``), or ``runs`` [(start, end, data)] on the state of that version,
    with the new state's ``size`` and ``crc``."""

    def __init__(self, version, state=None, runs=None, size=None, crc=None):
        if (state is None) == (runs is None):
            raise ValueError('server changes hold the whole state or runs, not both or neither')
        self.version, self.state, self.runs, self.size, self.crc = version, state, runs, size, crc

    @classmethod
    def from_message(cls, m):
        """From an aft_msgs/GetStateDelta response; DeltaError if its runs do not add up."""
        if m.whole:
            return cls(m.version, state=bytes(m.state))
        if not len(m.starts) == len(m.ends) == len(m.lengths):
            raise DeltaError('the server sent %d starts, %d ends and %d lengths of runs'
                             % (len(m.starts), len(m.ends), len(m.lengths)))
        if sum(m.lengths) != len(m.data):
            raise DeltaError('the server\'s runs hold %d bytes of data, their lengths add up to %d'
                             % (len(m.data), sum(m.lengths)))
        data, runs, at = bytes(m.data), [], 0
        for start, end, length in zip(m.starts, m.ends, m.lengths):
            runs.append((start, end, data[at:at + length]))
            at += length
        return cls(m.version, runs=runs, size=m.size, crc=m.crc)


def apply(base, delta, base_crc=None):
    """The state that delta turns base into; DeltaError (changing nothing) if it cannot be applied.
    base_crc: the base's CRC if the caller knows it."""
    return _apply(base, delta, base_crc)[0]


def _apply(base, delta, base_crc):
    """(the state rebuilt, its CRC)."""
    delta, base = bytes(delta), bytes(base)
    base_crc = crc(base) if base_crc is None else base_crc
    if len(delta) < _HEADER.size or delta[:4] != MAGIC:
        raise DeltaError('not a state delta (%d bytes, no %r header)' % (len(delta), MAGIC))
    magic, version, base_len, header_crc, new_len, new_crc, count = _HEADER.unpack_from(delta)
    if version != VERSION:
        raise DeltaError('state delta version %d, this node reads version %d' % (version, VERSION))
    if base_len != len(base) or header_crc != base_crc:
        raise DeltaError('the delta is against a state of %d bytes (CRC %08x), the state held has %d bytes '
                         '(CRC %08x)' % (base_len, header_crc, len(base), base_crc))
    parts, offset, previous = [], _HEADER.size, 0
    for index in range(count):
        if offset + _RUN.size > len(delta):
            raise DeltaError('state delta truncated in run %d of %d' % (index + 1, count))
        start, end, length = _RUN.unpack_from(delta, offset)
        offset += _RUN.size
        if not previous <= start <= end <= base_len or offset + length > len(delta):
            raise DeltaError('state delta run %d of %d is out of bounds (%d-%d, %d bytes of data)'
                             % (index + 1, count, start, end, length))
        parts.append(base[previous:start])
        parts.append(delta[offset:offset + length])
        offset += length
        previous = end
    if offset != len(delta):
        raise DeltaError('state delta has %d bytes after its last run' % (len(delta) - offset))
    parts.append(base[previous:])
    result = b''.join(parts)
    result_crc = crc(result)
    if len(result) != new_len or result_crc != new_crc:
        raise DeltaError('the state rebuilt from the delta does not match it (%d bytes, CRC %08x; the delta says '
                         '%d bytes, CRC %08x)' % (len(result), result_crc, new_len, new_crc))
    return result, result_crc


class DeltaEncoder(object):
    """Primary side: what to send for each new state. ``min_size``: states smaller than this are sent
    whole (a delta's header would cost more than it saves)."""

    def __init__(self, min_size=1024):
        self.min_size = min_size
        self.base = None          # the state of the previous checkpoint sent with a state
        self.base_crc = None
        self.version = None       # the server's version of base, when the server's own changes gave it
        self.sent_bytes = 0       # state bytes sent (deltas or whole)
        self.state_bytes = 0      # what whole states would have cost

    def reset(self, state=None):
        """A full state was sent (a state transfer), or nothing is known of the backup's (None)."""
        self.base = bytes(state) if state is not None else None
        self.base_crc = crc(self.base) if state is not None else None
        self.version = None       # the server's version of base, when the server's own changes gave it

    def wants_changes(self):
        """Whether to ask the server's own changes for the next checkpoint rather than its whole state: only
        once the last state is at least ``min_size``. A smaller one is sent whole whatever the server
        tells, and a whole getState is the cheaper call (the bank's: 0.067 ms, its changes 0.101 ms)."""
        return self.base is not None and len(self.base) >= self.min_size

    def next(self, state, version=None):
        """(payload, is_delta) for a checkpoint carrying ``state`` (of the server's ``version``, if it
        told); it becomes the next base."""
        state = bytes(state)
        payload, is_delta, state_crc = state, False, None
        if self.base is not None and len(state) >= self.min_size:
            state_crc = crc(state)
            delta = encode(self.base, state, self.base_crc, state_crc)
            if len(delta) < len(state) // 2:
                payload, is_delta = delta, True
        return self._sent(state, state_crc if state_crc is not None else crc(state), payload, is_delta, version)

    def next_changes(self, changes):
        """(payload, is_delta) for a checkpoint from the server's own changes (:class:`ServerChanges`)
        since ``self.version``: its runs are applied to the base and the result checked against the
        server's size and CRC. DeltaError (nothing changed) if they do not rebuild it: the caller then
        captures the whole state (``next``)."""
        if changes.state is not None:
            return self.next(changes.state, changes.version)
        if self.base is None or self.version is None:
            raise DeltaError('the server sent changes, and this After holds no state of a version it named')
        state = rebuild(self.base, changes.runs)
        state_crc = crc(state)
        if len(state) != changes.size or state_crc != changes.crc:
            raise DeltaError('the server\'s changes since version %s rebuild %d bytes (CRC %08x); the server says '
                             '%d bytes (CRC %08x)' % (self.version, len(state), state_crc, changes.size, changes.crc))
        payload, is_delta = state, False
        if len(state) >= self.min_size:
            delta = _pack(len(self.base), self.base_crc, len(state), state_crc, changes.runs)
            if len(delta) < len(state) // 2:
                payload, is_delta = delta, True
        return self._sent(state, state_crc, payload, is_delta, changes.version)

    def _sent(self, state, state_crc, payload, is_delta, version):
        self.base, self.base_crc, self.version = state, state_crc, version
        self.sent_bytes += len(payload)
        self.state_bytes += len(state)
        return payload, is_delta


class DeltaDecoder(object):
    """Backup side: the whole state of each checkpoint, from a whole state or a delta on the last one."""

    def __init__(self):
        self.base = None
        self.base_crc = None
        self._rebuilt = (None, None)   # the last state rebuilt here, with its CRC (checked already)

    def state(self, payload, is_delta):
        """The whole state a checkpoint carries; DeltaError (base kept) if its delta cannot be applied."""
        if not is_delta:
            return bytes(payload)
        if self.base is None:
            raise DeltaError('a state delta arrived, and this backup holds no state to apply it to')
        self._rebuilt = _apply(self.base, payload, self.base_crc)
        return self._rebuilt[0]

    def accept(self, state):
        """The checkpoint carrying ``state`` (whole) was accepted: the next delta applies to it."""
        rebuilt, rebuilt_crc = self._rebuilt
        self.base, self.base_crc = state, rebuilt_crc if state is rebuilt else crc(state)
        self._rebuilt = (None, None)
