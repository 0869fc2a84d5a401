"""Checkpointing for Primary-Backup Replication.

Primary side (:class:`CheckpointSender`): after each request, After builds a checkpoint
(the reply and the server's state) and holds the reply until the backup acknowledges
it. A reply therefore never reaches a client before the backup can reproduce it: if
the primary dies at any point, the backup either has the checkpoint (and answers the
re-sent request from its cache) or has not (and executes it, from the same state).

Backup side (:class:`CheckpointReceiver`): acknowledges a checkpoint as soon as it holds it,
and applies it to its server afterwards, off the primary's critical path (every checkpoint
carries the whole state, so applying the newest one is enough; a promotion applies it first).
It accepts checkpoints in sequence order, acknowledges duplicates again without re-applying
them, and refuses a gap (a lost checkpoint makes the backup unusable, so it says so instead of
going on silently). Once promoted it is fenced: a deposed primary's late checkpoints are refused.

With a witness (aft_ftm.witness), every checkpoint and acknowledgment carries the configuration
epoch, and the rules become those of a system that heals:
- The primary never goes on alone by itself: when its backup is lost, slow or refusing, the
  sender asks (``Need.EXCLUDE``) and releases its held replies only once the witness excluded
  the backup (:meth:`CheckpointSender.excluded`). A refusal means it was deposed
  (:meth:`CheckpointSender.depose`): it never releases them, and its replica fail-stops.
- A backup starts empty (JOINING) and follows a primary only from a full checkpoint, a state
  transfer with the replies clients may ask for again (:meth:`CheckpointSender.join`); once it
  acknowledged it, the sender asks the witness to admit it (``Need.ADMIT``). A backup that can no
  longer mirror its primary (a gap, a state its server refused) goes back to JOINING: it re-joins
  instead of being lost for good, and it can never take over in between.
- A checkpoint from an After it does not follow (STRAY) or of an older epoch (STALE) is refused
  and reported, and changes nothing: one stray message cannot disable a backup.
"""
import enum

from .errors import RoleError
from .protocol import Role, check_role_change


class Held(object):
    """The replies of one checkpoint (one, or a group commit's batch), waiting for its acknowledgment."""
    __slots__ = ('seq', 'replies', 'since')

    def __init__(self, seq, replies, since):
        self.seq = seq
        self.replies = replies
        self.since = since


class Need(enum.IntEnum):
    """What the sender needs from the witness before it can go on (false when nothing)."""
    NOTHING = 0
    EXCLUDE = 1     # the backup is lost, slow or refusing: exclude it, then release the held replies
    ADMIT = 2       # a joined backup holds our state: make it the backup of a new epoch


CATCHUP_TIMEOUTS = 10   # a catch-up checkpoint is acknowledged within this many ack timeouts of being sent


class CheckpointSender(object):
    """Primary's After: sequence numbers, replies held until acknowledged, joins."""

    def __init__(self, role, first_seq=1, epoch=0):
        if role not in (Role.PRIMARY, Role.ALONE):
            raise RoleError('a checkpoint sender is PRIMARY or ALONE, not %s' % role.name)
        self.role = role        # changed only by _change_role()
        self.epoch = epoch
        self.first_seq = first_seq   # a replacement After starts above its predecessor's numbers
        self.seq = first_seq - 1
        self.held = {}          # seq -> Held
        self.acked = 0
        self.refused = 0
        self.joiner = None      # the joining After, while its state transfer is not acknowledged
        self.join_seq = None    # the seq of that state transfer (a full checkpoint)
        self.join_since = None
        self.admitted = role == Role.PRIMARY   # the witness knows our backup (always true without one)
        self.deposed = None     # why the witness refused us: nothing is ever released again
        self.session = first_seq   # acks of checkpoints below this were for an earlier backup: ignored
        # A join with catch-up: until the joiner holds the state transfer, the replies are released at once (as
        # ALONE: the witness does not count on the joiner yet) and their checkpoints (seq -> when sent) are
        # only to be acknowledged before the joiner is admitted.
        self.catching_up = False
        self.catchup = {}
        self.catchup_sent = {}   # seq -> when sent: acks of the others refresh ``catchup``, never this
    def _change_role(self, role):
        """The one place where the sender's role changes (RoleError unless an allowed edge)."""
        check_role_change(self.role, role)
        self.role = role

    def needs_checkpoint(self):
        return self.role == Role.PRIMARY and not self.deposed

    def hold(self, reply, now, batch=()):
        """Register a checkpoint for reply, and for the replies of its batch before it (group commit);
        returns its sequence number. They are released together, in order, once it is acknowledged;
        while a joiner catches up (:meth:`releases_at_once`), the caller releases them at once."""
        self.seq += 1
        if self.catching_up:
            self.catchup[self.seq] = self.catchup_sent[self.seq] = now
        else:
            self.held[self.seq] = Held(self.seq, list(batch) + ([reply] if reply is not None else []), now)
        return self.seq

    def releases_at_once(self, seq):
        """Checkpoint seq holds nothing: its replies go to the clients now (a joiner catching up)."""
        return seq in self.catchup

    def join(self, joiner, now, catch_up=False):
        """A backup asks for a state transfer: returns the seq of the full checkpoint to send it.

        From now on every reply is held until the joiner acknowledges it, so that whatever is
        released, the joiner holds; it becomes the backup once the witness admits it (Need.ADMIT).
        With ``catch_up``, the replies are held only once the joiner acknowledged the state transfer
        (until then they go at once, as ALONE: clients do not wait for a long transfer), and the joiner is
        admitted once it acknowledged every checkpoint sent meanwhile too: whatever is released after
        the admission, the joiner holds, as without catch-up."""
        if self.deposed:
            raise RoleError('deposed: %s' % self.deposed)
        self._change_role(Role.PRIMARY)
        self.admitted = False
        self.joiner = joiner
        self.seq += 1
        self.join_seq = self.session = self.seq
        self.join_since = now
        self.catching_up, self.catchup, self.catchup_sent = catch_up, {}, {}
        return self.seq

    def ready_to_admit(self):
        """The joiner holds the state transfer and every checkpoint sent while it caught up: ask the witness."""
        return self.role == Role.PRIMARY and not self.admitted and not self.deposed and self.joiner is not None \
            and self.join_seq is None and not self.catchup

    def progress(self, seq, now):
        """The joiner acknowledged a part of the state transfer ``seq`` (aft_ftm.transfer): the transfer
        moves, so its ack timeout, and that of the checkpoints queued behind it, count from now.
        Returns False (nothing changed) if ``seq`` is not the transfer under way."""
        if self.deposed or seq != self.join_seq:
            return False
        self.join_since = now
        for held in self.held.values():
            held.since = now
        for queued in self.catchup:
            # Queued behind the parts, they are not sent yet: their bound counts from when they can be
            # (a transfer longer than CATCHUP_TIMEOUTS ack timeouts excluded a joiner acknowledging every
            # part on time: review of group commit, session 33).
            self.catchup[queued] = self.catchup_sent[queued] = now
        return True

    def on_ack(self, seq, ok, now=None):
        """The backup answered checkpoint seq (at ``now``, None: not told). Returns (released replies, Need).
        A catch-up checkpoint acknowledged is progress, as a part is (:meth:`progress`): the ones still
        queued count their ack timeout from now. Before, they counted from the last part's ack, and a
        joiner acknowledging a steady stream of them was excluded for silence (review of stop 39)."""
        if self.deposed or self.role != Role.PRIMARY or seq < self.session:
            return [], Need.NOTHING   # a late answer of a backup excluded since: says nothing of this one
        if seq == self.join_seq:
            self.join_seq = self.join_since = None
            self.catching_up = False   # the joiner holds the state: from now on every reply waits for it
            if ok:
                return [], Need.ADMIT if not self.catchup else Need.NOTHING
            self.refused += 1
            return [], Need.EXCLUDE
        if seq in self.catchup:
            del self.catchup[seq]
            self.catchup_sent.pop(seq, None)
            if not ok:
                self.refused += 1
                return [], Need.EXCLUDE
            if now is not None:
                for queued in self.catchup:
                    self.catchup[queued] = now
            return [], Need.ADMIT if self.ready_to_admit() else Need.NOTHING
        held = self.held.pop(seq, None)
        if held is None:
            if ok:
                return [], Need.NOTHING     # duplicate or late ack
            # The backup failed to apply a checkpoint it had acknowledged: it is no longer valid.
            self.refused += 1
            return [], Need.EXCLUDE
        if ok:
            self.acked += 1
            return list(held.replies), Need.NOTHING
        # The backup could not apply it: it no longer mirrors us. Exclude it before going on.
        self.refused += 1
        self.held[seq] = held
        return [], Need.EXCLUDE

    def admit(self, epoch):
        """The witness made the joiner our backup in ``epoch``."""
        self.admitted = True
        self.joiner = None
        self.catching_up = False
        self.epoch = max(self.epoch, epoch)

    def excluded(self, epoch):
        """The witness excluded the backup (or there was none): release every held reply, in order,
        and send no more checkpoints."""
        if self.deposed:
            return []
        self.epoch = max(self.epoch, epoch)
        return self.go_alone()

    def go_alone(self):
        """The backup is gone: release every held reply, send no more checkpoints."""
        self._change_role(Role.ALONE)
        self.joiner = self.join_seq = self.join_since = None
        self.catching_up, self.catchup, self.catchup_sent = False, {}, {}
        released = [r for s in sorted(self.held) for r in self.held[s].replies]
        self.held.clear()
        return released

    def depose(self, reason):
        """The witness refused us: another site serves. Returns how many replies are withheld for good."""
        self.deposed = reason
        return len(self.held)

    def overdue(self, now, timeout):
        """True if some reply (or a state transfer) has waited for its acknowledgment longer than timeout."""
        if self.deposed:
            return False
        if self.join_since is not None and now - self.join_since > timeout:
            return True
        # A joiner acknowledging more slowly than checkpoints are made never catches up: each catch-up
        # checkpoint must be acknowledged within CATCHUP_TIMEOUTS ack timeouts of being sent.
        return any(now - h.since > timeout for h in self.held.values()) or \
            any(now - since > timeout for since in self.catchup.values()) or \
            any(now - sent > CATCHUP_TIMEOUTS * timeout for sent in self.catchup_sent.values())


class AdmissionGate(object):
    """A joiner is given the state, and admitted, only while its site runs, as this site's crash
    detector hears it (its beats within its timeout). A site stopping (its server died, its detector
    announced its fail-stop) may still have an After that joins: admitted, it was watched afresh and
    declared failed a timeout later, again and again (a campaign: 3 times in 1 s, each an exclusion, an
    admission and a false suspicion). A site just started may not be heard yet, so the gate waits up to
    ``patience`` seconds of that joiner's asking before it gives the join up (the joiner asks again)."""

    def __init__(self, patience):
        self.patience = patience
        self.waiting = None   # (joiner, since, last asked): the joiner unheard

    def decide(self, joiner, unheard, now):
        """(admit, give_up): ``unheard`` is why the joiner's site is not heard now (None: heard, or not
        known). Go on if heard; wait (False, None) while unheard for less than ``patience``; then
        give the join up (False, why). A wait not asked about for ``patience`` starts afresh."""
        if not unheard:
            self.waiting = None
            return True, None
        if self.waiting is None or self.waiting[0] != joiner or now - self.waiting[2] > self.patience:
            self.waiting = (joiner, now, now)
        since = self.waiting[1]
        self.waiting = (joiner, since, now)
        if now - since < self.patience:
            return False, None
        self.waiting = None
        return False, '%s (for %.1f s)' % (unheard, now - since)


class UncheckedAdmission(object):
    """A joiner admitted although this site's crash detector could not say whether it hears the joiner's
    site (the detector frozen, hung or watching another site): the gate fails open, as before it
    existed, and that is said once per joiner within ``every`` seconds (a joiner re-asks every 0.5 s)."""

    def __init__(self, tell, every=10.0):
        self.tell = tell
        self.every = every
        self.last = {}   # joiner -> when it was last said

    def say(self, joiner, why, now):
        if now - self.last.get(joiner, float('-inf')) < self.every:
            return False
        self.last[joiner] = now
        self.tell('%s is let join without its site being checked as heard: %s; a site that no longer runs may '
                  'be admitted and then declared failed' % (joiner, why))
        return True


class BatchError(Exception):
    """The replies of a batch did not come as the Protocol numbered them (one lost or out of order)."""


class GroupCommit(object):
    """Primary's After, group commit: gathers the replies of one batch (aft_ftm.protocol) until its last,
    so that one state captured then, with the Protocol forwarding nothing meanwhile, covers them all.

    ``add(reply)`` returns the replies to checkpoint together, in order, once the batch is complete (at
    once for a reply outside any batch: ``batch`` 0), and None while more of it are executing. The
    replies of a batch come as the Protocol numbered them, (n, n), (n-1, n), ..., (1, n) (one pipeline, one
    connection per hop, so in order): anything else (one lost, the first included) raises BatchError, and the caller must fail-stop, since a state
    captured then could hold a request whose reply it does not carry.
    """

    def __init__(self):
        self.replies = []       # the batch so far (its last not there yet)
        self.since = None       # when its latest reply came (the clock the caller passes)

    def stalled(self, now, gap):
        """Why the batch gathered is broken, if no reply of it came for longer than ``gap`` seconds
        (its requests run one after the other, each bounded by the server timeout: a later one lost in
        the pipeline, the last included, would otherwise hold the Protocol for max_batch times its
        processing timeout, minutes, with no alarm), else None. The caller must fail-stop, as for a
        BatchError."""
        if not self.replies or self.since is None or now - self.since <= gap:
            return None
        last = self.replies[-1]
        return 'no reply of the batch for %.1f s after %s/%d with %d of %d left: the rest never came' % (
            now - self.since, last.origin, last.id, last.batch[0], last.batch[1])

    def add(self, reply, now=None):
        self.since = now
        left, size = tuple(getattr(reply, 'batch', None) or (0, 0))
        if left == 0:
            if self.replies and not is_refusal(reply):
                raise BatchError('%s/%d was executed outside its batch while %d replies of a batch wait for '
                                 'its last' % (reply.origin, reply.id, len(self.replies)))
            return [reply]   # a Protocol's own refusal (never forwarded) may come in the middle of a batch
        if not self.replies and left != size:
            raise BatchError('%s/%d came with %d of its batch of %d left: the first %d never came' % (
                reply.origin, reply.id, left, size, size - left))
        if self.replies and tuple(self.replies[-1].batch) != (left + 1, size):
            before = self.replies[-1]
            raise BatchError('%s/%d came with %d of its batch of %d left after %s/%d with %d of %d left' % (
                reply.origin, reply.id, left, size, before.origin, before.id, before.batch[0], before.batch[1]))
        self.replies.append(reply)
        if left > 1:
            return None
        replies, self.replies = self.replies, []
        return replies

    def flush(self):
        """The replies gathered so far (the batch is released without a checkpoint: no backup any more)."""
        replies, self.replies = self.replies, []
        return replies


def is_refusal(reply):
    """A reply that changed nothing (aft_msgs/Reply NOT_EXECUTED): its checkpoint carries no state."""
    return getattr(reply, 'status', 0) == NOT_EXECUTED


NOT_EXECUTED = 2   # aft_msgs/Reply.NOT_EXECUTED (this module does not import the messages)


class Decision(enum.Enum):
    APPLY = 0       # new, in order: acknowledge, store the reply, apply the state
    REACK = 1       # already applied: acknowledge again, change nothing
    GAP = 2         # a checkpoint is missing: refuse, the backup no longer mirrors its primary
    FENCED = 3      # we are no longer a backup: refuse
    APPLY_FULL = 4  # a state transfer: start (again) following the sender here
    STRAY = 5       # from an After this backup does not follow: refuse, report, change nothing
    STALE = 6       # of an epoch older than this backup's: a deposed primary; refuse, report, change nothing
    JOINING = 7     # no state yet and not a state transfer: refuse (its sender must not count on us)


# Decisions that refuse a checkpoint without saying anything about this backup's own state.
HARMLESS = (Decision.STRAY, Decision.STALE)


class Follow(enum.Enum):
    """Where a backup After is in its life."""
    JOINING = 0     # holds no state of any primary: asks for a state transfer
    FOLLOWING = 1   # mirrors ``sender``: may take over
    PROMOTED = 2    # took over: fenced against every primary's checkpoints


FOLLOW_EDGES = {
    (Follow.JOINING, Follow.FOLLOWING): 'a state transfer (or, without joins, the first checkpoint) arrived',
    (Follow.FOLLOWING, Follow.JOINING): 'a gap or a refused state: it must be transferred again',
    (Follow.FOLLOWING, Follow.PROMOTED): 'the primary failed: this backup takes over',
    (Follow.JOINING, Follow.PROMOTED): 'the witness made this site the first primary: it serves its own state',
}


class CheckpointReceiver(object):
    """Backup's After: ordering, duplicates, joins and fencing of a deposed primary.

    ``join`` False is the first-start mode of a deployment without a witness (and of the car's
    boards): the backup follows its sender from the sender's first checkpoint, and a backup that
    lost a checkpoint is invalid for good.
    """

    def __init__(self, join=False, epoch=0):
        self.role = Role.BACKUP     # changed only by promote()
        self.join = join
        self.state = Follow.JOINING
        self.epoch = epoch
        self.last_seq = 0
        self.sender = None
        self.first_seq = 0      # the first checkpoint number the sender followed said (0: not said)
        self.invalid = 'holds no state yet' if join else None   # why it cannot take over, while it cannot
        self.expect = ''        # join: a state transfer is accepted from an After whose name starts so

    def in_sync(self):
        """This backup starts beside a primary that starts too, both from the same state (an
        adaptation replaced both Afters while the pair was quiescent): it follows that primary from its
        first checkpoint, without a state transfer."""
        self._change(Follow.FOLLOWING)

    def _change(self, new, why=None):
        if new != self.state and (self.state, new) not in FOLLOW_EDGES:
            raise RoleError('backup %s -> %s is not allowed' % (self.state.name, new.name))
        self.state = new
        if new == Follow.JOINING:
            self.invalid = why or 'holds no state yet'
        elif new == Follow.FOLLOWING:
            self.invalid = None

    def decide(self, seq, sender, first_seq=1, replaces='', epoch=0, full=False):
        """What to do with checkpoint seq of sender (whose first checkpoint is first_seq, which
        declares that it replaces After ``replaces``, if it does, in configuration ``epoch``)."""
        if self.role != Role.BACKUP or self.state == Follow.PROMOTED:
            return Decision.FENCED
        if epoch and epoch < self.epoch:
            return Decision.STALE
        if self.join:
            if full and (not self.expect or sender.startswith(self.expect)) and (
                    self.state == Follow.JOINING or sender == self.sender and seq > self.last_seq):
                return Decision.APPLY_FULL
            if self.state == Follow.JOINING:
                return Decision.JOINING if not self.expect or sender.startswith(self.expect) else Decision.STRAY
        elif self.invalid and self.sender is not None:
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
            return Decision.STRAY if self.join else Decision.FENCED
        if self.first_seq and first_seq and first_seq != self.first_seq:
            # The same After started again, numbering from a clock stepped back below the numbers
            # followed: acknowledged as a copy, its checkpoint was neither stored nor applied, and the
            # primary released replies this backup never held. It cannot be followed.
            return Decision.GAP
        if seq <= self.last_seq:
            return Decision.REACK
        if seq != self.last_seq + 1:
            return Decision.GAP
        return Decision.APPLY

    def accept(self, seq, sender, epoch=0, first_seq=0):
        """Checkpoint seq is held (its reply stored, its state to be applied); ``first_seq``: the first
        number its sender said it numbers from."""
        if self.state == Follow.JOINING:
            self._change(Follow.FOLLOWING)
        if sender != self.sender or first_seq:
            self.first_seq = first_seq
        self.last_seq = seq
        self.sender = sender
        self.epoch = max(self.epoch, epoch)

    def failed(self, seq, reason):
        """Checkpoint seq could not be applied (or one is missing): this backup no longer mirrors its
        primary. With joins it asks for a state transfer again; without, it is invalid for good."""
        why = 'checkpoint %d could not be applied: %s' % (seq, reason)
        if self.join and self.state == Follow.FOLLOWING:
            self._change(Follow.JOINING, why)
            self.sender = None
            self.last_seq = 0
        else:
            self.invalid = self.invalid or why

    def promote(self, initial=False):
        """Stop accepting checkpoints; returns the last accepted sequence number.

        Raises RoleError if this backup holds no valid state (unless ``initial``: the witness made
        this site the first primary, which serves from its own server's state).
        """
        if self.invalid and not (initial and self.state == Follow.JOINING):
            raise RoleError('this backup cannot take over: %s' % self.invalid)
        check_role_change(self.role, Role.ALONE)
        self._change(Follow.PROMOTED)
        self.role = Role.ALONE      # the receiver's one role change, checked above
        return self.last_seq
