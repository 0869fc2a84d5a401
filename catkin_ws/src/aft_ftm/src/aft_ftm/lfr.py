"""Leader-Follower Replication (LFR) without ROS: the decisions of an LFR replica's Before and After.

The ROS adapter (aft_ftm.ros.lfr_nodes) passes messages (anything with the attributes used here),
the clock (``now``, monotonic seconds) and its node name in, and carries the decisions out: it
publishes, calls the witness, the server's state manager and the Before. Nothing here blocks,
sleeps or reads a clock.

Invariants the After keeps (:class:`LfrAfter`):
- A leader with a follower (LEADING) releases a reply only once the follower said it computed the
  same request (an ack), or once the follower is gone (:meth:`LfrAfter.go_alone`, with a witness
  only after the witness excluded it). A refusal of the leader's Protocol ("not executed") is sent
  to the follower and held the same way, so that a copy of the request re-sent after a failover is
  refused there too, never executed.
- An ack may come before the leader's own result (both compute concurrently): it is remembered and
  the reply goes out as soon as it is computed. A duplicate ack releases nothing twice.
- A leader the witness deposed (DEPOSED) answers nothing more: its held replies are withheld for
  good, and its site fail-stops.
- A follower starts empty (JOINING) under a witness and follows a leader only after one state
  transfer (a full aft_msgs/Checkpoint on /ftm/lfr_transfers/<site>) from the peer site's After; it
  may take over (ALONE) only while FOLLOWING, unless the witness made it the first primary.
  A Join tells the last transfer the follower accepted (``last_seq``): a Join of the admitted
  follower that does not name our transfer was sent before it accepted it, and is late and ignored;
  one naming it was sent after: the follower lost its state, and the leader has it excluded first.
  Numbers are only compared for equality, so that a leader started after a backward clock step
  (numbering its transfers below its predecessor's) tells them apart all the same.
- A follower sets a transferred state only once its Before follows that transfer and every request
  the Before passed on before is computed (:meth:`LfrAfter.in_flight`): a request the leader
  forwarded before the transfer (contained in its state) is never computed after it, whatever
  the delays (a Before or Proceed frozen past the ack timeout, a slow server call, forwards
  delivered after the transfer; see :class:`LfrForwarder`).
- A transfer or an ack from an After that is not the peer site's is ignored and reported
  (:attr:`Ack.STRAY`, :meth:`LfrAfter.check_transfer`): one stray message changes nothing.

Every change of state goes through ``_change`` along :data:`EDGES`; the replica's role is derived
from the state (:data:`ROLE_OF`), so that each node has exactly one owner of its role.
"""
import enum

from .errors import RoleError
from .once import RecentKeys
from .protocol import DuplicateCache, Role, check_role_change, key as request_key


# Joins of the admitted follower that name another transfer are late (sent before it accepted ours) for
# this long after the first; still coming then, they are a follower that lost its state (s).
LATE_JOINS_FOR = 2.0


class State(enum.Enum):
    """Where an LFR After is in its life."""
    JOINING = 0     # follower holding no state of any leader: asks for a state transfer
    FOLLOWING = 1   # follower holding its leader's state: computes the forwarded requests, may take over
    ALONE = 2       # leader without a follower: replies at once
    LEADING = 3     # leader with a follower: holds each reply until the follower computed it
    DEPOSED = 4     # a leader the witness refused: answers nothing more (its site fail-stops)


# The replica role of each state (a deposed After keeps the role it was deposed in, see LfrAfter.role).
ROLE_OF = {State.JOINING: Role.BACKUP, State.FOLLOWING: Role.BACKUP, State.ALONE: Role.ALONE,
           State.LEADING: Role.PRIMARY}


# Allowed state changes, each with the event that causes it.
EDGES = {
    (State.JOINING, State.FOLLOWING): "the leader's state transfer was set on the server",
    (State.FOLLOWING, State.JOINING): 'excluded by the witness, or never admitted after its transfer: it joins again',
    (State.FOLLOWING, State.ALONE): 'the leader failed: the follower takes over (Recovery)',
    (State.JOINING, State.ALONE): 'the witness made this site the first primary: it serves its own state',
    (State.ALONE, State.LEADING): 'a follower holds our state and the witness admitted it',
    (State.LEADING, State.ALONE): 'the follower is lost (silent or restarted) and excluded, or Recovery says so',
    (State.ALONE, State.DEPOSED): 'the witness refused us: another site serves',
    (State.LEADING, State.DEPOSED): 'the witness refused us: another site serves',
}


class Out(enum.Enum):
    """What to do with a reply of this replica's server (:meth:`LfrAfter.on_reply`)."""
    DROP = 0            # nothing: a follower's refusal, or a deposed leader's reply
    STORE = 1           # follower: store it in the Protocol, tell the leader (Notify seq = computed)
    HOLD = 2            # leader: wait for the follower's ack
    HOLD_REFUSAL = 3    # leader: send the refusal to the follower, hold it until it acknowledges
    RELEASE = 4         # send it to the Protocol
    RELEASE_NOTIFY = 5  # send it to the Protocol, then notify the follower (it acknowledged first)


class Ack(enum.Enum):
    """What an ack from the follower means (:meth:`LfrAfter.on_ack`)."""
    RELEASE = 0         # the follower computed a held request: send the reply, notify the follower
    EARLY = 1           # before our own result: remembered, the reply goes out as soon as computed
    IGNORED = 2         # not leading, or an ack of a state transfer no longer under way: changes nothing
    TRANSFER = 3        # the follower holds the state transfer under way
    STRAY = 4           # not from the peer site's After: ignored, reported


class JoinDecision(enum.Enum):
    """A leader's answer to a Join (:meth:`LfrAfter.on_join`)."""
    IGNORE = 0          # our own site's, we follow, we are deposed, or a late Join of our follower
    EXCLUDE = 1         # our follower asks again: it restarted; have it excluded first
    TRANSFER = 2        # alone: transfer our state to the joining site


class JoinStep(enum.Enum):
    """What a follower does at each join period (:meth:`LfrAfter.join_step`)."""
    NOTHING = 0
    JOIN = 1            # send a Join (once the leader's transfers can reach us)
    STATUS = 2          # joined long ago, never seen admitted: ask the witness whether we are its backup


class ConfChange(enum.Enum):
    """What a new configuration of the witness means here (:meth:`LfrAfter.on_configuration`)."""
    NOTHING = 0
    DEPOSED = 1         # another site is the primary: fail-stop (call depose())
    EXCLUDED = 2        # this follower was excluded: it joins again (already JOINING)


class Held(object):
    """A reply waiting for the follower's ack."""
    __slots__ = ('reply', 'since')

    def __init__(self, reply, since):
        self.reply = reply
        self.since = since


class Transfer(object):
    """A state transfer to a joining follower, waiting for its ack."""
    __slots__ = ('seq', 'joiner', 'since', 'cache', 'acknowledged_s')

    def __init__(self, seq, joiner, since, cache):
        self.seq = seq
        self.joiner = joiner            # the joining site
        self.since = since
        self.cache = cache              # the replies it carries (clients may ask for them again)
        self.acknowledged_s = None      # seconds from since to the follower's ack


def initial_state(role, joined):
    """The state an After starts in: a follower ``joined`` holds its leader's state already (no
    witness, or started beside it by an adaptation, ``in_sync``)."""
    if role == Role.BACKUP:
        return State.FOLLOWING if joined else State.JOINING
    return State.LEADING if role == Role.PRIMARY else State.ALONE


class LfrAfter(object):
    """An LFR After's decisions. ``name`` its node name (in messages), ``site`` and ``peer`` its own
    and its peer's site ('' without a witness: then transfers and acks are not checked for their
    sender), ``join_seq`` the number below the first state transfer's (the adapter takes the wall
    clock in microseconds, so that a restarted leader's numbers differ from its predecessor's)."""

    def __init__(self, name, role, joined=True, site='', peer='', ack_timeout=1.0, join_period=0.5,
                 join_seq=0, cache_bytes=0):
        self.name = name
        self.site = site
        self.peer = peer
        self.expect = '/%s/' % peer if peer else ''   # the peer's After's name starts so
        self.ack_timeout = ack_timeout
        self.join_period = join_period
        self.state = initial_state(role, joined)
        self.reason = 'started'
        self.deposed = None     # why the witness deposed this leader
        self.deposed_role = None   # the role it had then (a deposed After reports it)
        self.epoch = 0          # the witness's epoch of this replica's role
        self.held = {}          # leader: (origin, id) -> Held
        self.acked = set()      # leader: acks that came before our own result
        self.computed = 0       # follower: results of forwarded requests
        self.duplicates = 0     # second copies of replies already had (dropped)
        self.peer_refusals = set()   # follower: keys of the leader's refusals it stored (not its own replies)
        self.notified = 0
        self.recent = DuplicateCache(0, cache_bytes)   # replies a state transfer carries: never evicted
        self.follower = None    # leader: the follower admitted: (After, site incarnation, transfer seq)
        self.late_since = None  # leader: when the follower's first late Join of a run came (None: none yet)
        self.late_last = None   # leader: when its last late Join came
        self.transfer = None    # leader: the Transfer waiting for its ack
        self.join_seq = join_seq
        self.accepted = 0       # follower: the seq of the last state transfer it accepted
        self.joined_since = 0.0
        self.configuration = None   # the witness's newest configuration seen

    # -- state -----------------------------------------------------------------------------
    @property
    def role(self):
        return self.deposed_role if self.state == State.DEPOSED else ROLE_OF[self.state]

    @property
    def joined(self):
        """False while a follower holds no state (it cannot take over)."""
        return self.state != State.JOINING

    def _change(self, new, why):
        """The one place where the state changes: along EDGES, and along the allowed role changes."""
        if new == self.state:
            return
        if (self.state, new) not in EDGES:
            raise RoleError('%s: LFR %s -> %s is not allowed (%s)' % (self.name, self.state.name, new.name, why))
        if new != State.DEPOSED:
            check_role_change(self.role, ROLE_OF[new])
        self.state, self.reason = new, why

    # -- replies -------------------------------------------------------------------------
    def remember(self, reply):
        """Keep a reply for a state transfer (forgetting those its client no longer waits for)."""
        self.recent.forget_below(reply.origin, reply.oldest_pending)
        self.recent.store(reply)

    def on_reply(self, reply, now, refused=False):
        """This replica's server computed a reply (``refused``: the Protocol's "not executed"). A second
        copy of a reply already had (the same message delivered twice across a rebind, as Before's
        forwards can be) is dropped and counted in ``duplicates``: a leader held it for an ack that
        never came again, excluding a healthy follower; a follower counted it as computed, and its
        fence and its promotion went ahead while a forwarded request still ran (review of session 36)."""
        k = request_key(reply)
        if self.recent.lookup(k) is not None:
            if k not in self.peer_refusals:
                self.duplicates += 1
                return Out.DROP
            self.peer_refusals.discard(k)   # the leader refused a request this follower computes: its own
        if self.role == Role.BACKUP:
            if refused:
                return Out.DROP   # a follower's Protocol refuses nothing (nor does it get requests)
            self.computed += 1
            self.remember(reply)
            return Out.STORE
        if self.state == State.DEPOSED:
            return Out.DROP
        reply.epoch = self.epoch
        self.remember(reply)
        if self.state == State.ALONE:
            return Out.RELEASE
        key = (reply.origin, reply.id)
        if refused:
            self.held[key] = Held(reply, now)
            return Out.HOLD_REFUSAL
        if key not in self.acked:
            self.held[key] = Held(reply, now)
            return Out.HOLD
        self.acked.discard(key)
        return Out.RELEASE_NOTIFY

    def from_peer(self, sender):
        """True if ``sender`` (a node name; None: unknown) may be the peer site's After."""
        return not self.expect or sender is None or sender.startswith(self.expect)

    def on_ack(self, origin, rid, now, sender=None):
        """The follower computed request (origin, rid); origin '' acknowledges state transfer rid.
        Returns (Ack, the reply to release or None)."""
        if not self.from_peer(sender):
            return Ack.STRAY, None
        if not origin:
            if self.transfer is not None and rid == self.transfer.seq and self.transfer.acknowledged_s is None:
                self.transfer.acknowledged_s = now - self.transfer.since
                return Ack.TRANSFER, None
            return Ack.IGNORED, None
        key = (origin, rid)
        held = self.held.pop(key, None)
        if held is not None:
            return Ack.RELEASE, held.reply
        if self.state != State.LEADING:
            return Ack.IGNORED, None
        self.acked.add(key)
        return Ack.EARLY, None

    def on_peer_refusal(self, reply):
        """Follower: the leader refused a request. True if it is to be stored (and acknowledged)."""
        if self.state != State.FOLLOWING:
            return False
        self.remember(reply)
        if len(self.peer_refusals) >= 10000:   # bounded: those no longer stored are forgotten
            self.peer_refusals = {k for k in self.peer_refusals if self.recent.lookup(k) is not None}
        self.peer_refusals.add(request_key(reply))
        return True

    # -- losing the follower ---------------------------------------------------------------
    def overdue(self, now):
        """True if the follower has been silent about a held reply for longer than ack_timeout."""
        return self.state == State.LEADING and any(now - h.since > self.ack_timeout for h in self.held.values())

    def go_alone(self, epoch=0, why='the follower is lost'):
        """The follower is gone (excluded): returns every held reply, oldest first, to release."""
        self._change(State.ALONE, why)
        self.epoch = max(self.epoch, epoch)
        self.follower = None
        released = [h.reply for h in sorted(self.held.values(), key=lambda h: h.since)]
        self.held.clear()
        self.acked.clear()
        for reply in released:
            reply.epoch = self.epoch
        return released

    def depose(self, why):
        """The witness refused this leader: it answers nothing more. Returns how many replies are
        withheld for good."""
        if self.state != State.DEPOSED:
            role = self.role
            self._change(State.DEPOSED, why)
            self.deposed_role = role
        self.deposed = why
        withheld = len(self.held)
        self.held.clear()
        return withheld

    # -- joins (leader) ----------------------------------------------------------------------
    def on_join(self, join, now=None):
        """A Join (site, after, incarnation, last_seq) arrived (at ``now``, monotonic, if given).

        From the follower, naming another transfer than the one it joined with, it is late: sent before it
        accepted ours. But a follower's After started again in the same site incarnation (an adaptation's
        replacement) asks with 0 too, every join period, and holds nothing: such "late" Joins still coming
        LATE_JOINS_FOR (or 4 join periods) after the first, with no pause of 3 join periods between two, are
        a follower that lost its state, excluded (review of session 36: ignored for ever, with no alarm,
        and the follower could not take over)."""
        if join.site == self.site or self.role == Role.BACKUP or self.state == State.DEPOSED:
            return JoinDecision.IGNORE
        if self.state == State.LEADING:
            follower = self.follower
            if follower is not None and (join.after, join.incarnation) == follower[:2] \
                    and join.last_seq != follower[2]:
                if now is None:
                    return JoinDecision.IGNORE
                if self.late_since is None or now - self.late_last > 3 * self.join_period:
                    # (a new run: a follower still asking sends one every join period; a backlog of
                    # late ones, retransmitted after a loss, comes after a pause)
                    self.late_since = now
                self.late_last = now
                if now - self.late_since < max(LATE_JOINS_FOR, 4 * self.join_period):
                    return JoinDecision.IGNORE   # sent before it accepted our transfer: late
            return JoinDecision.EXCLUDE
        return JoinDecision.TRANSFER

    def start_transfer(self, joiner, now):
        """The Protocol is quiescent and the server's state captured: the Transfer to send (seq and the
        replies it carries), or None if this After no longer leads alone."""
        if self.state != State.ALONE:
            return None
        self.join_seq += 1
        self.transfer = Transfer(self.join_seq, joiner, now, self.recent.replies())
        return self.transfer

    def end_transfer(self):
        """Stop waiting for the transfer's ack (acknowledged or not)."""
        transfer, self.transfer = self.transfer, None
        return transfer

    def admitted(self, after, incarnation, seq, epoch):
        """The witness admitted the follower that acknowledged transfer seq, and the Before forwards."""
        self._change(State.LEADING, 'the witness admitted %s at epoch %d' % (after, epoch))
        self.epoch = max(self.epoch, epoch)
        self.follower = (after, incarnation, seq)
        self.late_since = None

    # -- joins (follower) --------------------------------------------------------------------
    def join_step(self, now):
        """The join timer fired."""
        if self.state == State.JOINING:
            return JoinStep.JOIN
        if self.state != State.FOLLOWING:
            return JoinStep.NOTHING
        conf = self.configuration
        if conf is None or self.site in (conf.primary, conf.backup) \
                or now - self.joined_since < max(2 * self.ack_timeout, 4 * self.join_period):
            return JoinStep.NOTHING
        return JoinStep.STATUS

    def not_admitted(self, epoch):
        """The witness does not name this follower its backup: it joins again. False if it no longer follows."""
        if self.state != State.FOLLOWING:
            return False
        self._change(State.JOINING, 'not admitted by the witness after its state transfer (epoch %d)' % epoch)
        return True

    def check_transfer(self, seq, sender, epoch, full):
        """Why state transfer seq of ``sender`` is refused (nothing changes), or None to set it."""
        if self.state != State.JOINING:
            return '%s is not joining' % self.name
        if not full or not self.expect or not sender.startswith(self.expect):
            return '%s does not follow %s' % (self.name, sender)
        if epoch < self.epoch:
            return 'state transfer of epoch %d, older than epoch %d' % (epoch, self.epoch)
        return None

    def in_flight(self, passed):
        """How many of the ``passed`` forwarded requests its Before passed on are not computed yet.
        The state of a transfer is set only once none is: a request passed on before the transfer
        and computed after it would be computed twice (it is in the transferred state)."""
        return max(0, passed - self.computed)

    def transferred(self, seq, epoch, cache, now):
        """The server holds the state of transfer seq: follow its sender."""
        self._change(State.FOLLOWING, 'state transfer %d' % seq)
        for reply in cache:
            self.remember(reply)
        self.accepted = seq
        self.joined_since = now
        self.epoch = max(self.epoch, epoch)

    # -- the witness's configuration --------------------------------------------------------
    def on_configuration(self, conf):
        """A configuration (epoch, primary, backup) of the witness."""
        if self.configuration is None or conf.epoch >= self.configuration.epoch:
            self.configuration = conf
        if conf.epoch <= self.epoch:
            return ConfChange.NOTHING
        if (conf.primary == self.site and self.role != Role.BACKUP) or \
                (conf.backup == self.site and self.state == State.FOLLOWING):
            self.epoch = conf.epoch   # this replica's own configuration (an After an adaptation started)
            return ConfChange.NOTHING
        if self.role != Role.BACKUP and self.state != State.DEPOSED and conf.primary != self.site:
            return ConfChange.DEPOSED
        if self.state == State.FOLLOWING and self.site not in (conf.primary, conf.backup):
            self._change(State.JOINING, 'excluded at epoch %d' % conf.epoch)
            return ConfChange.EXCLUDED
        return ConfChange.NOTHING

    def unfollowed_backup(self):
        """Whether the witness's newest configuration names this leader's peer its backup while this
        leader goes on alone, no transfer under way: an ADMIT it gave up on (no answer within its
        timeout) that the witness carried out later. A promotion of that follower would serve a state
        without every reply answered since: the leader must have it excluded."""
        conf = self.configuration
        return (self.state == State.ALONE and self.transfer is None and conf is not None and bool(self.peer)
                and conf.primary == self.site and conf.backup == self.peer and conf.epoch >= self.epoch)

    # -- role changes (Recovery) -----------------------------------------------------------------
    def check_role(self, role, initial=False):
        """Raise RoleError unless Recovery may make this After ``role`` now (``initial``: the witness
        makes this site the first primary)."""
        check_role_change(self.role, role)
        if self.state == State.JOINING and role == Role.ALONE and not initial:
            raise RoleError('%s holds no state: it never joined' % self.name)

    def set_role(self, role, epoch=0, initial=False):
        """Recovery's order (the adapter has waited for the forwarded requests to be computed).
        Returns (replies to release, None) or ([], why the role is kept). Raises RoleError if refused."""
        self.check_role(role, initial)
        if self.state == State.DEPOSED:
            self.deposed_role = role   # it answers nothing whatever its role
        elif self.role == Role.BACKUP and role == Role.ALONE:
            self._change(State.ALONE, 'Recovery promotes it at epoch %d' % epoch)
            self.epoch = max(self.epoch, epoch)
        elif self.role == Role.PRIMARY and role == Role.ALONE:
            if epoch and epoch < self.epoch:
                # A late order (Recovery stalled) about a follower that has joined again since.
                return [], 'role PRIMARY kept: epoch %d is newer than %d' % (self.epoch, epoch)
            return self.go_alone(epoch, 'Recovery: the follower failed (epoch %d)' % epoch), None
        elif self.role == role:
            self.epoch = max(self.epoch, epoch)
        # ALONE -> PRIMARY: only a join makes a leader lead (admitted()); Recovery's order (it gives
        # every node its configured role at start) changes nothing.
        return [], None


class Forwarded(enum.Enum):
    """What a follower's Before does with a request the leader forwarded (:meth:`LfrForwarder.on_forwarded`)."""
    PASS = 0            # pass it on to the Proceed (the server computes it)
    NOT_FOLLOWER = 1    # refused: this Before no longer follows (promoted, fenced)
    STALE = 2           # refused: forwarded before the state transfer this follower joined with,
                        # so that transfer's state contains it already (computing it again would
                        # put the follower ahead of its leader)
    DUPLICATE = 3       # refused: this follower passed the same request (origin, id) on already; a
                        # second copy (a publisher heard on two connections across a rebind, or a
                        # message published again by anyone on the graph) would compute it twice


class LfrForwarder(object):
    """An LFR Before's decisions: a leader (PRIMARY) forwards each request to the follower; a
    follower (BACKUP) passes the leader's forwarded requests on, in order; once promoted (ALONE) it
    is fenced: it refuses them. ``passed`` counts the requests passed on (Recovery, and a follower's
    After before it sets a transferred state, wait for the After to have computed that many).

    Forwards are fenced by state transfer: the leader's Before stamps each forwarded request with
    the seq of the state transfer its follower was admitted with (``transfer``, 0 without a join);
    a follower's After, before it sets a transferred state on its server, makes its Before follow
    that transfer (:meth:`follow`): from then on a request stamped below it was forwarded before
    the transfer, is contained in the transferred state and is refused (:attr:`Forwarded.STALE`).
    A Before frozen past the leader's ack timeout, whose follower was excluded and joined again
    meanwhile, thus never passes its backlog on to the server again. Transfer seqs grow (the
    leader numbers them from the wall clock), so the forwards of the transfer joined with and of
    later ones pass.

    A follower remembers the last ``remember`` requests it passed on (origin, id): the leader forwards
    each request once, so a second copy is refused (:attr:`Forwarded.DUPLICATE`), never computed
    twice (the follower's state would run ahead of its leader's, silently, until a failover served it)."""

    def __init__(self, role, remember=65536):
        self.role = role
        self.recent = RecentKeys(remember)   # follower: (origin, id) of the requests passed on
        self.duplicates = 0  # second copies of a forward refused
        self.epoch = 0       # the witness's epoch of the last role given (a late, older order changes nothing)
        self.transfer = 0    # leader: the stamp of its forwards; follower: forwards stamped below are stale
        self.passed = 0
        self.refused = 0
        self.stale = 0       # forwards refused as contained in the state transfer joined with

    def forwards(self):
        return self.role == Role.PRIMARY

    def stamp(self):
        """Leader: the state transfer its follower joined with (stamped on each forwarded request)."""
        return self.transfer

    def on_forwarded(self, transfer=0, key=None):
        """A request forwarded by the leader, stamped ``transfer``, ``key`` its (origin, id): pass it on
        or refuse it (Forwarded)."""
        if self.role != Role.BACKUP:
            self.refused += 1
            return Forwarded.NOT_FOLLOWER
        if self.transfer and transfer != self.transfer:   # (equality: a leader started after a backward
            # clock step numbers lower; a follower that followed no transfer has nothing to refuse by)
            self.stale += 1
            return Forwarded.STALE
        if key is not None and not self.recent.add(key):
            self.duplicates += 1
            return Forwarded.DUPLICATE
        self.passed += 1
        return Forwarded.PASS

    def follow(self, transfer):
        """Follower: its After is about to set the state of ``transfer``. Refuse from now on every
        forward stamped otherwise; returns how many requests were passed on so far (the After waits
        until it computed them all before it sets the state). Raises RoleError unless a follower.
        Numbers are only compared for equality: a leader started after a backward clock step numbers
        its transfers below its predecessor's (a maximum kept refused all its forwards). The After's
        calls never overtake one another (an exclusive deadline: no call while an abandoned one runs)."""
        if self.role != Role.BACKUP:
            raise RoleError('a %s Before follows no state transfer' % self.role.name)
        self.transfer = transfer
        return self.passed

    def set_role(self, role, epoch=0, transfer=0):
        """The one place where the role changes (``transfer``: PRIMARY only, the state transfer the
        admitted follower holds, stamped on forwards; 0 keeps the stamp). Returns None, or why the
        role is kept; raises RoleError."""
        check_role_change(self.role, role)
        if self.role == Role.PRIMARY and role == Role.ALONE and epoch and epoch < self.epoch:
            return 'role PRIMARY kept: epoch %d is newer than %d' % (self.epoch, epoch)
        self.role = role
        self.epoch = max(self.epoch, epoch)
        if role == Role.PRIMARY and transfer:
            self.transfer = transfer
        return None
