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

Both sides hold the last state as a :class:`StateBuffer`: runs that keep the state's length (a
server's usual changes) are applied to it in place, and its CRC-32 is had from the CRCs of the
64 KB blocks changed and a fold over the blocks' CRCs (zlib's CRC-32 of a concatenation, from a
linear map made once from zlib itself), so a checkpoint of a few changed bytes in a 10 MB state
costs about 0.1 ms on each side instead of a 10 MB splice and CRC (5 ms). A run that changes the
length rebuilds the state whole, as before.

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


def _parse(delta, base_len, base_crc):
    """(the new state's length, its CRC, runs [(start, end, data)]) of a delta against a state of
    ``base_len`` bytes with CRC ``base_crc``; DeltaError if it is not such a delta."""
    delta = bytes(delta)
    if len(delta) < _HEADER.size or delta[:4] != MAGIC:
        raise DeltaError('not a state delta (%d bytes, no %r header)' % (len(delta), MAGIC))
    magic, version, header_len, header_crc, new_len, new_crc, count = _HEADER.unpack_from(delta)
    if version != VERSION:
        raise DeltaError('state delta version %d, this node reads version %d' % (version, VERSION))
    if header_len != base_len or header_crc != base_crc:
        raise DeltaError('the delta is against a state of %d bytes (CRC %08x), the state held has %d bytes '
                         '(CRC %08x)' % (header_len, header_crc, base_len, base_crc))
    runs, offset, previous = [], _HEADER.size, 0
    for index in range(count):
        if offset + _RUN.size > len(delta):
            raise DeltaError('state delta truncated in run %d of %d' % (index + 1, count))
        start, end, length = _RUN.unpack_from(delta, offset)
        offset += _RUN.size
        if not previous <= start <= end <= base_len or offset + length > len(delta):
            raise DeltaError('state delta run %d of %d is out of bounds (%d-%d, %d bytes of data)'
                             % (index + 1, count, start, end, length))
        runs.append((start, end, delta[offset:offset + length]))
        offset += length
        previous = end
    if offset != len(delta):
        raise DeltaError('state delta has %d bytes after its last run' % (len(delta) - offset))
    return new_len, new_crc, runs


def _apply(base, delta, base_crc):
    """(the state rebuilt, its CRC)."""
    base = bytes(base)
    base_crc = crc(base) if base_crc is None else base_crc
    new_len, new_crc, runs = _parse(delta, len(base), base_crc)
    result = rebuild(base, runs)
    result_crc = crc(result)
    if len(result) != new_len or result_crc != new_crc:
        raise DeltaError('the state rebuilt from the delta does not match it (%d bytes, CRC %08x; the delta says '
                         '%d bytes, CRC %08x)' % (len(result), result_crc, new_len, new_crc))
    return result, result_crc


# -- A state held for deltas: changes applied in place, its CRC-32 from the blocks changed ---------------
CRC_BLOCK = 64 * 1024   # bytes per block of a StateBuffer's CRCs
_SHIFT = []             # the four byte tables of "CRC_BLOCK zero bytes through CRC-32's register" (made once)


def _shift_tables():
    """Tables T[k][b] of the linear map Z (CRC_BLOCK zero bytes fed to CRC-32's register, no pre- or
    post-conditioning), on the byte b in position k of the register. For zlib's CRC-32,
    crc(A + B) = Z(crc(A)) ^ crc(B) when B has CRC_BLOCK bytes, and Z(v) = crc32(zeros, v) ^ crc32(zeros, 0),
    so the 32 basis vectors come from zlib itself."""
    if not _SHIFT:
        zeros = bytes(CRC_BLOCK)
        offset = zlib.crc32(zeros, 0)
        basis = [zlib.crc32(zeros, 1 << bit) ^ offset for bit in range(32)]
        tables = []
        for k in range(4):
            table = [0] * 256
            for value in range(1, 256):
                low = value & -value                      # the lowest bit set, and the rest already made
                table[value] = table[value ^ low] ^ basis[8 * k + low.bit_length() - 1]
            tables.append(table)
        _SHIFT[:] = tables
    return _SHIFT


class StateBuffer(object):
    """A state with its CRC-32 (``crc``), whose runs that keep the length are applied in place
    (:meth:`replace`): the state is then a bytearray with the CRC-32 of each CRC_BLOCK block, and the
    whole CRC is had from the changed blocks and a fold over the blocks' CRCs, O(changes + blocks)
    instead of O(size) (a 10 MB state: a splice and a CRC of 10 MB cost about 5 ms per checkpoint on
    each side). Until its first change in place it is the bytes it was made from, with their CRC
    (``known_crc`` if the caller has it), if made ``lazy`` or with its CRC known: a state captured
    whole for each checkpoint costs no more than its CRC. Otherwise it is made ready for changes in
    place at once (a copy and the blocks' CRCs: 5 ms for 10 MB), so that the first change after a state
    transfer does not pay it on the clients' path."""

    def __init__(self, data, known_crc=None, lazy=False):
        self.data = data if isinstance(data, bytes) else bytes(data)
        self.blocks = None        # made at the first change in place (at once unless lazy)
        if lazy or known_crc is not None:
            self.crc = zlib.crc32(self.data) if known_crc is None else known_crc
        else:
            self._in_place()
            self.crc = self._fold()

    def __len__(self):
        return len(self.data)

    def __eq__(self, other):
        return self.data == (other.data if isinstance(other, StateBuffer) else other)

    __hash__ = None   # mutable

    def bytes(self):
        return bytes(self.data)

    def _in_place(self):
        if self.blocks is None:
            self.data = bytearray(self.data)
            with memoryview(self.data) as view:   # (no copy of each block; released before any resize)
                self.blocks = [zlib.crc32(view[at:at + CRC_BLOCK]) for at in range(0, len(self.data), CRC_BLOCK)]

    def _fold(self):
        shift = _shift_tables()
        t0, t1, t2, t3 = shift
        full = len(self.data) // CRC_BLOCK
        value = 0                                 # the CRC-32 of nothing
        for block in self.blocks[:full]:
            value = (t0[value & 255] ^ t1[(value >> 8) & 255] ^ t2[(value >> 16) & 255] ^ t3[value >> 24]) ^ block
        if full < len(self.blocks):               # the last, shorter block: zlib goes on from the value
            with memoryview(self.data) as view:
                value = zlib.crc32(view[full * CRC_BLOCK:], value)
        return value

    def replace(self, runs, expect_crc=None):
        """Apply runs [(start, end, data)] that keep their length (data as long as end - start), in order
        and not overlapping, in place; returns the new CRC. DeltaError, changing nothing, if a run is out
        of bounds or out of order, or if the result's CRC is not ``expect_crc`` (when given)."""
        previous, size = 0, len(self.data)
        for index, (start, end, data) in enumerate(runs):
            if not previous <= start <= end <= size or len(data) != end - start:
                raise DeltaError('run %d of %d (%d-%d, %d bytes) does not fit the %d-byte state in place'
                                 % (index + 1, len(runs), start, end, len(data), size))
            previous = end
        self._in_place()
        undo = [(start, bytes(self.data[start:end])) for start, end, _ in runs]
        blocks, old_crc = list(self.blocks), self.crc
        touched = set()
        for start, end, data in runs:
            self.data[start:end] = data
            touched.update(range(start // CRC_BLOCK, (end - 1) // CRC_BLOCK + 1) if end > start else ())
        with memoryview(self.data) as view:
            for block in touched:
                self.blocks[block] = zlib.crc32(view[block * CRC_BLOCK:(block + 1) * CRC_BLOCK])
        self.crc = self._fold()
        if expect_crc is not None and self.crc != expect_crc:
            got = self.crc
            for start, old in undo:
                self.data[start:start + len(old)] = old
            self.blocks, self.crc = blocks, old_crc
            error = DeltaError('the state rebuilt has CRC %08x, expected %08x' % (got, expect_crc))
            error.got = got
            raise error
        return self.crc


def fits_in_place(runs):
    """Whether every run keeps its length (StateBuffer.replace can take them)."""
    return all(len(data) == end - start for start, end, data in runs)


class DeltaEncoder(object):
    """Primary side: what to send for each new state. ``min_size``: states smaller than this are sent
    whole (a delta's header would cost more than it saves). The state sent last is held as a
    :class:`StateBuffer`: the server's own changes that keep the length are applied to it in place."""

    def __init__(self, min_size=1024):
        self.min_size = min_size
        self.base = None          # StateBuffer: the state of the previous checkpoint sent with a state
        self.version = None       # the server's version of base, when the server's own changes gave it
        self.sent_bytes = 0       # state bytes sent (deltas or whole)
        self.state_bytes = 0      # what whole states would have cost

    @property
    def base_crc(self):
        return self.base.crc if self.base is not None else None

    def reset(self, state=None, version=None):
        """A full state was sent (a state transfer), of the server's ``version`` if known, or nothing is
        known of the backup's (None)."""
        self.base = StateBuffer(state) if state is not None else None
        self.version = version if state is not None else None

    def wants_changes(self):
        """Whether to ask the server's own changes for the next checkpoint rather than its whole state: only
        once the last state is at least ``min_size``. A smaller one is sent whole whatever the server
        tells, and a whole getState is the cheaper call (the bank's: 0.067 ms, its changes 0.101 ms)."""
        return self.base is not None and len(self.base) >= self.min_size

    def next(self, state, version=None):
        """(payload, is_delta) for a checkpoint carrying ``state`` (of the server's ``version``, if it
        told); it becomes the next base."""
        buffer = StateBuffer(state, lazy=True)
        state = buffer.data
        payload, is_delta = state, False
        if self.base is not None and len(state) >= self.min_size:
            delta = encode(self.base.data, state, self.base.crc, buffer.crc)
            if len(delta) < len(state) // 2:
                payload, is_delta = delta, True
        return self._sent(buffer, payload, is_delta, version)

    def next_changes(self, changes):
        """(payload, is_delta) for a checkpoint from the server's own changes (:class:`ServerChanges`)
        since ``self.version``: its runs are applied to the base and the result checked against the
        server's size and CRC. DeltaError (nothing changed) if they do not rebuild it: the caller then
        captures the whole state (``next``)."""
        if changes.state is not None:
            return self.next(changes.state, changes.version)
        base_len, base_crc = (len(self.base), self.base.crc) if self.base is not None else (0, None)
        buffer = self._rebuilt(changes)
        payload, is_delta = None, False
        if len(buffer) >= self.min_size:
            delta = _pack(base_len, base_crc, len(buffer), buffer.crc, changes.runs)
            if len(delta) < len(buffer) // 2:
                payload, is_delta = delta, True
        if payload is None:
            payload = buffer.bytes()
        return self._sent(buffer, payload, is_delta, changes.version)

    def follow(self, changes):
        """Bring the base up to the server's state from its changes (:class:`ServerChanges`) since
        ``self.version``, no checkpoint made of it: a state transfer then sends the base instead of a
        whole getState (a primary that ran alone since its last checkpoint holds that state and version).
        DeltaError (nothing changed) if they do not rebuild the server's state."""
        if changes.state is not None:
            self.reset(changes.state, changes.version)
            return
        self.base, self.version = self._rebuilt(changes), changes.version

    def _rebuilt(self, changes):
        """The base with the server's runs applied (in place where they keep the length), checked
        against the server's size and CRC; DeltaError, the base unchanged, if it does not match."""
        if self.base is None or self.version is None:
            raise DeltaError('the server sent changes, and this After holds no state of a version it named')
        base_len = len(self.base)
        if fits_in_place(changes.runs) and changes.size == base_len:
            try:
                self.base.replace(changes.runs, changes.crc)
            except DeltaError as e:
                raise DeltaError('the server\'s changes since version %s rebuild %d bytes (CRC %08x); the server '
                                 'says %d bytes (CRC %08x)' % (self.version, base_len, getattr(e, 'got', 0),
                                                               changes.size, changes.crc))
            return self.base
        state = rebuild(self.base.data, changes.runs)
        state_crc = crc(state)
        if len(state) != changes.size or state_crc != changes.crc:
            raise DeltaError('the server\'s changes since version %s rebuild %d bytes (CRC %08x); the server '
                             'says %d bytes (CRC %08x)' % (self.version, len(state), state_crc, changes.size,
                                                           changes.crc))
        return StateBuffer(state, state_crc)

    def _sent(self, buffer, payload, is_delta, version):
        self.base, self.version = buffer, version
        self.sent_bytes += len(payload)
        self.state_bytes += len(buffer)
        return payload, is_delta


class DeltaDecoder(object):
    """Backup side: the whole state of each checkpoint, from a whole state or a delta on the last one.
    The state held is a :class:`StateBuffer`: a delta whose runs keep the length is applied to it in
    place, and :meth:`state` then returns that buffer (its ``bytes()`` is the state)."""

    def __init__(self):
        self.base = None          # StateBuffer

    @property
    def base_crc(self):
        return self.base.crc if self.base is not None else None

    def state(self, payload, is_delta):
        """The whole state a checkpoint carries (bytes, or this decoder's StateBuffer once a delta was
        applied to it in place); DeltaError (base kept) if its delta cannot be applied."""
        if not is_delta:
            return bytes(payload)
        if self.base is None:
            raise DeltaError('a state delta arrived, and this backup holds no state to apply it to')
        new_len, new_crc, runs = _parse(payload, len(self.base), self.base.crc)
        if new_len == len(self.base) and fits_in_place(runs):
            try:
                self.base.replace(runs, new_crc)
            except DeltaError as e:
                raise DeltaError('the state rebuilt from the delta does not match it (the delta says %d bytes, '
                                 'CRC %08x): %s' % (new_len, new_crc, e))
            return self.base
        return _apply(self.base.data, payload, self.base.crc)[0]

    def accept(self, state):
        """The checkpoint carrying ``state`` (whole, or this decoder's buffer) was accepted: the next delta
        applies to it."""
        if state is not self.base:
            self.base = state if isinstance(state, StateBuffer) else StateBuffer(state)
