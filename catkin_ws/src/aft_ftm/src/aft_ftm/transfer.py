"""A state transfer in parts, with back-pressure (PBR's re-integration, issue 18).

A join's state transfer is one full aft_msgs/Checkpoint. With a large state that is one message of
the whole state: the primary's ack timeout then has to cover the whole transfer (a 10 MB state on a
slow link is excluded long before it arrives), and nothing bounds what is in flight. Here the state
goes in parts of at most ``chunk_bytes`` (:func:`split`), numbered 0 .. parts - 1, at most
``window`` of them sent and not yet acknowledged (:class:`Outgoing`): the sender sends the next
part only once the backup acknowledged an earlier one, and each acknowledgment is progress, so the
ack timeout counts from the last part acknowledged, not from the start of the transfer. The last
part carries the replies of the transfer (the cache) and is acknowledged as the whole checkpoint.

The backup assembles the parts in order (:class:`Incoming`): a part already held is acknowledged
again and changes nothing; a part out of order (one lost, or one from another transfer in the
middle of this one) raises :class:`TransferError`, and the backup refuses the transfer (it asks for
another). Nothing is applied before the last part: a backup holds a transfer whole or not at all.

Plain Python, no ROS: the state is any sequence (bytes on ROS, the simulation's tuples).
"""
import itertools


class TransferError(Exception):
    """The parts of a state transfer did not come in order: the transfer is refused."""


def split(data, chunk_bytes):
    """``data`` cut into parts of at most ``chunk_bytes`` items (0: one part); always at least one part."""
    if chunk_bytes <= 0 or len(data) <= chunk_bytes:
        return [data]
    return [data[i:i + chunk_bytes] for i in range(0, len(data), chunk_bytes)]


def join(parts):
    """The parts put back together, of the type they came in."""
    if not parts:
        raise TransferError('no part to assemble')
    if isinstance(parts[0], (bytes, bytearray)):
        return b''.join(bytes(p) for p in parts)
    return type(parts[0])(itertools.chain.from_iterable(parts))


class Outgoing(object):
    """Primary's After: the parts of one state transfer and which of them may go now.

    ``next_parts()`` returns the indexes to send now (each once), never more than ``window`` beyond
    the parts acknowledged; ``acknowledged(part)`` records that the backup holds parts 0..part.
    """

    def __init__(self, seq, data, chunk_bytes, window):
        if window < 1:
            raise ValueError('a transfer window holds at least one part, not %d' % window)
        self.seq = seq
        self.parts = split(data, chunk_bytes)
        self.window = window
        self.sent = 0        # parts 0 .. sent - 1 were handed out
        self.held = 0        # parts 0 .. held - 1 are acknowledged

    @property
    def count(self):
        return len(self.parts)

    def all_sent(self):
        return self.sent == self.count

    def next_parts(self):
        upto = min(self.count, self.held + self.window)
        due = list(range(self.sent, upto))
        self.sent = max(self.sent, upto)
        return due

    def acknowledged(self, part):
        """The backup holds every part up to ``part``. Returns True if that is news (progress)."""
        if part >= self.sent:
            raise TransferError('part %d of transfer %d acknowledged, but only %d of %d were sent'
                                % (part, self.seq, self.sent, self.count))
        if part < self.held:
            return False
        self.held = part + 1
        return True


class Incoming(object):
    """Backup's After: the parts of the state transfer being received, assembled in order.

    ``add`` returns None while parts are missing (acknowledge the part), the whole state once the
    last part came (apply the transfer), and raises TransferError for a part out of order.
    ``duplicate`` tells whether a part is one already held (acknowledge it again, change nothing).
    """

    def __init__(self):
        self.key = None      # (sender, seq, parts) of the transfer being assembled
        self.parts = []

    def holding(self):
        return self.key is not None

    def duplicate(self, sender, seq, part, parts):
        return self.key == (sender, seq, parts) and part < len(self.parts)

    def add(self, sender, seq, part, parts, data):
        if parts < 2 or not 0 <= part < parts:
            raise TransferError('part %d of %d is not a part of a transfer in parts' % (part, parts))
        if part == 0:
            self.key, self.parts = (sender, seq, parts), []   # a new transfer replaces one not finished
        elif self.key != (sender, seq, parts):
            expected = 'no transfer is being received' if self.key is None else \
                'transfer %d of %s in %d parts is being received' % (self.key[1], self.key[0], self.key[2])
            self.abandon()
            raise TransferError('part %d of transfer %d of %s in %d parts: %s' % (part, seq, sender, parts, expected))
        elif part != len(self.parts):
            held = len(self.parts)
            self.abandon()
            raise TransferError('part %d of transfer %d of %s came after part %d: one is missing'
                                % (part, seq, sender, held - 1))
        self.parts.append(data)
        if len(self.parts) < parts:
            return None
        whole = join(self.parts)
        self.abandon()
        return whole

    def receive(self, sender, seq, part, parts, data):
        """One part: returns the whole state once the last part came, else None (acknowledge the part; a
        part already held changes nothing). Raises TransferError for a part out of order."""
        if self.duplicate(sender, seq, part, parts):
            return None
        return self.add(sender, seq, part, parts, data)

    def take(self, cp):
        """A checkpoint ``cp`` (sender, seq, part, parts, state) of a transfer in parts: returns (whole, refusal):
        the whole state once its last part came (else None: acknowledge the part), and why the transfer
        is refused ('' unless a part came out of order)."""
        try:
            return self.receive(cp.sender, cp.seq, cp.part, cp.parts, cp.state), ''
        except TransferError as e:
            return None, 'state transfer %d from %s refused: %s' % (cp.seq, cp.sender, e)

    def abandon(self):
        """Forget the transfer being assembled (refused, or this backup stops following)."""
        self.key, self.parts = None, []
