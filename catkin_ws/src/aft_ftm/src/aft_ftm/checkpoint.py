"""Checkpointing for Primary-Backup Replication.

Primary side (:class:`CheckpointSender`): after each request, After builds a checkpoint
(the reply and the server's state) and holds the reply until the backup acknowledges
it. A reply therefore never reaches a client before the backup can reproduce it: if
the primary dies at any point, the backup either has the checkpoint (and answers the
re-sent request from its cache) or has not (and executes it, from the same state).

Backup side (:class:`CheckpointReceiver`): acknowledges a checkpoint as soon as it holds it,
and applies it to its server afterwards, off the primary's critical path (every checkpoint
carries the whole state, so applying the newest one is enough; a promotion applies it first).
A backup whose setState fails is invalid: it says so to the primary (which goes on alone) and
refuses to take over, so that it never serves from a wrong state. It accepts checkpoints in
sequence order,
acknowledges duplicates again without re-applying them, refuses a gap (a lost
checkpoint makes the backup unusable, so it says so instead of going on silently), and
is fenced once promoted: a deposed primary's late checkpoints are refused.
"""
import enum

from .errors import RoleError
from .protocol import Role, check_role_change


class Held(object):
    """A reply waiting for the backup's acknowledgment."""
    __slots__ = ('seq', 'reply', 'since')

    def __init__(self, seq, reply, since):
        self.seq = seq
        self.reply = reply
        self.since = since


class CheckpointSender(object):
    """Primary's After: sequence numbers and replies held until acknowledged."""

    def __init__(self, role, first_seq=1):
        if role not in (Role.PRIMARY, Role.ALONE):
            raise RoleError('a checkpoint sender is PRIMARY or ALONE, not %s' % role.name)
        self.role = role
        self.first_seq = first_seq   # a replacement After starts above its predecessor's numbers
        self.seq = first_seq - 1
        self.held = {}          # seq -> Held
        self.acked = 0
        self.refused = 0

    def needs_checkpoint(self):
        return self.role == Role.PRIMARY

    def hold(self, reply, now):
        """Register a checkpoint for reply; returns its sequence number."""
        self.seq += 1
        self.held[self.seq] = Held(self.seq, reply, now)
        return self.seq

    def on_ack(self, seq, ok):
        """The backup answered checkpoint seq. Returns (released replies, backup_lost)."""
        held = self.held.pop(seq, None)
        if held is None:
            if ok:
                return [], False        # duplicate or late ack
            # The backup failed to apply a checkpoint it had acknowledged: it is no longer valid.
            self.refused += 1
            return self.go_alone(), True
        if ok:
            self.acked += 1
            return [held.reply], False
        # The backup could not apply it: it no longer mirrors us. Release and go alone.
        self.refused += 1
        self.held[seq] = held
        return self.go_alone(), True

    def go_alone(self):
        """The backup is gone: release every held reply, send no more checkpoints."""
        check_role_change(self.role, Role.ALONE)
        self.role = Role.ALONE
        released = [self.held[s].reply for s in sorted(self.held)]
        self.held.clear()
        return released

    def overdue(self, now, timeout):
        """True if some reply has waited for its acknowledgment longer than timeout."""
        return any(now - h.since > timeout for h in self.held.values())


class Decision(enum.Enum):
    APPLY = 0       # new, in order: acknowledge, store the reply, apply the state
    REACK = 1       # already applied: acknowledge again, change nothing
    GAP = 2         # a checkpoint is missing: refuse, the backup is no longer consistent
    FENCED = 3      # we are no longer a backup: refuse


class CheckpointReceiver(object):
    """Backup's After: ordering, duplicates, and fencing of a deposed primary."""

    def __init__(self):
        self.role = Role.BACKUP
        self.last_seq = 0
        self.sender = None
        self.invalid = None     # why this backup can no longer take over, once it cannot

    def decide(self, seq, sender, first_seq=1, replaces=''):
        """What to do with checkpoint seq of sender (whose first checkpoint is first_seq, and
        which declares that it replaces After ``replaces``, if it does)."""
        if self.role != Role.BACKUP or self.invalid:
            return Decision.FENCED
        if self.sender is None:
            # Nothing followed yet: start at the sender's first checkpoint, never in the middle.
            return Decision.APPLY if seq == first_seq else Decision.GAP
        if replaces and replaces == self.sender and seq == first_seq and seq > self.last_seq:
            # The After an adaptation put in place of the one followed, from its first checkpoint.
            return Decision.APPLY
        if sender == self.sender and seq == first_seq and seq > self.last_seq:
            # The same After started again (a rollback respawned it): it numbers from the clock.
            return Decision.APPLY
        if sender != self.sender:
            return Decision.FENCED
        if seq <= self.last_seq:
            return Decision.REACK
        if seq != self.last_seq + 1:
            return Decision.GAP
        return Decision.APPLY

    def accept(self, seq, sender):
        """Checkpoint seq is held (its reply stored, its state to be applied)."""
        self.last_seq = seq
        self.sender = sender

    def failed(self, seq, reason):
        """Checkpoint seq could not be applied: this backup is invalid for good."""
        self.invalid = 'checkpoint %d could not be applied: %s' % (seq, reason)

    def promote(self):
        """Stop accepting checkpoints; returns the last accepted sequence number.

        Raises RoleError if this backup is invalid (a checkpoint could not be applied).
        """
        if self.invalid:
            raise RoleError('this backup cannot take over: %s' % self.invalid)
        check_role_change(self.role, Role.ALONE)
        self.role = Role.ALONE
        return self.last_seq
