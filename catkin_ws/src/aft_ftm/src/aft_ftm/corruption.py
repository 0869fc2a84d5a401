"""Software fault injection: corrupt the values in a ROS message (bit flip, offset, stuck value).

Works on any generated message by introspection of its fields: numeric fields (integers and
floats, in nested messages and fixed-size positions too) are the targets.
"""
import copy
import random
import struct

from .errors import ConfigError

MODES = ('bitflip', 'offset', 'stuck')
_INT_BITS = {'int8': 8, 'uint8': 8, 'byte': 8, 'char': 8, 'int16': 16, 'uint16': 16, 'int32': 32,
             'uint32': 32, 'int64': 64, 'uint64': 64}
_FLOATS = ('float32', 'float64')


def numeric_fields(msg, prefix=()):
    """Paths (tuples of field names) of the scalar numeric fields of a generated message."""
    paths = []
    for name, slot_type in zip(getattr(msg, '__slots__', ()), getattr(msg, '_slot_types', ())):
        if slot_type in _INT_BITS or slot_type in _FLOATS:
            paths.append((prefix + (name,), slot_type))
        elif '/' in slot_type and '[' not in slot_type:
            paths.extend(numeric_fields(getattr(msg, name), prefix + (name,)))
    return paths


def _get(msg, path):
    for name in path:
        msg = getattr(msg, name)
    return msg


def _set(msg, path, value):
    for name in path[:-1]:
        msg = getattr(msg, name)
    setattr(msg, path[-1], value)


def flip_bit(value, slot_type, bit):
    """value with one bit flipped (bit counted in the field's own width)."""
    if slot_type in _FLOATS:
        fmt, width = ('<d', 64) if slot_type == 'float64' else ('<f', 32)
        (raw,) = struct.unpack('<Q' if width == 64 else '<I', struct.pack(fmt, value))
        raw ^= 1 << (bit % width)
        (flipped,) = struct.unpack(fmt, struct.pack('<Q' if width == 64 else '<I', raw))
        return flipped
    width = _INT_BITS[slot_type]
    unsigned = slot_type.startswith('u') or slot_type in ('byte', 'char')
    raw = (value & ((1 << width) - 1)) ^ (1 << (bit % width))
    if not unsigned and raw >= 1 << (width - 1):
        raw -= 1 << width
    return raw


class Corruptor(object):
    """Decides which results to corrupt (probability, or the next ``count`` on command) and how."""

    def __init__(self, mode='bitflip', probability=0.0, magnitude=1.0, seed=None):
        self.mode = self._mode(mode)
        if not 0.0 <= probability <= 1.0:
            raise ConfigError('fault probability must be within [0, 1], got %r' % (probability,))
        self.probability = probability
        self.magnitude = magnitude
        self.rng = random.Random(seed)
        self.armed = []           # modes of the next results to corrupt, on command
        self.last = None          # the last result relayed (for stuck)
        self.injected = 0

    @staticmethod
    def _mode(mode):
        if mode not in MODES:
            raise ConfigError('fault mode must be one of %s, got %r' % (', '.join(MODES), mode))
        return mode

    def arm(self, count, mode='', magnitude=None, field=''):
        """Corrupt the next count results (with mode, or the configured one; in field, or one at random)."""
        mode = self._mode(mode) if mode else self.mode
        self.armed.extend([(mode, magnitude if magnitude is not None else self.magnitude, field)] * count)

    def relay(self, result):
        """The result to pass on: result itself, or a corrupted copy. Never modifies result."""
        if self.armed:
            mode, magnitude, field = self.armed.pop(0)
        elif self.probability and self.rng.random() < self.probability:
            mode, magnitude, field = self.mode, self.magnitude, ''
        else:
            self.last = result
            return result
        corrupted = self.corrupt(result, mode, magnitude, field)
        self.injected += 1
        self.last = result
        return corrupted

    def corrupt(self, result, mode, magnitude, field=''):
        if mode == 'stuck':
            return copy.deepcopy(self.last) if self.last is not None else copy.deepcopy(result)
        fields = numeric_fields(result)
        if field:
            fields = [(p, t) for p, t in fields if '.'.join(p) == field]
            if not fields:
                raise ConfigError('%s has no numeric field %r (it has: %s)' % (
                    type(result).__name__, field, ', '.join('.'.join(p) for p, _ in numeric_fields(result))))
        if not fields:
            raise ConfigError('%s has no numeric field to corrupt' % type(result).__name__)
        corrupted = copy.deepcopy(result)
        path, slot_type = self.rng.choice(fields)
        value = _get(corrupted, path)
        if mode == 'bitflip':
            width = 64 if slot_type == 'float64' else 32 if slot_type == 'float32' else _INT_BITS[slot_type]
            bit = self.rng.randrange(width - 1 if slot_type not in _FLOATS else 52 if width == 64 else 23)
            new = flip_bit(value, slot_type, bit)
        elif slot_type in _FLOATS:
            new = value + magnitude
        else:
            new = value + (int(round(magnitude)) or 1)   # an integer offset is never zero
            if new < 0 and (slot_type.startswith('u') or slot_type in ('byte', 'char')):
                new = value + abs(int(round(magnitude)) or 1)
        _set(corrupted, path, new)
        return corrupted
