"""The logic of PBR's After for a publish/subscribe node (:mod:`aft_ftm.ros.cycle_nodes`), without rospy.

Every checkpoint of a pub/sub node carries the node's whole state after one cycle, so every one
is a state transfer (``full``): a backup follows its primary from whichever checkpoint reaches it
first, a backup that starts while the primary runs follows from the next cycle end, and a lost
checkpoint costs nothing once the next one arrives.

The replica's role (:data:`aft_ftm.protocol.ROLE_EDGES`) lives in its CheckpointSender (PRIMARY,
ALONE) or, for a backup, its CheckpointReceiver (BACKUP, then ALONE once promoted, which then takes
a sender of its own); they guard every change.

- PRIMARY checkpoints each cycle's state. A checkpoint refused, or not acknowledged within
  ``ack_timeout``, means the backup is lost: ALONE, reported (``backup_lost``). Outputs are never
  held (a control loop cannot wait), so nothing else changes.
- ALONE sends no checkpoint. A join request (a backup that started, came back after a power loss,
  or no longer mirrors it) makes it PRIMARY again at the next cycle end ('a backup joined'), and
  that cycle's checkpoint is the joiner's state transfer. The joiner is its backup once it
  acknowledged it. A PRIMARY asked to join by its own backup first goes ALONE: that backup no
  longer mirrors it, and the checkpoints it never answered must not count against the joiner.
- BACKUP follows its primary: a CheckpointReceiver with joins, taking state transfers only from
  an After whose name starts with ``expect``. While it holds no state (JOINING) it asks to join
  every ``join_period`` and can never take over. A FOLLOWING backup whose own node ran
  ``stale_cycles`` cycles over at least ``stale_after`` seconds without a checkpoint no longer
  mirrors its primary (which went on alone): it goes back to JOINING, reported
  (``backup_invalid``), and asks again. So does one whose node refused a state.
- ``set_role`` ALONE (the watchdog, at failover): a following backup takes over, and may take a
  backup of its own later; a JOINING one refuses (it holds no state). PRIMARY is never asked for:
  a replica becomes primary again when a backup joins it.
- A node that hangs (``cycle_timeout`` > 0: no cycle end for that long on the node's own clock, and
  for ``HANG_WALL_MIN`` on the wall clock, once it has ended one; a SIGSTOP, a deadlock): its
  process lives on and its board's crash detector beats on, so no watchdog would ever see it. A
  PRIMARY's After whose backup acknowledged every checkpoint fail-stops its site (``fail_stop``:
  its crash detector falls silent, the watchdog fences the board and promotes the backup) and
  passes nothing on from then on; one whose backup may be lost, or an ALONE one, raises
  ``node_hung`` (nobody can take over: the outputs stop until the node resumes); a following
  BACKUP no longer mirrors its primary (``backup_invalid``: it must not be promoted with a node
  that runs nothing; a state its node takes once resumed, decided before, is refused). The node's
  clock (simulated time) is used so that a stopped simulator, which stops every node's cycles, is
  not taken for a hang; time the After's inputs are held by a suspension is not counted. With the
  watch on, a backup goes stale only after twice ``cycle_timeout`` of its node's clock as well:
  a hung primary is failed over before that, at any simulation rate.

Invariants: a backup passes no output on; only a backup that applied a checkpoint of its primary
takes over; every change that leaves the pair without a valid backup is a Note with ``alarm``.
``now`` is always passed in (seconds, one monotonic clock).
"""
import collections

from .checkpoint import CheckpointReceiver, CheckpointSender, Decision, Follow, Need
from .errors import RoleError
from .primary_word import PrimaryWord, Word
from .protocol import Role, check_role_change


class Note(object):
    """Something to report: always logged, and raised as an alarm (mechanism ``pbr``) if ``alarm``."""
    __slots__ = ('kind', 'detail', 'alarm')

    def __init__(self, kind, detail, alarm=False):
        self.kind = kind
        self.detail = detail
        self.alarm = alarm

    def __repr__(self):
        return 'Note(%s%s: %s)' % (self.kind, ', alarm' if self.alarm else '', self.detail)


# A hang must also last this long on the wall clock (s): a simulation at 20 times real time makes 0.5 s
# of its time 25 ms of scheduling.
HANG_WALL_MIN = 0.1

# Why a backup refuses a state its node took after the backup stopped mirroring.
STALE_STATE = 'its node took this state only after the backup stopped mirroring its primary (it hung meanwhile)'

# A checkpoint to send: always a state transfer (full), of the sender numbered from first_seq.
Outgoing = collections.namedtuple('Outgoing', 'seq first_seq state')


class CycleReplica(object):
    """One replica's After of a pub/sub node (see the module's docstring)."""

    def __init__(self, name, role, first_seq, expect='', ack_timeout=0.5, join_period=0.25,
                 stale_after=1.0, stale_cycles=3, cycle_timeout=0.0):
        for what, value in (('ack_timeout', ack_timeout), ('join_period', join_period),
                            ('stale_after', stale_after), ('stale_cycles', stale_cycles),
                            ('cycle_timeout', cycle_timeout or 1)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise ValueError('%s must be a number > 0, got %r' % (what, value))
        self.cycle_timeout = cycle_timeout   # 0: a hung node is not watched
        self.node_cycle_at = None   # the node's clock at its last cycle end (None: none yet)
        self.node_cycle_wall = None  # when this replica heard it (monotonic)
        self.follow_round = 0       # backup: counts its invalidations; a state taken before one is stale
        self.applying = {}          # backup: checkpoint seq -> the follow_round it was decided in
        self.applied_node_at = None  # backup: the node's clock at the cycle end before the last checkpoint taken
        self.node_hung = False      # told, until the node ends a cycle again
        self.stopped = None         # why this replica fail-stopped (it passes nothing on then)
        self.name = name
        self.ack_timeout = ack_timeout
        self.join_period = join_period
        self.stale_after = stale_after
        self.stale_cycles = stale_cycles
        self.sender = CheckpointSender(role, first_seq) if role != Role.BACKUP else None
        self.receiver = None
        if role == Role.BACKUP:
            self.receiver = CheckpointReceiver(join=True)
            self.receiver.expect = expect
        self.joiner = None          # sender: the After that asked to join, taken at the next cycle end
        self.last_ask = None        # backup: when it last asked to join
        self.last_applied = None    # backup: when it last applied a checkpoint
        self.own_cycles = 0         # backup: its own node's cycles since then
        self.transfers = 0          # sender: state transfers sent to joiners
        self.named = PrimaryWord()  # the watchdog's word on the primary board, as followed
        self.promoted = False       # made ALONE by the watchdog (SetRole) since this replica started

    @property
    def role(self):
        return self.sender.role if self.sender is not None else self.receiver.role

    @property
    def following(self):
        """A backup that holds its primary's state (it may take over)."""
        return self.receiver is not None and self.receiver.role == Role.BACKUP and \
            self.receiver.state == Follow.FOLLOWING

    def passes_outputs(self):
        return self.role != Role.BACKUP and self.stopped is None

    # -- a hung node -----------------------------------------------------------------------------
    def node_cycled(self, stamp, wall):
        """The node ended a cycle stamped ``stamp`` (its own clock), heard at ``wall`` (monotonic).
        Returns notes."""
        if stamp > 0:   # (stamped 0: the node read no clock yet; not a time to count from)
            self.node_cycle_at, self.node_cycle_wall = stamp, wall
        if self.node_hung:
            self.node_hung = False
            return [Note('node_resumed', '%s: its node ends cycles again' % self.name)]
        return []

    def check_node(self, node_now, wall, held=False):
        """The hang watch, every tick: ``node_now`` is the node's clock as this replica reads it (0: none yet),
        ``wall`` monotonic, ``held`` whether a suspension holds the After's inputs. Returns (a fail-stop
        reason or None, notes).

        A hang is a silence of more than ``cycle_timeout`` on the node's clock and of ``HANG_WALL_MIN`` at
        least on the wall clock (at 20 times real time, 0.5 s of simulated time is 25 ms of scheduling).
        A PRIMARY fail-stops only while its backup can take over: it acknowledged every checkpoint sent
        (a backup that lost power leaves the last one unacknowledged); else the hang is said, and the
        fail-stop comes at a later look if the acknowledgment does."""
        last = self.node_cycle_at
        if not self.cycle_timeout or last is None or self.stopped is not None or node_now <= 0:
            return None, []
        if held or node_now < last:   # held: not the node's silence; a clock gone back: counted afresh
            self.node_cycle_at, self.node_cycle_wall = node_now, wall
            return None, []
        silence = node_now - last
        if silence <= self.cycle_timeout or wall - self.node_cycle_wall < HANG_WALL_MIN:
            return None, []
        what = 'its node ended no cycle for %.2f s (timeout %.2f s): it hangs' % (silence, self.cycle_timeout)
        role = self.role
        if role == Role.PRIMARY and self._backup_ready():
            self.stopped = what
            self.node_hung = True
            return '%s; the backup takes over' % what, [
                Note('node_hung', '%s: %s; this site fail-stops so that the backup takes over' % (self.name, what),
                     alarm=True)]
        if self.node_hung:
            return None, []
        self.node_hung = True
        if role == Role.BACKUP and self.following:
            return None, self._invalid(self.receiver.last_seq, what)
        why = {Role.PRIMARY: 'its backup has not acknowledged the last checkpoint (it may be lost): the site does '
                             'not fail-stop while the backup cannot take over',
               Role.ALONE: 'no backup can take over: its outputs stop until it resumes'}.get(
            role, 'this backup holds no state and cannot take over')
        return None, [Note('node_hung', '%s: %s; %s' % (self.name, what, why), alarm=True)]

    def site_stopped(self, reason):
        """This replica's site fail-stopped (its crash detector's last heartbeat says why: this After
        hung past the detector's ~alive_timeout, say). A BACKUP stops for good: its next checkpoints
        are refused (its primary goes on alone at once) and it never asks to join again. Before, a
        backup After resumed after its board fell silent for good re-joined, and its primary counted
        on a backup the watchdog would never promote. A primary serves on: the watchdog fences it
        if its backup takes over, and if none can, it is all the car has (review of session 38).
        Returns notes."""
        if self.stopped is not None:
            return []
        if self.role != Role.BACKUP:
            return [Note('site_stopped', '%s: its site fail-stopped (%s); as %s it serves on until it is fenced'
                         % (self.name, reason, self.role.name), alarm=True)]
        self.stopped = 'its site fail-stopped: %s' % reason
        return [Note('site_stopped', '%s: %s; it refuses checkpoints and does not join until its site is started '
                     'again' % (self.name, self.stopped), alarm=True)]

    def primary_named(self, site, board, term, incarnation, names_nodes=True):
        """The watchdog named ``board`` the primary in ``term`` of its run ``incarnation`` (this replica
        runs on ``site``), followed by aft_ftm.primary_word's rule. A PRIMARY or ALONE replica of another
        board named in a new word was deposed while it could not hear (frozen, cut off) and nobody fenced
        it (no power switch for its host): it stops passing anything on, for good, and its site must
        fail-stop. Returns (why the site must fail-stop, or None; notes). A word refused (a term passed,
        another run naming another board: a watchdog started again starts from its configured primary,
        whatever board drives) is said, not obeyed.

        The first word a promoted replica hears never deposes it: it may be older than the role the watchdog
        gave it (a board started again, then promoted, before the latched word of the take-over that
        failed it reached it; review of session 51). Only a replica the watchdog promoted is so
        exempted: a primary started so, frozen before its subscription connected, hears the word of
        the take-over first and must step down (review of session 52)."""
        first = self.named.run is None and self.promoted
        word = self.named.hear(board, term, incarnation, names_nodes)
        if word.refused:
            return None, [Note(word.value, '%s: the word naming board %s the primary in term %d of watchdog run %s is '
                               'refused (%s); in force: %s; this After stays %s'
                               % (self.name, board, term, incarnation, self.named.why, self.named.describe(),
                                  self.role.name), alarm=True)]
        if word is not Word.TAKEN or first or board == site or self.role == Role.BACKUP or self.stopped is not None:
            return None, []
        self.stopped = 'deposed: the watchdog named board %s the primary (term %d) while this %s ran on' % (
            board, term, self.role.name)
        return self.stopped, [Note('deposed', '%s: %s; it passes nothing on from now on and its site fail-stops'
                                   % (self.name, self.stopped), alarm=True)]

    # -- every replica ---------------------------------------------------------------------------
    def cycle_end(self, state, now):
        """The node ended a cycle with ``state`` (bytes). Returns (the Outgoing checkpoint or None, notes)."""
        if self.sender is None:
            return None, self._own_cycle(now)
        if self.stopped is not None:
            return None, []
        if self.joiner is not None and not self.sender.deposed:
            joiner, self.joiner = self.joiner, None
            if self.sender.role == Role.PRIMARY:
                self.sender.go_alone()   # our backup asks to join: it no longer mirrors us
            seq = self.sender.join(joiner, now)
            self.transfers += 1
            return Outgoing(seq, self.sender.first_seq, state), [
                Note('join', '%s asked to join: its state transfer is checkpoint %d' % (joiner, seq))]
        if not self.sender.needs_checkpoint():
            return None, []
        return Outgoing(self.sender.hold(None, now), self.sender.first_seq, state), []

    def check(self, now):
        """The timed duties. Returns (whether to send a join request now, notes)."""
        if self.sender is not None:
            if self.sender.role == Role.PRIMARY and self.sender.overdue(now, self.ack_timeout):
                self.sender.go_alone()
                return False, [Note('backup_lost', 'a checkpoint was not acknowledged within %.2f s: the backup is '
                                    'lost; %s goes on alone until a backup joins' % (self.ack_timeout, self.name),
                                    alarm=True)]
            return False, []
        # (A backup whose node hangs does not ask: it could not take the state transfer.)
        if self.receiver.role == Role.BACKUP and self.receiver.state == Follow.JOINING and not self.node_hung and \
                self.stopped is None and (self.last_ask is None or now - self.last_ask >= self.join_period):
            self.last_ask = now
            return True, []
        return False, []

    def set_role(self, role, first_seq):
        """A role change asked from outside (the watchdog). ``first_seq`` numbers the checkpoints of a
        promoted backup. Returns the last checkpoint applied (0 if none); RoleError changes nothing."""
        if role == Role.PRIMARY and self.role != Role.PRIMARY:
            raise RoleError('%s becomes primary when a backup asks to join it, not on request' % self.name)
        if role == Role.ALONE and self.receiver is not None and self.receiver.role == Role.BACKUP:
            last_seq = self.receiver.promote()   # RoleError if it holds no state
            self.sender = CheckpointSender(Role.ALONE, first_seq)
            self.promoted = True
            return last_seq
        if role == Role.ALONE and self.sender is not None and self.sender.role == Role.PRIMARY:
            self.sender.go_alone()
            return 0
        check_role_change(self.role, role)   # the same role: nothing to do; anything else is refused
        return 0

    # -- primary side ----------------------------------------------------------------------------
    def on_join(self, after):
        """A backup After asks for a state transfer. Returns notes."""
        if self.sender is None:
            return [Note('join_ignored', '%s asks to join, but %s is a backup' % (after, self.name))]
        if self.stopped is not None:
            return [Note('join_ignored', '%s asks to join, but %s fail-stopped' % (after, self.name))]
        if self.sender.join_seq is not None and self.sender.joiner == after:
            return []   # its state transfer is on its way
        self.joiner = after
        return []

    def on_ack(self, seq, ok, error, to):
        """The backup answered checkpoint seq (``to``: the After it answers, '' if it does not say).
        Returns notes."""
        if self.sender is None or (to and to != self.name):
            return []
        joiner = self.sender.joiner
        _, need = self.sender.on_ack(seq, ok)
        if need == Need.ADMIT:
            self.sender.admit(0)
            return [Note('joined', '%s holds our state (checkpoint %d): it is our backup' % (joiner, seq))]
        if need == Need.EXCLUDE:
            self.sender.go_alone()
            return [Note('backup_lost', 'the backup refused checkpoint %d (%s): %s goes on alone until a backup '
                         'joins' % (seq, error or 'no reason given', self.name), alarm=True)]
        return []

    # -- backup side -----------------------------------------------------------------------------
    def on_checkpoint(self, seq, sender, first_seq, full):
        """A checkpoint arrived. Returns (Decision, notes). On APPLY and APPLY_FULL the caller sets the
        state into its node, then calls :meth:`applied`."""
        if self.receiver is None or self.stopped is not None:
            return Decision.FENCED, []
        decision = self.receiver.decide(seq, sender, first_seq, full=full)
        if decision == Decision.GAP:
            return decision, self._invalid(seq, 'a checkpoint is missing before it')
        if decision in (Decision.APPLY, Decision.APPLY_FULL):
            self.applying[seq] = self.follow_round
            while len(self.applying) > 64:   # (bounded: a caller that never says applied)
                self.applying.pop(next(iter(self.applying)))
        return decision, []

    def applied(self, seq, sender, ok, error, now, first_seq=0):
        """The node took the state of checkpoint seq (ok), or refused it (error); ``first_seq``: the number
        its sender numbers from (a sender started again numbering below is then a gap, not copies).
        Returns notes."""
        refusal = self.refusal(seq) if ok else None
        if refusal:
            ok, error = False, refusal
        self.applying.pop(seq, None)
        if not ok:
            return self._invalid(seq, error)
        joining = self.receiver.state == Follow.JOINING
        self.receiver.accept(seq, sender, first_seq=first_seq)
        self.last_applied, self.own_cycles = now, 0
        self.applied_node_at = self.node_cycle_at
        if joining:
            return [Note('following', '%s follows %s from checkpoint %d' % (self.name, sender, seq))]
        return []

    def replaceable(self, now):
        """Whether a backup could take over from this replica now: a PRIMARY, not fail-stopped, whose
        backup is admitted, with no state transfer under way or asked for, and no checkpoint waiting
        for its acknowledgment past ack_timeout. (Not "every checkpoint acknowledged": one is in
        flight for a round trip at every cycle, and a sign of life taken then said no; review of
        session 38.)"""
        sender = self.sender
        return self.stopped is None and sender is not None and sender.role == Role.PRIMARY and sender.admitted and \
            sender.join_seq is None and self.joiner is None and not sender.overdue(now, self.ack_timeout)

    def _backup_ready(self):
        """A primary's backup can take over: admitted, no state transfer under way or asked for, and every
        checkpoint acknowledged (a backup that lost power leaves the last one unacknowledged; a joiner
        still taking its transfer holds nothing the watchdog may promote)."""
        sender = self.sender
        return sender.admitted and sender.join_seq is None and self.joiner is None and not sender.held

    def refusal(self, seq):
        """Why checkpoint seq, just set into the node, must be refused (None: it may be followed from). A
        backup whose node hangs cannot take over, whatever state it took (its node's set_state may answer
        while its cycle is stuck); one decided before this backup last stopped mirroring its primary (its
        node hung in the set_state call, and the hang watch invalidated it meanwhile) holds an old state
        (review of session 37)."""
        if self.stopped is not None:
            return self.stopped
        if self.node_hung:
            return 'its node hangs: this backup could not take over'
        if self.applying.get(seq, self.follow_round) != self.follow_round:
            return STALE_STATE
        return None

    def _own_cycle(self, now):
        if not self.following:
            return []
        self.own_cycles += 1
        if self.applied_node_at is None:   # (its node's first cycle heard since: counted from there)
            self.applied_node_at = self.node_cycle_at
        # With the hang watch on, also twice its timeout on the node's clock: the primary's After sees its
        # own node hung after one, and its board is failed over meanwhile; a backup invalid by then could
        # not take over (at half real time, 1 s of wall clock was all the primary's detection).
        span = None if self.node_cycle_at is None or self.applied_node_at is None else \
            self.node_cycle_at - self.applied_node_at
        if self.cycle_timeout and span is not None and 0 <= span < 2 * self.cycle_timeout:
            return []
        if self.own_cycles >= self.stale_cycles and now - self.last_applied >= self.stale_after:
            return self._invalid(self.receiver.last_seq, 'no checkpoint for %.2f s, over %d cycles of its own node'
                                 % (now - self.last_applied, self.own_cycles))
        return []

    def _invalid(self, seq, why):
        """This backup no longer mirrors its primary: JOINING again, asking at once."""
        following = self.receiver.state == Follow.FOLLOWING
        self.follow_round += 1
        self.receiver.failed(seq, why)
        self.last_ask = None
        if following:
            return [Note('backup_invalid', '%s no longer mirrors its primary (%s): it cannot take over and asks to '
                         'join again' % (self.name, why), alarm=True)]
        return [Note('join_failed', '%s could not take checkpoint %d (%s): it asks to join again'
                     % (self.name, seq, why))]
