"""Primary-Backup Replication (paper section 5.2.2): the After of each replica."""
import concurrent.futures
import json
import queue
import threading
import time

import rospy
from aft_msgs.msg import Checkpoint, CheckpointAck, Join
from aft_msgs.srv import GetState, GetStateDelta, SetRole, SetRoleResponse, SetState, StoredReplies, \
    StoredRepliesResponse
from std_msgs.msg import String

from .. import config, health
from ..checkpoint import (HARMLESS, AdmissionGate, BatchError, CheckpointReceiver, CheckpointSender, Decision,
                          Follow, GroupCommit, Need, is_refusal)
from ..delta import DeltaDecoder, DeltaEncoder, DeltaError, ServerChanges, StateBuffer
from ..errors import RoleError
from ..transfer import Incoming, Outgoing, TransferError
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import DuplicateCache, Role, check_role_change
from ..witness import Op
from .alarms import alarm
from .bpa_nodes import AfterNode, BeforeNode
from .deadline import CallTimeout, Deadline
from .params import param
from .persistent_service import PersistentService
from .ports import wait_for_connections
from .protocol_node import ROLES
from .replica_side import SIDE_PORTS, ReplicaSide
from .witness_client import site_launcher_pid


class PbrBeforeNode(BeforeNode):
    """PBR's Before: a pass-through (PBR has no Before action) that follows the replica's role, so
    that Recovery promotes Before and After whatever the mechanism (a switch to or from LFR keeps
    Recovery's list of nodes the same shape).

    Parameters: ~role (primary | backup | alone, default primary)
    Subscribes: pro2bfr (aft_msgs/Request), port ``inp``.  Publishes: bfr2prd (aft_msgs/Request), port ``out``.
    Services: ~set_role (aft_msgs/SetRole, last_seq 0: it holds nothing), ~rebind (aft_msgs/Rebind)
    """
    MECHANISM = 'pbr'

    def __init__(self):
        self.role = ROLES[param('role', config.choice(*ROLES), 'primary')]
        super(PbrBeforeNode, self).__init__()

    def setup(self, timeout):
        rospy.Service('~set_role', SetRole, self._on_set_role)
        return super(PbrBeforeNode, self).setup(timeout)

    def _on_set_role(self, req):
        role = Role(req.role)
        try:
            check_role_change(self.role, role)
        except RoleError as e:
            return SetRoleResponse(success=False, message=str(e))
        self.role = role
        return SetRoleResponse(success=True, message='role %s' % role.name, last_seq=0)


# The applier's share of the time at most: a state that takes long to set (10 MB: tens of ms) is applied
# less often than ~apply_period. That costs a failover nothing (a promotion sets the newest state in any
# case, whole), and it leaves the CPU to the requests (on 2 cores, a 10 MB set_state every 10 ms doubled
# the cost of each request).
APPLY_SHARE = 0.25
FULL_APPLY_DELAY_PER_MB = 0.02   # s: a state transfer's set_state waits this long per MB (1 s at most)


class PbrAfterNode(AfterNode):
    """PBR's After. As primary: captures the server's state after each request, checkpoints it to
    the backup's After and passes the reply on once the backup acknowledged it. As backup: sets
    its server's state from each checkpoint, stores the reply in its Protocol, acknowledges.

    With a witness (``~witness``), see aft_ftm.checkpoint and aft_ftm.witness: a primary whose
    backup is lost, slow or refusing releases its held replies only once the witness excluded the
    backup, and fail-stops if the witness deposed it; a backup starts empty and joins (asks for a
    state transfer, every ``~join_period``), and joins again whenever it stops mirroring its
    primary (a gap, a refused state, excluded by the witness). A checkpoint from an After it does
    not follow, or of an older epoch, is refused with an alarm and changes nothing.

    Parameters:
        ~role (primary | backup | alone, default primary): with a witness every site starts as backup
            and Recovery promotes the one the witness names.
        ~ack_timeout (float, 1 s): a checkpoint (or a state transfer) not acknowledged for this long
            means the backup is lost: it is excluded (with the witness's grant) and held replies released.
        ~batch_gap (float, 30 s, the Protocol's processing timeout): group commit: a batch gathered with
            no further reply of it for this long is broken (one lost on its way): the site fail-stops,
            as for a reply out of order. Its requests run one after the other, each within the server
            timeout (5 s; an inner TR runs each up to 3 times): keep it above what one request may take.
        ~connect_timeout (float, 10 s): how long set-up waits for the peer's After.
        ~apply_period (float, 0.01 s; 0 = at once): a backup applies the newest checkpointed state
            to its server at most this often, and always before it takes over.
        ~replaces (str, default none): the primary After this one replaces (an adaptation's update):
            the backup then follows this one's checkpoints instead.
        ~witness (str, default ''): the witness's aft_msgs/Witness service ('' : no witness).
        ~in_sync (bool, false): started by an adaptation beside its new primary (or backup), the pair
            quiescent: a backup follows the primary from its first checkpoint instead of joining.
        ~site, ~peer (str, required with a witness): this replica's site and the other one.
        ~site_pid (int, default: the parent process, the site's roslaunch): the site's incarnation.
        ~join_period (float, 0.5 s): a joining backup asks for a state transfer this often.
        ~state_timeout (float, 5 s): the longest a get_state or set_state call may take. A promotion
            waits for a set_state past it up to this long more (the server is slow: the After still
            holds the state), then sets the newest state.
        ~protocol (str, default protocol): this replica's Protocol, suspended (quiescent) while a state
            transfer is captured, so that the state holds exactly the requests whose replies it carries.
        ~cache_bytes (int, 64 MiB): bound of the replies kept for a state transfer (those clients
            have not confirmed); the Protocol's reply cache has the same bound and refuses first.
        ~incremental (bool, true): a checkpoint carries what changed in the state since the previous
            one (aft_ftm.delta, computed here from getState: no change to the server), when that is
            under half the state; the backup rebuilds the whole state, checks it (CRC) and refuses a
            delta that does not apply (it joins again). A state transfer is always whole.
        ~delta_min_bytes (int, 1024): states smaller than this are always sent whole.
        ~server_changes (bool, true): where the server offers ``<get_state>_delta`` (aft_msgs/GetStateDelta:
            what changed since a version it named), the primary asks it after each request instead of the whole
            state, applies the runs to the state it checkpointed last and checks the result against the server's
            CRC. Changes that do not rebuild the server's state, or 3 failed calls in a row, raise the
            ``server_changes_refused`` alarm, that checkpoint is made from the whole state, and the server's changes
            are not asked again. A failed call is the first of the capture's two tries. They are asked only
            while the state is at least ~delta_min_bytes (below, it goes whole anyway, and getState is cheaper).
        ~chunk_bytes (int, 1 MiB; 0 = one message): a state transfer (a join) goes in parts of at most this
            many bytes of state (aft_ftm.transfer), ...
        ~transfer_window (int, 4): ... at most this many parts sent and not yet acknowledged (back-pressure):
            the ack timeout then counts from the last part acknowledged, and the checkpoints made meanwhile
            wait until the last part is sent.
        ~catch_up (bool, true): while a joiner receives its state transfer, replies go to the clients at once
            (as ALONE: the witness does not count on the joiner yet) and their checkpoints follow the transfer;
            replies are held again from the transfer's acknowledgment, and the joiner is admitted once it
            acknowledged every checkpoint sent meanwhile. False: every reply waits from the transfer on.
    Services called:
        get_state (aft_msgs/GetState), set_state (aft_msgs/SetState): the server's state manager;
        <get_state>_delta (aft_msgs/GetStateDelta), where the server offers it.
        the witness (aft_msgs/Witness).
    Subscribes:
        prd2aft (aft_msgs/Reply), port ``inp``
        acks (aft_msgs/CheckpointAck), port ``acks``: the backup's acknowledgments
        peer_checkpoints (aft_msgs/Checkpoint), port ``peer_checkpoints``: the primary's checkpoints
        join_requests (aft_msgs/Join), port ``join_requests``: a backup asking for a state transfer
        <witness>'s configuration (aft_msgs/Configuration; its node's ~configuration): deposed or excluded by the witness
    Publishes:
        aft2pro (aft_msgs/Reply), port ``out``
        checkpoints (aft_msgs/Checkpoint), port ``checkpoints``: to the backup's After
        peer_acks (aft_msgs/CheckpointAck), port ``peer_acks``: to the primary's After
        aft2pro_s (aft_msgs/Checkpoint), port ``stored``: replies for this replica's Protocol
        join (aft_msgs/Join), port ``join``: to the primary's After
        fail_stop (aft_msgs/Failure), port ``fail_stop``; alarms (aft_msgs/Alarm), port ``alarms``
        ~events (std_msgs/String, latched): one JSON record per state transfer this After sent (joiner,
            bytes of state, parts, replies, seconds until acknowledged and until admitted)
        /diagnostics (diagnostic_msgs/DiagnosticArray): role, epoch, held replies, whether a backup may
            take over (aft_ftm.health)
    Services:
        ~rebind (aft_msgs/Rebind), ~set_role (aft_msgs/SetRole), ~suspend, ~resume (aft_msgs/Suspend)
        ~stored_replies (aft_msgs/StoredReplies): every reply held, as of the last checkpoint applied, for
            its Protocol about to take over when messages that stored some of them were lost.
    """
    MECHANISM = 'pbr'
    WAIT_OUTPUTS = ('stored',)
    CHANGES_FAILURES = 3   # the server's changes failing this many calls in a row are asked no more

    def __init__(self):
        role = ROLES[param('role', config.choice(*ROLES), 'primary')]
        self.ack_timeout = param('ack_timeout', config.positive_float, 1.0)
        self.admission = AdmissionGate(self.ack_timeout)   # a joiner admitted only while its site is heard
        self.connect_timeout = param('connect_timeout', config.positive_float, 10.0)
        self.apply_period = param('apply_period', config.non_negative_float,
                                  0.01)
        self.replaces = param('replaces', config.non_empty_str, '')
        self.witness_service = param('witness', config.witness_service, '')
        with_witness = bool(self.witness_service)
        self.site = param('site', config.non_empty_str, required=with_witness) or ''
        self.peer = param('peer', config.non_empty_str, required=with_witness) or ''
        self.site_pid = param('site_pid', config.non_negative_int, site_launcher_pid())
        self.join_period = param('join_period', config.positive_float, 0.5)
        self.state_timeout = param('state_timeout', config.positive_float, 5.0)
        self.batch_gap = param('batch_gap', config.positive_float, 30.0)
        cache_bytes = param('cache_bytes', config.non_negative_int, 64 << 20)
        # Checkpoints are numbered from the wall clock (microseconds), so that an After replacing
        # another one (an adaptation) numbers above it: the backup's Protocol compares them.
        self.first_seq = int(time.time() * 1e6)
        self.pending_state = None   # backup: the newest checkpointed state not yet applied
        super(PbrAfterNode, self).__init__(
            extra_ports=[PortSpec('checkpoints', PUBLISH, 'aft_msgs/Checkpoint'),
                         PortSpec('acks', SUBSCRIBE, 'aft_msgs/CheckpointAck'),
                         PortSpec('peer_checkpoints', SUBSCRIBE, 'aft_msgs/Checkpoint'),
                         PortSpec('peer_acks', PUBLISH, 'aft_msgs/CheckpointAck'),
                         PortSpec('stored', PUBLISH, 'aft_msgs/Checkpoint')] + list(SIDE_PORTS),
            extra_callbacks={'acks': self._on_ack, 'peer_checkpoints': self._on_checkpoint,
                             'join_requests': self._on_join})
        # The replica's role has one owner: the CheckpointSender once there is one (a primary, or a
        # promoted backup), else the CheckpointReceiver (see the role property).
        self.sender = CheckpointSender(role, self.first_seq) if role != Role.BACKUP else None
        self.in_sync = param('in_sync', config.flag, False)
        self.receiver = CheckpointReceiver(join=with_witness) if role == Role.BACKUP else None
        if self.receiver is not None and with_witness and self.in_sync:
            self.receiver.in_sync()
        if self.receiver is not None and self.peer:
            self.receiver.expect = '/%s/' % self.peer
        self.recent = DuplicateCache(0, cache_bytes)   # replies a state transfer carries: never evicted
        self.group = GroupCommit()  # primary: the replies of a batch until its last (the Protocol's ~max_batch)
        self.incremental = param('incremental', config.flag, True)
        self.encoder = DeltaEncoder(param('delta_min_bytes', config.non_negative_int, 1024))
        self.use_server_changes = param('server_changes', config.flag, True) and self.incremental
        self.server_changes = None   # the server's <get_state>_delta, once found at set-up
        self.changes_failures = 0    # its calls failed in a row
        self.decoder = DeltaDecoder()
        self.chunk_bytes = param('chunk_bytes', config.non_negative_int, 1 << 20)
        self.transfer_window = param('transfer_window', config.positive_int, 4)
        self.catch_up = param('catch_up', config.flag, True)
        self.outgoing = None        # primary: the state transfer in parts being sent (aft_ftm.transfer)
        self.outgoing_template = None   # its checkpoint (every field but the state)
        # The parts, and the checkpoints behind them, are written by a thread of their own, in order: a
        # publisher writes synchronously, and a part on a slow link must not hold the lock the replies need.
        self.outbox = queue.Queue()
        self.parts_dropped = 0      # parts of transfers given up, never written (_write_outbox)
        self.deferred = []          # primary: checkpoints made while its parts are sent, sent after its last
        self.incoming = Incoming()  # backup: the parts of the state transfer being received
        self.joiner = None          # (site, incarnation) of the backup being joined
        self.joiner_epoch = 0       # the epoch its state transfer was made in
        self.join_record = None     # the state transfer under way, for ~events
        self.lock = threading.Lock()
        # backup: a set_state made by the applier runs outside self.lock (a large state takes tens of ms,
        # and the checkpoints behind it are acknowledged meanwhile); one at a time, and whoever must
        # apply under self.lock (a promotion, a suspension) waits for it first (self.applied)
        self.applying = False
        self.applied = threading.Condition(self.lock)
        self.next_apply = 0.0   # monotonic: the applier's next call not before (see APPLY_SHARE)
        self.promoting = 0      # promotions waiting for the applier: a set_state past its deadline is not fatal
        protocol = param('protocol', config.non_empty_str, 'protocol') if with_witness else ''
        self.side = ReplicaSide(self.ports, 'pbr', self.site, self.site_pid, self.witness_service, protocol,
                                self.state_timeout)
        self.witness = self.side.witness
        self.state_calls = Deadline('state', exclusive=True)   # a late set_state must not overtake a newer one
        self.get_state = PersistentService('get_state', GetState)
        self.set_state = PersistentService('set_state', SetState)
        self.configuration_seen = None   # the witness's newest configuration
        self.followed_since = 0.0   # when the last state transfer was accepted

    def setup(self, timeout):
        for name in ('checkpoints', 'peer_acks', 'acks', 'peer_checkpoints', 'join', 'join_requests', 'fail_stop'):
            self.ports.bind(name)
        self.ports.bind('stored', 'aft2pro_s')
        self.ports.bind('alarms', '/aft/alarms')
        if self.witness is not None and not self.witness.setup(timeout):
            return False
        try:
            rospy.wait_for_service('get_state', timeout)
            rospy.wait_for_service('set_state', timeout)
            # Opened now: a promoted backup's first state call must not need the master.
            self.get_state.connect()
            self.set_state.connect()
        except (rospy.ROSException, rospy.ServiceException) as e:
            rospy.logerr('%s: the server state manager (%s, %s) is not available: %s', self.name,
                         rospy.resolve_name('get_state'), rospy.resolve_name('set_state'), e)
            return False
        if self.use_server_changes:
            self._find_server_changes()
        if self.witness is None or self.in_sync:
            peer_ports = {Role.PRIMARY: ['checkpoints', 'acks'], Role.BACKUP: ['peer_checkpoints', 'peer_acks'],
                          Role.ALONE: []}[self.role]
            missing = wait_for_connections(self.ports, peer_ports, self.connect_timeout)
            if missing:
                rospy.logerr('%s: the peer After is not connected on %s within %.1f s', self.name,
                             [self.ports.topic(n) for n in missing], self.connect_timeout)
                return False
        if self.role == Role.BACKUP:
            missing = wait_for_connections(self.ports, ['stored'], timeout)
            if missing:
                rospy.logerr('%s: the Protocol is not connected to %s', self.name, self.ports.topic('stored'))
                return False
        if not super(PbrAfterNode, self).setup(timeout):
            return False
        self.timer = rospy.Timer(rospy.Duration(min(0.1, self.ack_timeout / 4)), self._check_acks)
        threading.Thread(target=self._write_outbox, name='transfer-outbox', daemon=True).start()
        if self.apply_period > 0:
            self.applier = rospy.Timer(rospy.Duration(self.apply_period), self._apply_pending)
        if self.witness is not None:
            self.joiner_timer = rospy.Timer(rospy.Duration(self.join_period), self._ask_to_join)
            self.configuration = self.witness.subscribe(self._on_configuration, report=lambda detail: alarm(self.ports, 'witness', 'forged_configuration', detail))
        self.events = rospy.Publisher('~events', String, queue_size=10, latch=True)
        rospy.Service('~set_role', SetRole, self._on_set_role)
        rospy.Service('~stored_replies', StoredReplies, self._on_stored_replies)
        rospy.loginfo('%s: ready as %s', self.name, self.role.name)
        return True

    def _on_stored_replies(self, _req):
        """Every reply held, for the Protocol about to take over (some messages that stored them may be lost)."""
        with self.lock:
            if self.receiver is None or not self.receiver.sender:
                return StoredRepliesResponse(success=False, message='%s follows no primary' % self.name)
            if self.receiver.state != Follow.PROMOTED:
                # only the After taking over answers (not one an adaptation replaced, still following)
                return StoredRepliesResponse(success=False, message='%s is not taking over (%s)'
                                             % (self.name, self.receiver.state.name))
            return StoredRepliesResponse(success=True, message='', seq=self.receiver.last_seq,
                                         sender=self.receiver.sender, epoch=self.receiver.epoch,
                                         cache=self.recent.replies())

    @property
    def role(self):
        """This replica's role, read from its one owner (changed only through the sender's and the
        receiver's guarded methods)."""
        return self.sender.role if self.sender is not None else self.receiver.role

    def health(self):
        with self.lock:
            sender, receiver = self.sender, self.receiver
            epoch = sender.epoch if sender is not None else receiver.epoch if receiver is not None else 0
            extra = [('following', receiver.state.name), ('last_checkpoint', receiver.last_seq)] \
                if receiver is not None and self.role == Role.BACKUP else []
            if sender is not None:   # what the checkpoints' states cost, against whole states every time
                extra += [('checkpoint_state_bytes', self.encoder.sent_bytes),
                          ('whole_state_bytes', self.encoder.state_bytes),
                          ('state_changes', ('told by the server' if self.encoder.wants_changes() else
                                             'told by the server from %d bytes' % self.encoder.min_size)
                           if self.server_changes is not None else
                           'computed here' if self.incremental else 'none (whole states)')]
            return health.replica_after(
                self.site, 'pbr', self.role, epoch, self.peer, held=len(sender.held) if sender is not None else 0,
                stopped='deposed: %s' % sender.deposed if sender is not None and sender.deposed else None,
                cannot_take_over=receiver.invalid if receiver is not None and self.role == Role.BACKUP else None,
                extra=extra)

    # -- suspension (adaptation) ---------------------------------------------------
    def quiescent(self):
        """Primary: every checkpoint acknowledged (no reply held), no batch gathering."""
        with self.lock:
            return self.sender is None or not (self.sender.held or self.group.replies)

    def before_suspend(self):
        """Backup: apply the newest checkpointed state now, so a replacement After (or another
        mechanism) finds the server up to date."""
        with self.lock:
            self._wait_applier()
            self._apply_locked()

    # -- helpers ------------------------------------------------------------------------
    def _remember(self, reply):
        self.recent.forget_below(reply.origin, reply.oldest_pending)
        self.recent.store(reply)

    def _find_server_changes(self):
        """Use the server's <get_state>_delta if it offers one (advertised before its get_state)."""
        name = rospy.resolve_name('get_state') + '_delta'
        try:
            rospy.wait_for_service(name, 0.5)   # advertised before get_state: there now, if offered
            changes = PersistentService(name, GetStateDelta)
            changes.connect()
        except (rospy.ROSException, rospy.ServiceException):
            rospy.loginfo('%s: the server offers no %s: deltas are computed here from its whole state',
                          self.name, name)
            return
        self.server_changes = changes
        rospy.loginfo('%s: the server tells its own state changes (%s)', self.name, name)

    def _checkpoint_state(self):
        """(payload, is_delta, None) for the checkpoint of the state after the requests run, from the
        server's own changes where it tells them, else from its whole state; (None, False, error) if the
        state cannot be had."""
        tries = 2
        if self.server_changes is not None and self.encoder.wants_changes():
            since = self.encoder.version or ''
            name = self.server_changes.resolved_name
            try:
                answer = self.state_calls.call(self.server_changes, self.state_timeout, since)
                changes = self.encoder.next_changes(ServerChanges.from_message(answer))
                self.changes_failures = 0
                return changes + (None,)
            except DeltaError as e:
                # Never sent: the backup holds the last checkpoint, and the whole state is captured below.
                self._stop_server_changes('the changes of %s refused: %s' % (name, e))
            except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
                # The call counts as the first of the capture's two tries (a timed-out call stays pending,
                # and the capture then fails at once, as a hung getState did).
                tries = 1
                self.changes_failures += 1
                if self.changes_failures >= self.CHANGES_FAILURES:
                    self._stop_server_changes('%d calls of %s in a row failed, the last: %s'
                                              % (self.changes_failures, name, e))
                else:
                    rospy.logwarn('%s: %s failed (%s); the whole state is captured', self.name, name, e)
                    self.server_changes = self.server_changes.fresh()
        state, error = self._capture(tries)
        if state is None:
            return None, False, error
        return self.encoder.next(state) + (None,) if self.incremental else (state, False, None)

    def _stop_server_changes(self, why):
        """Ask the server's changes no more (an alarm: every checkpoint now costs a whole getState)."""
        self.server_changes = None
        alarm(self.ports, 'pbr', 'server_changes_refused', '%s: %s; the whole state is captured from now on'
              % (self.site or self.name, why))

    def _capture_whole(self):
        """(the server's whole state, its version or None, None) for a state transfer, or (None, None, why).
        Asked through the server's changes where it tells them: since the version of the state held (the
        last checkpoint's), or since none (the whole state then comes with its version), so the
        checkpoints after the transfer are the server's changes since it (with plain getState the first
        of them would cost a whole state again: 40 ms at 10 MB)."""
        tries = 2
        if self.server_changes is not None:
            # The state of the last checkpoint is held with its version (a primary alone since): the
            # server's changes since then bring it up to date, with no whole state through a service call
            # (10 MB: 44 ms of the join's pause).
            since = self.encoder.version if self.encoder.base is not None else None
            try:
                told = ServerChanges.from_message(self.state_calls.call(self.server_changes, self.state_timeout,
                                                                        since or ''))
                if told.state is not None:
                    return told.state, told.version, None
                if since:
                    self.encoder.follow(told)
                    return self.encoder.base.bytes(), self.encoder.version, None
            except DeltaError as e:   # the base unchanged; as for a checkpoint, never asked again
                self._stop_server_changes('the changes of %s refused: %s' % (self.server_changes.resolved_name, e))
            except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
                tries = 1   # the first of the capture's two tries, as in _checkpoint_state
                rospy.logwarn('%s: %s failed (%s); the whole state is captured', self.name,
                              self.server_changes.resolved_name, e)
                self.server_changes = self.server_changes.fresh()
        state, error = self._capture(tries)
        return state, None, error

    def _capture(self, tries=2):
        """The server's state, tried twice (tries) within ~state_timeout each; None if it cannot be had."""
        error = None
        for _ in range(tries):
            try:
                return self.state_calls.call(self.get_state, self.state_timeout).state, None
            except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
                error = e
                self.get_state = self.get_state.fresh()
        return None, error

    # -- primary ----------------------------------------------------------------
    def handle(self, reply):
        with self.lock:
            if self.sender is None or self.sender.deposed:
                return None   # a backup has nothing to reply; a deposed primary answers nothing
            reply.epoch = self.sender.epoch
            self._remember(reply)
            if not self.sender.needs_checkpoint():
                # Alone: nothing to checkpoint; a batch gathered while there was a backup goes out with it.
                self._release(self.group.flush())
                return reply
            try:
                replies = self.group.add(reply, time.monotonic())
            except BatchError as e:
                self.sender.depose('group commit broken: %s' % e)
                problem = 'group commit broken: %s' % e
                replies = None
            else:
                if replies is None:
                    return None   # more of its batch are executing: one checkpoint covers them all
                if all(is_refusal(r) for r in replies):
                    # A refusal changes no state (and the state may already hold the request executing now,
                    # its reply not here yet): the checkpoint carries the refusal alone, so that the backup
                    # answers a copy of the request the same way.
                    seq = self.sender.hold(replies[-1], time.monotonic(), replies[:-1])
                    self._send_checkpoint(Checkpoint(
                        seq=seq, first_seq=self.first_seq, sender=self.name, replaces=self.replaces,
                        reply=replies[-1], batch=replies[:-1], epoch=self.sender.epoch))
                    if self.sender.releases_at_once(seq):
                        self._release(replies)   # a joiner catching up: nobody counts on it yet
                    return None
                payload, delta, error = self._checkpoint_state()
                if payload is None:
                    # The requests ran but cannot be checkpointed: replying would leave the backup behind.
                    # Fail-stop: this site falls silent, the backup takes over and executes the requests
                    # that the Proxies re-send.
                    self.sender.depose('cannot capture the server state')
                    problem = 'cannot capture the server state after %s/%d: %s' % (reply.origin, reply.id, error)
                else:
                    seq = self.sender.hold(replies[-1], time.monotonic(), replies[:-1])
                    self._send_checkpoint(Checkpoint(
                        seq=seq, first_seq=self.first_seq, sender=self.name, replaces=self.replaces,
                        reply=replies[-1], batch=replies[:-1], state=payload, delta=delta, epoch=self.sender.epoch))
                    if self.sender.releases_at_once(seq):
                        self._release(replies)   # a joiner catching up: nobody counts on it yet
                    return None
        self.side.fail_stop(problem)
        return None

    def _release(self, replies):
        for reply in replies:
            self.ports.publish('out', reply)

    def _send_checkpoint(self, cp):
        """Publish a checkpoint, or (a state transfer's parts still to send) queue it behind them: the
        joiner must hold the whole transfer before the checkpoints that follow it."""
        if self._transfer_live() and not self.outgoing.all_sent():
            self.deferred.append(cp)
        elif self.outbox.unfinished_tasks:
            self.outbox.put(cp)   # behind what the outbox has still to write
        else:
            self.ports.publish('checkpoints', cp)

    def _write_outbox(self):
        while not rospy.is_shutdown():
            try:
                cp = self.outbox.get(timeout=0.5)
            except queue.Empty:
                continue
            try:
                if cp.parts > 1 and not self._part_live(cp.seq):
                    # A part of a transfer given up (the joiner excluded): never written. Each retry
                    # queued behind the last one's unwritten parts on a slow link, and the outbox grew
                    # without bound (50 MB in 30 s) while the joiner was never admitted (review of stop 39).
                    self.parts_dropped += 1
                    continue
                self.ports.publish('checkpoints', cp)
            except rospy.ROSException as e:   # shutting down: nothing more leaves
                rospy.logwarn('%s: checkpoint %d not sent: %s', self.name, cp.seq, e)
            finally:
                self.outbox.task_done()

    def _part_live(self, seq):
        """Whether a part of transfer ``seq`` is still to be sent: that transfer is the join under way."""
        out, sender = self.outgoing, self.sender
        return out is not None and out.seq == seq and sender is not None and sender.join_seq == seq

    def _transfer_live(self):
        """The state transfer in parts is still the sender's join under way (else forget it)."""
        if self.outgoing is not None and (self.sender is None or self.sender.join_seq != self.outgoing.seq):
            self.outgoing, self.deferred = None, []
        return self.outgoing is not None

    def _send_parts(self, template):
        """Send the parts of the transfer the window allows now; after its last, what was queued behind."""
        out = self.outgoing
        for part in out.next_parts():
            last = part == out.count - 1
            self.outbox.put(Checkpoint(
                seq=out.seq, first_seq=self.first_seq, sender=self.name, replaces=self.replaces,
                epoch=template.epoch, full=True, state=out.parts[part], part=part, parts=out.count,
                cache=template.cache if last else []))
        if out.all_sent():
            deferred, self.deferred = self.deferred, []
            for cp in deferred:
                self.outbox.put(cp)

    def _on_part_ack(self, ack):
        """The joiner holds parts 0 .. ack.part of the transfer: send the next ones (back-pressure)."""
        problem = None
        with self.lock:
            if self.sender is None or not self._transfer_live() or ack.seq != self.outgoing.seq or not ack.ok:
                return
            try:
                if self.outgoing.acknowledged(ack.part):
                    self.sender.progress(ack.seq, time.monotonic())
                    self._send_parts(self.outgoing_template)
            except TransferError as e:
                problem = str(e)
        if problem:
            self._resolve(Need.EXCLUDE, 'the joiner acknowledged what was not sent: %s' % problem)

    def _on_ack(self, ack):
        if ack.to and ack.to != self.name:
            return   # another After's (both run side by side while an adaptation replaces one)
        # rospy gives every received message its publisher's node name in the connection header. An
        # ack from a node outside the peer's site (a stray or forged one) would release replies the
        # backup may not hold: ignored, with one alarm per sender (as LFR's leader does).
        sender = getattr(ack, '_connection_header', {}).get('callerid')
        if self.peer and sender and not sender.startswith('/%s/' % self.peer):
            self.side.tell('stray_ack', 'ack of checkpoint %d from %s ignored: %s is not in site %s, the peer '
                           'of %s' % (ack.seq, sender, sender, self.peer, self.name), sender)
            return
        if ack.partial:
            self._on_part_ack(ack)
            return
        with self.lock:
            if self.sender is None:
                return
            record = self.join_record
            if record is not None and ack.ok and ack.seq == record['seq'] and 'acknowledged_s' not in record:
                record['acknowledged_s'] = time.monotonic() - record['t0']
            released, need = self.sender.on_ack(ack.seq, ack.ok, time.monotonic())
            self._release(released)
        if need:
            self._resolve(need, 'the backup refused checkpoint %d: %s' % (ack.seq, ack.error) if not ack.ok
                          else 'the backup holds the state transfer %d' % ack.seq)

    def _check_acks(self, _event):
        with self.lock:
            broken = self.group.stalled(time.monotonic(), self.batch_gap) \
                if self.sender is not None and not self.sender.deposed else None
            if broken:
                self.sender.depose('group commit broken: %s' % broken)
        if broken:
            self.side.fail_stop('group commit broken: %s' % broken)
            return
        with self.lock:
            need = Need.NOTHING
            conf = self.configuration_seen
            # The witness names the peer this primary's backup while it checkpoints to nobody (ALONE, no
            # join under way): an ADMIT given up on and carried out late. A promotion would serve a state
            # without the replies released since: excluded, with an alarm (LFR's leader does the same).
            unfollowed = self.sender is not None and not self.sender.deposed and self.sender.role == Role.ALONE \
                and self.joiner is None and conf is not None and conf.primary == self.site and conf.backup \
                and conf.backup != self.site and conf.epoch >= self.sender.epoch
            if unfollowed:
                need = Need.EXCLUDE
            elif self.sender is not None and self.sender.overdue(time.monotonic(), self.ack_timeout):
                need = Need.EXCLUDE
            elif self.sender is not None and self.sender.ready_to_admit() and self.joiner is not None:
                need = Need.ADMIT   # the witness could not be reached earlier: ask again
        if unfollowed:
            self.side.tell('backup_unfollowed', 'the witness names %s the backup of epoch %d, but %s goes on alone '
                           'and checkpoints to nobody (an ADMIT answered after its caller gave up): it is excluded'
                           % (conf.backup, conf.epoch, self.site), key=('unfollowed', conf.epoch))
            self._resolve(need, '%s named the backup, but not followed' % conf.backup)
        elif need == Need.EXCLUDE:
            self._resolve(need, 'no acknowledgment from the backup for %.1f s' % self.ack_timeout)
        elif need == Need.ADMIT:
            self._resolve(need, 'the backup holds the state transfer')

    def _resolve(self, need, why):
        """Ask the witness what the sender needs, and carry out its answer."""
        # Being asked already: the timer asks again if still needed.
        self.side.alone(self._exclude if need == Need.EXCLUDE else lambda _why: self._admit(), why)

    def _exclude(self, why):
        grant = self.side.exclusion(self._deposed)
        if grant is None:
            return
        with self.lock:
            if self.sender is None or self.sender.role == Role.ALONE and not self.sender.held:
                if self.sender is not None:   # (an unfollowed backup excluded: that configuration is past)
                    self.sender.epoch = max(self.sender.epoch, grant.epoch)
                return
            released = self.sender.excluded(grant.epoch)
            self.joiner = None
            self._release(released)
        self.side.tell('alone', '%s goes on ALONE at epoch %d (%s); %s' % (self.site or self.name, grant.epoch, why,
                                                                       grant.message))

    def _admit(self):
        with self.lock:
            joiner, epoch = self.joiner, self.joiner_epoch
        if joiner is None:
            return
        unheard = self.side.joiner_unheard(joiner[0])   # heard when its join came (_on_join): still?
        if unheard:
            self._exclude('%s holds the state transfer, but is not admitted: %s' % (joiner[0], unheard))
            return
        grant = self.side.ask(Op.ADMIT, peer=joiner[0], peer_incarnation=joiner[1], epoch=epoch)
        if grant is None:
            return
        if not grant.granted:
            if grant.primary != self.site:
                self._deposed(grant.message)
            else:
                self._exclude('the witness refused to admit %s: %s' % (joiner[0], grant.message))
            return
        with self.lock:
            if self.sender is not None:
                self.sender.admit(grant.epoch)
            self.joiner = None
            record, self.join_record = self.join_record, None
        if record is not None:
            record.update(admitted_s=time.monotonic() - record.pop('t0'), admitted_wall=time.time(), epoch=grant.epoch)
            self.events.publish(String(data=json.dumps(record, sort_keys=True)))
        self.side.told.clear()
        rospy.loginfo('%s: %s is the backup again (epoch %d)', self.name, joiner[0], grant.epoch)

    def _deposed(self, why):
        with self.lock:
            withheld = self.sender.depose(why) if self.sender is not None else 0
        self.side.fail_stop('deposed by the witness (%s): %d replies withheld' % (why, withheld))

    def _on_join(self, join):
        if join.site == self.site:
            return
        need = Need.NOTHING
        with self.lock:
            sender = self.sender
            if sender is None or sender.deposed:
                return
            if sender.role == Role.PRIMARY:
                if sender.joiner != join.after and join.last_seq == 0:
                    need = Need.EXCLUDE   # our backup started again: it holds nothing any more
                else:
                    return                # joining it already: its acknowledgment (or the ack timeout) decides
        if need:
            self._resolve(need, '%s asks to join again: it restarted' % join.site)
            return
        if self.side.join_waits(self.admission, self.lock, join):
            return   # only a site that runs gets the state: not heard yet, it asks again
        # The state must include exactly the requests whose replies it carries: capture it while the
        # Protocol is quiescent (suspended: no request executing, new ones held), then let it go on.
        if not self.side.quiesce_protocol(True):
            return
        try:
            self._transfer(join)
        finally:
            self.side.quiesce_protocol(False)

    def _transfer(self, join):
        with self.lock:
            sender = self.sender
            if sender is None or sender.deposed or sender.role != Role.ALONE:
                return
            state, version, error = self._capture_whole()
            if state is None:
                self.side.tell('join_failed', 'cannot transfer the state to %s: %s' % (join.site, error))
                return
            # The capture may take up to two state timeouts, as long as the Protocol's suspension lease:
            # if it ran out, the Protocol resumed and forwarded requests the state may or may not hold,
            # and a batch of them straddled the join (released alone, then found broken: the only
            # serving site fail-stopped). Still held (renewed for the rest of the join), it ran nothing.
            why = self.side.hold_protocol(2 * self.state_timeout)
            if why:
                self.side.tell('join_failed', 'cannot transfer the state to %s: the Protocol is not held (%s); '
                               'it asks again' % (join.site, why))
                return
            seq = sender.join(join.after, time.monotonic(), catch_up=self.catch_up)
            # the joiner holds this state: the next checkpoints are deltas on it (the server's changes since
            # its version, when it told it)
            self.encoder.reset(state, version)
            self.joiner = (join.site, join.incarnation)
            self.joiner_epoch = sender.epoch   # admitted only in this epoch (a late ADMIT is refused)
            cache = self.recent.replies()
            out = Outgoing(seq, state, self.chunk_bytes, self.transfer_window)
            self.join_record = {'event': 'join', 'joiner': join.site, 'seq': seq, 'state_bytes': len(state),
                                'replies': len(cache), 'parts': out.count, 't0': time.monotonic(),
                                'sent_wall': time.time()}
            template = Checkpoint(seq=seq, first_seq=self.first_seq, sender=self.name, replaces=self.replaces,
                                  epoch=sender.epoch, full=True, state=state, cache=cache)
            self.outgoing, self.deferred = None, []
            if out.count == 1:
                self.ports.publish('checkpoints', template)
            else:
                template.state = b''   # the parts carry it
                self.outgoing, self.outgoing_template = out, template
                self._send_parts(template)
            rospy.loginfo('%s: state transfer %d to %s (%d bytes of state in %d part(s), %d replies)', self.name, seq,
                          join.site, len(state), out.count, len(cache))

    # -- backup -----------------------------------------------------------------
    def _ask_to_join(self, _event):
        stuck = None
        with self.lock:
            if self.role != Role.BACKUP or self.receiver is None:
                return
            if self.receiver.state == Follow.FOLLOWING:
                # Joined, but never admitted (the primary gave the join up, or the witness refused it):
                # nobody counts on this backup; it must not think it is one. Join again.
                conf = self.configuration_seen
                waited = time.monotonic() - self.followed_since
                if conf is not None and self.site not in (conf.primary, conf.backup) \
                        and waited > max(2 * self.ack_timeout, 4 * self.join_period):
                    stuck = (self.receiver.sender, waited)
            if self.receiver.state != Follow.JOINING and stuck is None:
                return
        if stuck is not None:
            # The configuration naming this site may have been missed (a partition to the witness): ask it.
            status = self.side.ask(Op.STATUS)
            if status is None or status.backup == self.site:
                return
            with self.lock:
                if self.receiver.state != Follow.FOLLOWING or self.receiver.sender != stuck[0]:
                    return
                self.receiver.failed(self.receiver.last_seq, 'not admitted by the witness %.1f s after its state '
                                     'transfer (epoch %d)' % (stuck[1], status.epoch))
                self.pending_state = None
                why = self.receiver.invalid
            self.side.tell('backup_invalid', '%s: %s; it joins again' % (self.site, why))
            return
        if not self.ports.connections('peer_checkpoints'):
            return   # the state transfer would be lost: ask once the primary's checkpoints reach us
        self.ports.publish('join', Join(site=self.site, after=self.name, incarnation=self.witness.incarnation,
                                        last_seq=0, stamp=rospy.Time.now()))

    def _on_checkpoint(self, cp):
        with self.lock:
            if self.receiver is None:
                decision = Decision.FENCED
            else:
                decision = self.receiver.decide(cp.seq, cp.sender, cp.first_seq, cp.replaces, cp.epoch, cp.full)
            error = refused_transfer = ''
            if decision in (Decision.APPLY_FULL, Decision.APPLY) and cp.full and cp.parts > 1:
                # A state transfer in parts: acknowledge each, apply nothing before the last. (Whatever the
                # receiver decided: one that followed nobody yet, or took the sender for a replacement, got
                # APPLY, and set the first part as the whole state, review of stop 39.)
                cp.state, error = self.incoming.take(cp)
                if error:
                    refused_transfer, decision = error, Decision.GAP
                elif cp.state is None:
                    self.ports.publish('peer_acks', CheckpointAck(seq=cp.seq, ok=True, partial=True, part=cp.part,
                                                                  epoch=self.receiver.epoch, to=cp.sender))
                    return
                else:
                    decision = Decision.APPLY_FULL   # the whole state, and the replies its last part carries
            if decision == Decision.GAP and not refused_transfer:
                error = 'checkpoint %d received after %d: one is missing' % (cp.seq, self.receiver.last_seq)
            elif decision == Decision.JOINING:
                error = '%s holds no state yet: it is joining' % self.name
            elif decision == Decision.STRAY:
                error = '%s does not follow %s' % (self.name, cp.sender)
            elif decision == Decision.STALE:
                error = 'checkpoint of epoch %d, older than epoch %d' % (cp.epoch, self.receiver.epoch)
            elif decision == Decision.FENCED:
                error = ('%s is no longer a backup of %s%s' % (self.name, cp.sender, ': ' + self.receiver.invalid
                         if self.receiver is not None and self.receiver.invalid else ''))
            state = None
            if decision == Decision.APPLY_FULL or decision == Decision.APPLY \
                    and not all(is_refusal(r) for r in list(cp.batch) + [cp.reply]):   # refusals carry no state
                try:
                    state = self.decoder.state(cp.state, cp.delta)
                except DeltaError as e:
                    # Refused, changing nothing: this backup no longer mirrors its primary (it joins again).
                    error = 'checkpoint %d from %s: %s' % (cp.seq, cp.sender, e)
                    decision = Decision.GAP
            tell = None
            if decision in HARMLESS:
                tell = ('%s_checkpoint' % decision.name.lower(), 'checkpoint %d from %s refused, nothing changed: %s'
                        % (cp.seq, cp.sender, error), cp.sender)
            elif error and decision != Decision.JOINING and self.receiver is not None \
                    and self.receiver.state == Follow.FOLLOWING:
                # A backup that refuses its primary's checkpoint no longer mirrors it: it must never take
                # over with what it has (with a witness it joins again).
                self.receiver.failed(cp.seq, error)
                tell = ('backup_invalid', '%s cannot take over: %s%s' % (
                    self.site or self.name, error, '; it joins again' if self.receiver.join else ''), None)
            elif error and (self.receiver is None or decision == Decision.FENCED):
                tell = ('stale_checkpoint', 'checkpoint %d from %s refused: %s' % (cp.seq, cp.sender, error),
                        cp.sender)
            elif refused_transfer:
                tell = ('join_failed', '%s: %s; it asks again' % (self.site or self.name, refused_transfer), None)
            # Acknowledged once held. A promotion takes this lock and applies the state first.
            epoch = self.receiver.epoch if self.receiver is not None else self.sender.epoch
            if decision in (Decision.APPLY, Decision.APPLY_FULL):
                self.receiver.accept(cp.seq, cp.sender, cp.epoch, cp.first_seq)
                epoch = self.receiver.epoch
            self.ports.publish('peer_acks', CheckpointAck(seq=cp.seq, ok=not error, error=error, epoch=epoch,
                                                          to=cp.sender))
            if decision == Decision.APPLY:
                for reply in list(cp.batch) + [cp.reply]:
                    self._remember(reply)
                self.ports.publish('stored', Checkpoint(seq=cp.seq, first_seq=cp.first_seq, sender=cp.sender,
                                                        reply=cp.reply, batch=cp.batch, epoch=cp.epoch))
            elif decision == Decision.APPLY_FULL:
                for reply in cp.cache:
                    self._remember(reply)
                self.ports.publish('stored', Checkpoint(seq=cp.seq, first_seq=cp.first_seq, sender=cp.sender, full=True,
                                                        cache=cp.cache, epoch=cp.epoch))
            if decision == Decision.APPLY_FULL:
                self.followed_since = time.monotonic()
            if state is not None:
                self.decoder.accept(state)
                self.pending_state = (cp.seq, state)
                if decision == Decision.APPLY_FULL:
                    # A state transfer: set into the server a little later (the applier's set_state of a
                    # large state holds this process's interpreter for tens of ms; the checkpoints that
                    # follow the transfer are acknowledged first). A promotion applies it at once.
                    self.next_apply = max(self.next_apply, time.monotonic() + min(
                        1.0, FULL_APPLY_DELAY_PER_MB * len(state) / 1e6))
                if self.apply_period == 0:
                    self._apply_locked()
        if tell is not None:
            self.side.tell(*tell)
        if decision == Decision.APPLY_FULL:
            rospy.loginfo('%s: joined %s at checkpoint %d (epoch %d)', self.name, cp.sender, cp.seq, cp.epoch)

    def _apply_pending(self, _event=None):
        """The applier (every ~apply_period): the newest checkpointed state to the server, the call made
        outside self.lock, so that the checkpoints arriving meanwhile are acknowledged at once (a 10 MB
        state's set_state once held them for its whole length, a join's pause with it)."""
        with self.lock:
            if self.applying or time.monotonic() < self.next_apply:
                return
            taken = self._take_pending()
            if taken is None:
                return
            self.applying = True
        error, late = '', False
        started = time.monotonic()
        try:
            error, late = self._set_server_state(taken[1])
        except Exception as e:   # never a state lost without a word (the Timer thread goes on)
            error = 'cannot set the server state: %s' % e
        finally:
            with self.lock:
                ended = time.monotonic()
                self.next_apply = ended + (ended - started) * (1.0 - APPLY_SHARE) / APPLY_SHARE
                self.applying = False
                if error and late and self.promoting:
                    # The server is slow, not wrong, and this After still holds the state: the promotion
                    # waiting for this call waits for the late one too, then sets the newest state.
                    rospy.logwarn('%s: %s (checkpoint %d): the promotion sets it once the server answers',
                                  self.name, error, taken[0])
                    if self.pending_state is None:
                        self.pending_state = (taken[0], taken[1])
                elif error:
                    self._apply_failed(taken[0], error, taken[2])
                self.applied.notify_all()

    def _take_pending(self):
        """(seq, state, sender) of the newest checkpointed state to apply, taken (self.lock held); None."""
        if self.pending_state is None or self.receiver is None or self.receiver.state != Follow.FOLLOWING \
                or self.receiver.invalid:
            return None
        (seq, state), self.pending_state = self.pending_state, None
        if isinstance(state, StateBuffer):   # the decoder's own, changed in place by the next checkpoints
            state = state.bytes()
        return seq, state, self.receiver.sender

    def _set_server_state(self, state):
        """One set_state of the server (at most one at a time: see self.applying): ('' or why it failed,
        whether the call was abandoned past ~state_timeout or held back by one that was: it may land)."""
        try:
            result = self.state_calls.call(self.set_state, self.state_timeout, state)
            return ('' if result.success else 'the server refused the state: %s' % result.message), False
        except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
            self.set_state = self.set_state.fresh()
            return 'cannot set the server state: %s' % e, isinstance(e, CallTimeout)

    def _wait_applier(self):
        """(self.lock held) Wait for the applier's set_state under way, if any. The lock is released
        meanwhile: a caller waits first, before it looks at the role or the state, so that nothing it
        checked changes under it (two promotions once both went through)."""
        while self.applying:
            self.applied.wait()

    def _apply_locked(self, patient=False):
        """Apply the newest checkpointed state to the server now (self.lock held, the applier waited
        for: a promotion, a suspension); on failure the backup is invalid. ``patient`` (a promotion):
        a set_state abandoned past ~state_timeout that may still land is waited for first, up to
        ~state_timeout more (an older state landing after the newest would undo it)."""
        self._wait_applier()   # (a no-op when the caller waited first, as it must)
        if patient:
            self._wait_abandoned()
        taken = self._take_pending()
        if taken is None:
            return
        error, _ = self._set_server_state(taken[1])
        if error:
            self._apply_failed(taken[0], error, taken[2])

    def _wait_abandoned(self):
        """(self.lock held) Wait for a set_state abandoned past its deadline, ~state_timeout at most, the
        lock released meanwhile as for the applier's call (anyone else waits for it as for the applier)."""
        late = self.state_calls.abandoned()
        if late is None:
            return
        rospy.logwarn('%s: a set_state abandoned past %.1f s has not returned: waiting for it (%.1f s at most) '
                      'before setting the newest state', self.name, self.state_timeout, self.state_timeout)
        self.applying = True
        self.lock.release()
        try:
            concurrent.futures.wait([late], self.state_timeout)
        finally:
            self.lock.acquire()
            self.applying = False
            self.applied.notify_all()

    def _apply_failed(self, seq, error, sender):
        """The server refused (or never took) the state of checkpoint seq: this backup can no longer take
        over (self.lock held). Moot if it follows another primary since, or is invalid already."""
        if self.receiver is None or self.receiver.state != Follow.FOLLOWING or self.receiver.invalid \
                or self.receiver.sender != sender:
            rospy.logwarn('%s: %s (checkpoint %d of %s; moot now)', self.name, error, seq, sender)
            return
        self.receiver.failed(seq, error)
        rospy.logerr('%s: %s', self.name, self.receiver.invalid)
        self.ports.publish('peer_acks', CheckpointAck(seq=seq, ok=False, error=self.receiver.invalid,
                                                      epoch=self.receiver.epoch, to=sender or ''))
        alarm(self.ports, 'pbr', 'backup_invalid', '%s cannot take over: %s' % (
            self.site or self.name, self.receiver.invalid))

    # -- the witness's configuration ----------------------------------------------------
    def _on_configuration(self, conf):
        deposed = excluded = False
        with self.lock:
            if self.configuration_seen is None or conf.epoch >= self.configuration_seen.epoch:
                self.configuration_seen = conf
            if self.sender is not None and not self.sender.deposed and conf.epoch > self.sender.epoch \
                    and conf.primary != self.site:
                deposed = True
            elif self.sender is not None and conf.primary == self.site and self.sender.joiner is None:
                self.sender.epoch = max(self.sender.epoch, conf.epoch)   # an After an adaptation started
            elif self.receiver is not None and self.role == Role.BACKUP and conf.epoch > self.receiver.epoch \
                    and self.site not in (conf.primary, conf.backup) and self.receiver.state == Follow.FOLLOWING:
                self.receiver.failed(self.receiver.last_seq, 'excluded by the witness at epoch %d (%s)'
                                     % (conf.epoch, conf.reason))
                self.pending_state = None
                excluded = True
        if deposed:
            self._deposed('%s is the primary of epoch %d (%s)' % (conf.primary, conf.epoch, conf.reason))
        if excluded:
            self.side.tell('excluded', '%s was excluded at epoch %d (%s): it cannot take over and joins again'
                       % (self.site, conf.epoch, conf.reason))

    # -- role changes -----------------------------------------------------------
    def _on_set_role(self, req):
        role = Role(req.role)
        told_alone, took_over = False, None
        with self.lock:
            promotion = self.role == Role.BACKUP and role == Role.ALONE
            self.promoting += promotion   # (a count: another set_role meanwhile leaves it as it is)
            try:
                self._wait_applier()   # first: the role checked below stays what it is
                if self.role == Role.BACKUP and role == Role.ALONE:
                    self._apply_locked(patient=True)
                    last_seq = self.receiver.promote(initial=req.initial)
                    self.sender = CheckpointSender(Role.ALONE, self.first_seq, max(req.epoch, self.receiver.epoch))
                    took_over = None if req.initial else self.sender.epoch   # (read under the lock)
                elif self.role == Role.PRIMARY and role == Role.ALONE:
                    last_seq = self.sender.seq
                    if (req.epoch and req.epoch < self.sender.epoch) or self.sender.joiner is not None:
                        # A late order (Recovery stalled after the witness's vote) about a backup that has
                        # re-joined since, or one this After is joining itself: it changes nothing.
                        return SetRoleResponse(success=True, message='role PRIMARY kept: epoch %d is newer than %d'
                                               % (self.sender.epoch, req.epoch), last_seq=last_seq)
                    self._release(self.sender.excluded(req.epoch))
                    self.joiner = None
                    told_alone = True
                elif self.role == role:
                    if self.sender is not None:
                        self.sender.epoch = max(self.sender.epoch, req.epoch)
                    last_seq = self.receiver.last_seq if self.receiver else self.sender.seq
                else:
                    raise RoleError('role change %s -> %s is not allowed' % (self.role.name, role.name))
            except RoleError as e:
                return SetRoleResponse(success=False, message=str(e))
            finally:
                self.promoting -= promotion
        if told_alone:
            self.side.tell('alone', '%s goes on ALONE at epoch %d: its backup failed and the witness excluded it'
                       % (self.site or self.name, req.epoch))
        elif took_over is not None:   # its primary failed: no backup until a site joins, never silently
            self.side.tell('took_over', '%s is promoted at epoch %d and goes on ALONE: its primary failed; no backup until '
                           'a site joins' % (self.site or self.name, took_over))
        rospy.loginfo('%s: role is now %s (last checkpoint %d, epoch %d)', self.name, role.name, last_seq, req.epoch)
        return SetRoleResponse(success=True, message='role %s' % role.name, last_seq=last_seq)
