"""Leader-Follower Replication (paper Table II): the leader forwards each request to the follower,
both compute, the leader replies once the follower computed it too, then notifies it. No state is
transferred while both serve (bandwidth low), but the server must be deterministic. With a witness,
a follower joins by one state transfer (the server's getState/setState), as a PBR backup does.

The decisions (and each node's role) live in aft_ftm.lfr, without ROS; these nodes carry them out."""
import json
import queue
import threading
import time

import rospy
from aft_msgs.msg import Checkpoint, Join, Notify, Reply
from aft_msgs.srv import GetState, SetRole, SetRoleResponse, SetState
from std_msgs.msg import String

from .. import config, health, mechanisms
from ..checkpoint import AdmissionGate
from ..errors import RoleError
from ..lfr import Ack, ConfChange, Forwarded, JoinDecision, JoinStep, LfrAfter, LfrForwarder, Out, State
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import Role
from ..transfer import Incoming, Outgoing, TransferError
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


def _role():
    return ROLES[param('role', config.choice(*ROLES), 'primary')]


class LfrBeforeNode(BeforeNode):
    """LFR's Before. Leader: forwards each request to the follower, then to its own Proceed.
    Follower: passes the leader's forwarded requests to its Proceed, in the leader's order; once
    promoted (fenced) it refuses them. Each forwarded request carries the state transfer the
    follower joined with (Request.transfer); a follower refuses those forwarded before the transfer
    it joined with (they are in its transferred state: aft_ftm.lfr.LfrForwarder).

    Parameters: ~role (primary | backup | alone). With a witness, the After makes a leader's Before
    PRIMARY once a follower is admitted (SetRole last_seq: the follower's transfer, stamped on
    forwards) and ALONE once it is excluded; a follower's After makes its Before follow a state
    transfer before setting its state (SetRole BACKUP, last_seq: the transfer).
    Subscribes: pro2bfr (aft_msgs/Request), port ``inp``; peer_forward (aft_msgs/Request), port ``forwarded``.
    Publishes: bfr2prd (aft_msgs/Request), port ``out``; forward (aft_msgs/Request), port ``forward``.
    Services: ~set_role (aft_msgs/SetRole: returns the number of forwarded requests passed on),
        ~rebind (aft_msgs/Rebind)
    """
    MECHANISM = 'lfr'

    def __init__(self):
        self.forwarder = LfrForwarder(_role())   # the one owner of this Before's role
        super(LfrBeforeNode, self).__init__(
            extra_ports=[PortSpec('forward', PUBLISH, 'aft_msgs/Request'),
                         PortSpec('forwarded', SUBSCRIBE, 'aft_msgs/Request'),
                         PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
            extra_callbacks={'forwarded': self._on_forwarded})
        self.lock = threading.Lock()

    def setup(self, timeout):
        self.ports.bind('forward')
        self.ports.bind('alarms', '/aft/alarms')
        # Offered first: the LFR After waits for it before it takes input, and this Before's pipeline
        # connects only once the After does (see StageNode.setup).
        rospy.Service('~set_role', SetRole, self._on_set_role)
        return super(LfrBeforeNode, self).setup(timeout)

    def connected(self):
        # The leader's forwards are taken only once this Before's own pipeline is connected (see StageNode),
        # and before ~rebind is offered: an adaptation resumes the Protocols once it sees it.
        self.ports.bind('forwarded', 'peer_forward')

    def handle(self, request):
        with self.lock:
            forwards, request.transfer = self.forwarder.forwards(), self.forwarder.stamp()
        if forwards:
            self.ports.publish('forward', request)
        return request

    def _on_forwarded(self, request):
        with self.lock:
            decision = self.forwarder.on_forwarded(request.transfer, (request.origin, request.id))
            if decision == Forwarded.PASS:
                self.ports.publish('out', request)
                return
            stale, duplicates = self.forwarder.stale, self.forwarder.duplicates
        if decision == Forwarded.DUPLICATE:
            alarm(self.ports, 'lfr', 'duplicate_forward', 'forwarded request %s/%d refused: passed on once already, '
                  'a second copy is not computed (%d refused so far)' % (request.origin, request.id, duplicates),
                  request)
        elif decision == Forwarded.NOT_FOLLOWER:
            rospy.logwarn('%s: forwarded request %s/%d refused: no longer a follower', self.name,
                          request.origin, request.id)
        else:
            rospy.loginfo('%s: forwarded request %s/%d refused: forwarded before state transfer %d, whose state '
                          'holds it (%d refused so far)', self.name, request.origin, request.id,
                          self.forwarder.transfer, stale)

    def _on_set_role(self, req):
        role = Role(req.role)
        with self.lock:
            try:
                if role == Role.BACKUP and req.last_seq:
                    # Our follower's After is about to set the state of transfer last_seq.
                    passed = self.forwarder.follow(req.last_seq)
                    return SetRoleResponse(success=True, message='follows state transfer %d' % req.last_seq,
                                           last_seq=passed)
                kept = self.forwarder.set_role(role, req.epoch, req.last_seq)
            except RoleError as e:
                return SetRoleResponse(success=False, message=str(e))
            return SetRoleResponse(success=True, message=kept or 'role %s' % role.name,
                                   last_seq=self.forwarder.passed)


class LfrAfterNode(AfterNode):
    """LFR's After. Leader: holds each reply until the follower says it computed the request, then
    passes it on and notifies the follower. Follower: stores each computed reply in its Protocol
    (for the requests the Proxy re-sends after a failover) and tells the leader. A refusal of the
    leader's Protocol ("not executed") is sent to the follower and held the same way, so that a copy
    of the request sent after a failover is refused too, never executed.

    With a witness (``~witness``): a follower silent about a request is excluded with the witness's
    grant before the leader releases its held replies (deposed instead, the leader fail-stops); a
    follower starts empty and joins: the leader suspends its Protocol, sends its server's state and
    the replies clients may ask for again, and once the follower set that state and the witness
    admitted it, starts forwarding (its Before becomes PRIMARY) and resumes. A follower excluded by
    the witness joins again.

    Parameters:
        ~role (primary | backup | alone): with a witness every site starts as backup (follower) and
            Recovery promotes the one the witness names.
        ~server_deterministic (bool, required): the application's declaration; LFR refuses to start
            on a non-deterministic server.
        ~ack_timeout (float, 1 s): the follower silent this long about a request (or a state transfer)
            means it is lost.
        ~connect_timeout (float, 10 s)
        ~witness (str, default ''): the witness's aft_msgs/Witness service ('' : no witness, no joins).
        ~site, ~peer (str, required with a witness), ~site_pid (int, default: the site's roslaunch).
        ~in_sync (bool, false): started by an adaptation beside its new leader (or follower), the pair
            quiescent: a follower holds its leader's state without a transfer.
        ~join_period (float, 0.5 s): a joining follower asks for a state transfer this often.
        ~state_timeout (float, 5 s): the longest a get_state or set_state call may take.
        ~protocol (str, default protocol), ~before (str, default before): this replica's Protocol
            (suspended while a state transfer is captured and the follower admitted) and Before
            (told to forward once the follower is admitted, and to stop once it is excluded).
        ~cache_bytes (int, 64 MiB): bound of the replies kept for a state transfer.
        ~chunk_bytes (int, 1 MiB; 0 = one message), ~transfer_window (int, 4): a state transfer goes in
            parts of at most chunk_bytes, at most transfer_window of them sent and not yet acknowledged
            (aft_ftm.transfer, as PBR's): the ack timeout counts from the last part acknowledged, so a
            large state on a slow link joins (the Protocol stays suspended until it is whole).
    Services called (with a witness): get_state, set_state (the server's state manager), the witness,
        the Protocol's ~suspend/~resume, the Before's ~set_role.
    Subscribes: prd2aft (aft_msgs/Reply), port ``inp``; acks (aft_msgs/Notify), port ``acks``;
        peer_notify (aft_msgs/Notify), port ``notifications``; peer_refusals (aft_msgs/Reply), port
        ``peer_refusals``; peer_transfers (aft_msgs/Checkpoint), port ``transfers``: state transfers
        from the leader; join_requests (aft_msgs/Join), port ``join_requests``;
        <witness>'s configuration (aft_msgs/Configuration; its node's ~configuration).
    Publishes: aft2pro (aft_msgs/Reply), port ``out``; peer_acks (aft_msgs/Notify), port ``peer_acks``;
        notify (aft_msgs/Notify), port ``notify``; aft2pro_s (aft_msgs/Checkpoint), port ``stored``;
        refusals (aft_msgs/Reply), port ``refusals``; transfers (aft_msgs/Checkpoint), port
        ``transfer``: state transfers to a joining follower; join (aft_msgs/Join), port ``join``;
        fail_stop (aft_msgs/Failure), alarms (aft_msgs/Alarm: stray_ack for an ack, stray_checkpoint for a state
        transfer, from an After of another site than ~peer); ~events (std_msgs/String, latched): one
        JSON record per state transfer (bytes, replies; admitted_s: how long the Protocol was suspended);
        /diagnostics (diagnostic_msgs/DiagnosticArray): role, epoch, held replies (aft_ftm.health).
    Services: ~set_role (aft_msgs/SetRole), ~rebind (aft_msgs/Rebind)
    """
    MECHANISM = 'lfr'
    WAIT_OUTPUTS = ('stored',)

    def __init__(self):
        mechanisms.check_application('lfr', param('server_deterministic', config.flag, required=True),
                                     state_access=False)
        role = _role()
        self.ack_timeout = param('ack_timeout', config.positive_float, 1.0)
        self.admission = AdmissionGate(self.ack_timeout)   # a joiner given the state only while its site is heard
        self.connect_timeout = param('connect_timeout', config.positive_float, 10.0)
        witness = param('witness', config.witness_service, '')
        self.site = param('site', config.non_empty_str, required=bool(witness)) or ''
        self.peer = param('peer', config.non_empty_str, required=bool(witness)) or ''
        site_pid = param('site_pid', config.non_negative_int, site_launcher_pid())
        self.join_period = param('join_period', config.positive_float, 0.5)
        self.state_timeout = param('state_timeout', config.positive_float, 5.0)
        protocol = param('protocol', config.non_empty_str, 'protocol') if witness else ''
        before = param('before', config.non_empty_str, 'before')
        cache_bytes = param('cache_bytes', config.non_negative_int, 64 << 20)
        self.chunk_bytes = param('chunk_bytes', config.non_negative_int, 1 << 20)
        self.transfer_window = param('transfer_window', config.positive_int, 4)
        self.in_sync = param('in_sync', config.flag, False)
        self.outgoing = None        # leader: the state transfer in parts being sent (aft_ftm.transfer)
        self.incoming = Incoming()  # follower: the parts of the state transfer being received
        # Leader: the parts are written by a thread of their own. rospy writes a message synchronously:
        # on a slow or cut link a part blocks until the link takes it, and must hold neither the lock
        # nor the suspended Protocol (the join gives up after the ack timeout, whatever the writer does).
        self.to_write = queue.Queue()
        self.writing = False        # the writer is in a write (a part the link has not taken yet)
        super(LfrAfterNode, self).__init__(
            extra_ports=[PortSpec('acks', SUBSCRIBE, 'aft_msgs/Notify'),
                         PortSpec('peer_acks', PUBLISH, 'aft_msgs/Notify'),
                         PortSpec('notify', PUBLISH, 'aft_msgs/Notify'),
                         PortSpec('notifications', SUBSCRIBE, 'aft_msgs/Notify'),
                         PortSpec('stored', PUBLISH, 'aft_msgs/Checkpoint'),
                         PortSpec('refusals', PUBLISH, 'aft_msgs/Reply'),
                         PortSpec('peer_refusals', SUBSCRIBE, 'aft_msgs/Reply'),
                         PortSpec('transfer', PUBLISH, 'aft_msgs/Checkpoint'),
                         PortSpec('transfers', SUBSCRIBE, 'aft_msgs/Checkpoint')] + list(SIDE_PORTS),
            extra_callbacks={'acks': self._on_ack, 'notifications': self._on_notify,
                             'peer_refusals': self._on_peer_refusal, 'transfers': self._on_transfer,
                             'join_requests': self._on_join})
        self.side = ReplicaSide(self.ports, 'lfr', self.site, site_pid, witness, protocol, self.state_timeout)
        self.witness = self.side.witness
        self.lock = threading.Condition()   # guards self.core
        # The decisions and the one owner of this replica's role. A follower with a witness holds
        # nothing until a state transfer: it joins. State transfers are numbered from the wall clock
        # (microseconds), so that a restarted leader's numbers differ from those of its predecessor
        # a follower may name in its Join (only equality counts: the clock may have been stepped back).
        self.core = LfrAfter(self.name, role, joined=self.witness is None or role != Role.BACKUP or self.in_sync,
                             site=self.site, peer=self.peer, ack_timeout=self.ack_timeout,
                             join_period=self.join_period, join_seq=int(time.time() * 1e6), cache_bytes=cache_bytes)
        self.state_calls = Deadline('state', exclusive=True)   # a late set_state must not overtake a newer one
        self.before_role = PersistentService(before + '/set_role', SetRole)
        self.before_name = before
        self.get_state = PersistentService('get_state', GetState)
        self.set_state = PersistentService('set_state', SetState)

    def setup(self, timeout):
        for name in ('acks', 'peer_acks', 'notify', 'refusals', 'fail_stop'):
            self.ports.bind(name)
        self.ports.bind('notifications', 'peer_notify')
        self.ports.bind('peer_refusals')
        self.ports.bind('stored', 'aft2pro_s')
        self.ports.bind('alarms', '/aft/alarms')
        if self.witness is not None:
            self.ports.bind('transfer', 'transfers')
            self.ports.bind('transfers', 'peer_transfers')
            self.ports.bind('join')
            self.ports.bind('join_requests')
            if not self.witness.setup(timeout):
                return False
            try:
                rospy.wait_for_service('get_state', timeout)
                rospy.wait_for_service('set_state', timeout)
                self.get_state.connect()   # opened now: no state call needs the master later
                self.set_state.connect()
            except (rospy.ROSException, rospy.ServiceException) as e:
                rospy.logerr('%s: LFR with a witness joins a follower by a state transfer: the server state '
                             'manager (%s, %s) is not available: %s', self.name, rospy.resolve_name('get_state'),
                             rospy.resolve_name('set_state'), e)
                return False
        try:   # Before's set_role, called when the follower is excluded: opened now, not then
            rospy.wait_for_service(self.before_name + '/set_role', timeout)
            self.before_role.connect()
        except (rospy.ROSException, rospy.ServiceException) as e:
            rospy.logwarn('%s: %s/set_role not connected at set-up (%s): it is connected at its first call, '
                          'which then needs the ROS master', self.name, self.before_name, e)
        if self.witness is None or self.in_sync:
            peer = {Role.PRIMARY: ['notify', 'acks'], Role.BACKUP: ['peer_acks', 'notifications'],
                    Role.ALONE: []}
            missing = wait_for_connections(self.ports, peer[self.core.role], self.connect_timeout)
            if missing:
                rospy.logerr('%s: the peer After is not connected on %s', self.name,
                             [self.ports.topic(n) for n in missing])
                return False
        if not super(LfrAfterNode, self).setup(timeout):
            return False
        self.events = rospy.Publisher('~events', String, queue_size=10, latch=True)
        self.timer = rospy.Timer(rospy.Duration(min(0.1, self.ack_timeout / 4)), self._check_acks)
        if self.witness is not None:
            self.joiner_timer = rospy.Timer(rospy.Duration(self.join_period), self._ask_to_join)
            self.configuration = self.witness.subscribe(self._on_configuration, report=lambda detail: alarm(self.ports, 'witness', 'forged_configuration', detail))
        rospy.Service('~set_role', SetRole, self._on_set_role)
        if self.witness is not None:
            threading.Thread(target=self._write_parts, name='transfer-writer', daemon=True).start()
        return True

    def health(self):
        with self.lock:
            core = self.core
            return health.replica_after(
                self.site, 'lfr', core.role, core.epoch, self.peer, held=len(core.held),
                stopped='deposed: %s' % core.deposed if core.deposed else None,
                cannot_take_over=None if core.joined else 'holds no state: it is joining',
                extra=[('computed', core.computed)])

    def quiescent(self):
        """Leader: no reply waiting for the follower (checked by ~suspend)."""
        with self.lock:
            return not self.core.held

    # -- replies ------------------------------------------------------------------------
    def handle(self, reply):
        with self.lock:
            out = self.core.on_reply(reply, time.monotonic(), refused=reply.status == Reply.NOT_EXECUTED)
            if out == Out.STORE:
                computed = self.core.computed
                self.ports.publish('stored', Checkpoint(seq=computed, sender=self.name, reply=reply,
                                                        epoch=self.core.epoch))
                self.ports.publish('peer_acks', Notify(origin=reply.origin, id=reply.id, seq=computed))
                self.lock.notify_all()
            elif out == Out.HOLD_REFUSAL:
                self.ports.publish('refusals', reply)
        if out in (Out.RELEASE, Out.RELEASE_NOTIFY):
            self._release(reply, notify=out == Out.RELEASE_NOTIFY)
        return None

    def _release(self, reply, notify):
        self.ports.publish('out', reply)
        if notify:
            self.ports.publish('notify', Notify(origin=reply.origin, id=reply.id))

    def _on_ack(self, ack):
        # rospy gives every received message its publisher's node name in the connection header.
        sender = getattr(ack, '_connection_header', {}).get('callerid')
        if ack.partial:
            self._on_part_ack(ack, sender)
            return
        with self.lock:
            answer, reply = self.core.on_ack(ack.origin, ack.id, time.monotonic(), sender)
            if answer == Ack.TRANSFER:
                self.lock.notify_all()
        if answer == Ack.RELEASE:
            self._release(reply, notify=True)
        elif answer == Ack.STRAY:
            self.side.tell('stray_ack', 'ack of %s/%d from %s ignored: %s does not follow %s' % (
                ack.origin, ack.id, sender, sender, self.name), sender)

    def _on_part_ack(self, ack, sender):
        """The joiner holds parts 0 .. ack.part of the transfer being sent: the window opens."""
        with self.lock:
            out = self.outgoing
            if out is None or ack.id != out.seq or not self.core.from_peer(sender):
                return   # a transfer given up, or another's: nothing to open
            try:
                if out.acknowledged(ack.part):
                    self.lock.notify_all()
            except TransferError as e:
                rospy.logwarn('%s: %s', self.name, e)

    def _on_peer_refusal(self, refusal):
        """Follower: the leader refused a request; a copy sent here after a failover gets the same answer."""
        with self.lock:
            if not self.core.on_peer_refusal(refusal):
                return
            computed = self.core.computed
            self.ports.publish('stored', Checkpoint(seq=computed, sender=self.name, reply=refusal,
                                                    epoch=self.core.epoch))
            self.ports.publish('peer_acks', Notify(origin=refusal.origin, id=refusal.id, seq=computed))

    def _on_notify(self, _notification):
        with self.lock:
            # the leader replied: nothing more to do for it (the Protocol's cache is GC'd by watermark)
            self.core.notified += 1

    # -- losing the follower -----------------------------------------------------------
    def _check_acks(self, _event):
        with self.lock:
            unfollowed = self.core.unfollowed_backup()
            if not unfollowed and not self.core.overdue(time.monotonic()):
                return
        if unfollowed:
            self.side.alone(self._exclude_unfollowed)
            return
        why = 'the follower did not compute a request for %.1f s' % self.ack_timeout
        if self.witness is None:
            with self.lock:
                released = self.core.go_alone(why=why)
            for reply in released:
                self.ports.publish('out', reply)
            # A degraded state is never silent, with or without a witness.
            self.side.tell('alone', '%s goes on ALONE, no witness (%s)' % (self.site or self.name, why))
            return
        self.side.alone(self._exclude, why)

    def _exclude(self, why):
        """Ask the witness to exclude the follower; release the held replies only once it did."""
        grant = self.side.exclusion(self._deposed)
        if grant is None:
            return
        self._forwarding(Role.ALONE, grant.epoch)
        with self.lock:
            if self.core.state != State.LEADING:
                return
            released = self.core.go_alone(grant.epoch, why)
        for reply in released:
            self.ports.publish('out', reply)
        self.side.tell('alone', '%s goes on ALONE at epoch %d (%s); %s' % (self.site, grant.epoch, why, grant.message))

    def _exclude_unfollowed(self):
        """The witness names the peer this leader's backup, which it does not forward to (an ADMIT given up
        on, carried out late): exclude it, or a promotion would serve a state without the replies since."""
        with self.lock:
            if not self.core.unfollowed_backup():
                return
            conf = self.core.configuration
        self.side.tell('backup_unfollowed', 'the witness names %s the backup of epoch %d, but %s leads alone and '
                       'forwards nothing to it (an ADMIT answered after its caller gave up): it is excluded'
                       % (conf.backup, conf.epoch, self.site), key=('unfollowed', conf.epoch))
        grant = self.side.exclusion(self._deposed)
        if grant is None:
            return   # unreachable (alarmed): asked again at the next check
        self._forwarding(Role.ALONE, grant.epoch)
        with self.lock:
            self.core.epoch = max(self.core.epoch, grant.epoch)
        self.side.tell('alone', '%s goes on ALONE at epoch %d (%s excluded: %s)'
                       % (self.site, grant.epoch, conf.backup, grant.message))

    def _forwarding(self, role, epoch, transfer=0):
        """Tell this replica's Before to forward (PRIMARY, stamping ``transfer``) or not (ALONE); True if it did."""
        try:
            answer = self.state_calls.call(lambda: self.before_role(role=role.value, epoch=epoch, last_seq=transfer),
                                           self.state_timeout)
        except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
            self.before_role = self.before_role.fresh()
            answer, error = None, str(e)
        else:
            error = answer.message
        if answer is None or not answer.success:
            self.side.tell('forwarding_failed', 'cannot make Before %s: %s' % (role.name, error))
            return False
        return True

    def _deposed(self, why):
        with self.lock:
            withheld = self.core.depose(why)
        self.side.fail_stop('deposed by the witness (%s): %d replies withheld' % (why, withheld))

    # -- joins (leader side) -----------------------------------------------------------
    def _on_join(self, join):
        with self.lock:
            decision = self.core.on_join(join, time.monotonic())
        # One decision at a time: a follower asking while another is under way asks again later.
        if decision == JoinDecision.EXCLUDE:
            self.side.alone(self._exclude, '%s asks to join again (its After %s holds transfer %d, not ours): it '
                            'restarted or lost its state' % (join.site, join.after, join.last_seq))
        elif decision == JoinDecision.TRANSFER:
            # Only a site that runs gets the state: not heard yet, it asks again.
            if not self.side.join_waits(self.admission, self.lock, join):
                self.side.alone(self._transfer, join)

    def _write_parts(self):
        """The writer: each queued part in order, unless its transfer was given up meanwhile."""
        while not rospy.is_shutdown():
            try:
                part = self.to_write.get(timeout=1.0)
            except queue.Empty:
                continue
            with self.lock:
                wanted = self.outgoing is not None and self.outgoing.seq == part.seq
                self.writing = wanted
            if wanted:
                try:
                    self.ports.publish('transfer', part)
                except Exception as e:   # a port rebound or closed meanwhile: that transfer is not acknowledged
                    rospy.logwarn('%s: part %d of state transfer %d not sent: %s', self.name, part.part, part.seq, e)
                finally:
                    self.writing = False

    def _transfer(self, join):
        if self.writing or not self.to_write.empty():
            # The link to the joiner has not taken the last transfer's part yet (slow, or cut): a new
            # transfer would queue behind it while the Protocol waits. The joiner asks again.
            rospy.loginfo_throttle(5.0, '%s: %s asks to join while a part of the last transfer is still being '
                                   'written: it asks again later' % (self.name, join.site))
            return
        with self.lock:
            alone = self.core.state == State.ALONE
        if alone and self.side.quiesce_protocol(True):
            try:
                self._join(join)
            finally:
                self.side.quiesce_protocol(False)

    def _join(self, join):
        """The Protocol is quiescent (nothing executing, new requests held): the server's state holds
        exactly the requests answered so far. Transfer it, have the follower admitted, then forward."""
        t0 = time.monotonic()
        try:
            state = self.state_calls.call(self.get_state, self.state_timeout).state
        except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
            self.get_state = self.get_state.fresh()
            self.side.tell('join_failed', 'cannot transfer the state to %s: %s' % (join.site, e))
            return
        out = Outgoing(0, state, self.chunk_bytes, self.transfer_window)
        # The Protocol's suspension lease must outlast the transfer: each part may take up to the ack
        # timeout. Renewed now, and checked again before the follower is admitted.
        why = self.side.hold_protocol(2 * self.state_timeout + (out.count + 1) * self.ack_timeout)
        if why:
            self.side.tell('join_failed', 'cannot transfer the state to %s: the Protocol is not held: %s'
                           % (join.site, why))
            return
        with self.lock:
            transfer = self.core.start_transfer(join.site, t0)
            if transfer is None:
                return
            epoch = self.core.epoch   # the follower is admitted only in this epoch (a late ADMIT is refused)
            out.seq = transfer.seq
            record = {'event': 'join', 'joiner': join.site, 'seq': transfer.seq, 'state_bytes': len(state),
                      'replies': len(transfer.cache), 'parts': out.count, 'sent_wall': time.time()}
            self.outgoing = out
            try:
                acknowledged = self._send_transfer(out, transfer)
            finally:
                self.outgoing = None
                self.core.end_transfer()
        if not acknowledged:
            self.side.tell('join_failed', '%s did not acknowledge %s of the state transfer within %.1f s'
                           % (join.site, 'part %d of %d' % (out.held, out.count) if out.count > 1 else 'all',
                              self.ack_timeout))
            return
        record['acknowledged_s'] = transfer.acknowledged_s
        why = self.side.hold_protocol(2 * self.state_timeout)
        if why:
            # It resumed by itself meanwhile (its lease ran out): requests ran that the transferred
            # state does not hold. Admitting the follower would make it diverge.
            self.side.tell('join_failed', 'state transfer %d to %s not admitted: the Protocol ran requests '
                           'during it (%s); it asks again' % (transfer.seq, join.site, why))
            return
        unheard = self.side.joiner_unheard(join.site)   # heard when its join came (_on_join): still?
        if unheard:
            self.side.tell('join_failed', 'state transfer %d to %s not admitted: %s; it asks again'
                           % (transfer.seq, join.site, unheard))
            return
        grant = self.side.ask(Op.ADMIT, peer=join.site, peer_incarnation=join.incarnation, epoch=epoch)
        if grant is None and not self.side.hold_protocol(2 * self.state_timeout):
            # No answer: the witness may still carry it out. Asked once more (an identical repeat is
            # granted "already"); still unknown, a late grant is caught by _check_acks (unfollowed_backup).
            grant = self.side.ask(Op.ADMIT, peer=join.site, peer_incarnation=join.incarnation, epoch=epoch)
        if grant is None:
            self._void_admit(join.site)
            return
        if not grant.granted:
            if grant.primary != self.site:
                self._deposed(grant.message)
            else:
                with self.lock:   # its epoch, if it had missed a configuration: the next transfer's
                    self.core.on_configuration(grant)
                self.side.tell('join_failed', 'the witness refused to admit %s: %s' % (join.site, grant.message))
            return
        if not self._forwarding(Role.PRIMARY, grant.epoch, transfer.seq):
            self._exclude('Before cannot forward to the admitted follower %s' % join.site)
            return
        # Held still? The witness's answer and Before's may have taken seconds (this After stopped,
        # the machine stalled): a Protocol whose lease ran out meanwhile resumed by itself and ran
        # requests that neither the transferred state nor the forwarding holds; the follower was
        # admitted without them, silently, and a later failover lost answered updates (review of
        # session 36). A renewal that succeeds proves it never resumed.
        why = self.side.hold_protocol(2 * self.state_timeout)
        if why:
            why = 'the Protocol ran requests while %s was admitted (%s): the follower lacks them' % (join.site, why)
            self.side.tell('join_failed', 'state transfer %d not admitted after all: %s; it is excluded and asks '
                           'again' % (transfer.seq, why))
            self._exclude(why)
            return
        with self.lock:
            try:
                self.core.admitted(join.after, join.incarnation, transfer.seq, grant.epoch)
            except RoleError as e:
                rospy.logwarn('%s: %s admitted, but not followed: %s', self.name, join.site, e)
                return
        record.update(admitted_s=time.monotonic() - t0, admitted_wall=time.time(), epoch=grant.epoch)
        self.events.publish(String(data=json.dumps(record, sort_keys=True)))
        self.side.told.clear()
        rospy.loginfo('%s: %s is the follower again (epoch %d)', self.name, join.site, grant.epoch)

    def _void_admit(self, site):
        """An ADMIT left unanswered may still be carried out by the witness, naming a follower this leader
        will not forward to once it serves again: if the leader then failed before noticing (_check_acks),
        that follower was promoted without the replies released meanwhile (review of the witness, session
        33). Before the Protocol resumes, an EXCLUDE is granted: a new epoch, in which that ADMIT is
        refused when it comes. Asked while the Protocol is held (bounded: 10 s); past that the leader
        serves alone with the alarm admit_unsettled, and _check_acks still excludes a late admission."""
        deadline = time.monotonic() + 10.0
        refused = []
        while not rospy.is_shutdown():
            grant = self.side.exclusion(lambda why: refused.append(why) or self._deposed(why))
            if refused:
                return   # deposed (said there): it serves nothing
            if grant is not None:
                with self.lock:
                    self.core.epoch = max(self.core.epoch, grant.epoch)
                self.side.tell('join_failed', 'the admission of %s went unanswered: %s (epoch %d) voids it'
                               % (site, grant.message, grant.epoch))
                return
            if time.monotonic() > deadline or self.side.hold_protocol(2 * self.state_timeout):
                break
            time.sleep(0.5)
        self.side.tell('admit_unsettled', 'the admission of %s went unanswered and the witness could not be asked '
                       'to void it: %s serves alone; if the witness still admits %s, it is excluded as soon as '
                       'this leader hears it' % (site, self.site, site))

    def _send_transfer(self, out, transfer):
        """Queue the transfer's parts for the writer as the window allows, each acknowledgment opening it
        further (self.lock held; waiting releases it). True once the follower acknowledged the whole transfer,
        False if it was silent ack_timeout (from the start, or from the last part it acknowledged)."""
        while True:
            for part in out.next_parts():
                last = part == out.count - 1
                self.to_write.put(Checkpoint(
                    seq=transfer.seq, first_seq=transfer.seq, sender=self.name, epoch=self.core.epoch, full=True,
                    state=out.parts[part], cache=transfer.cache if last else [],
                    part=part if out.count > 1 else 0, parts=out.count if out.count > 1 else 0))
            held = out.held
            if not self.lock.wait_for(lambda: transfer.acknowledged_s is not None or out.held > held,
                                      timeout=self.ack_timeout):
                return False
            if transfer.acknowledged_s is not None:
                return True

    # -- joins (follower side) ---------------------------------------------------------
    def _ask_to_join(self, _event):
        with self.lock:
            step = self.core.join_step(time.monotonic())
            accepted = self.core.accepted
        if step == JoinStep.STATUS:
            # Joined, but never admitted (the witness refused it, or its configuration was missed): ask.
            status = self.side.ask(Op.STATUS)
            if status is None or status.backup == self.site:
                return
            with self.lock:
                again = self.core.not_admitted(status.epoch)
            if again:
                self.side.tell('backup_invalid', '%s: not admitted by the witness after its state transfer '
                               '(epoch %d); it joins again' % (self.site, status.epoch))
        elif step == JoinStep.JOIN and self.ports.connections('transfers'):
            self.ports.publish('join', Join(site=self.site, after=self.name, incarnation=self.witness.incarnation,
                                            last_seq=accepted, stamp=rospy.Time.now()))

    def _on_transfer(self, cp):
        with self.lock:
            problem = self.core.check_transfer(cp.seq, cp.sender, cp.epoch, cp.full)
            if problem is None and cp.parts > 1:
                # In parts: each acknowledged as it comes; nothing is set before the last. A part out of
                # order (one lost) refuses the transfer: the follower asks for another (join_period).
                whole, refused = self.incoming.take(cp)
                if refused:
                    self.side.tell('join_failed', '%s: %s; it asks again' % (self.site, refused))
                    return
                if whole is None:
                    self.ports.publish('peer_acks', Notify(origin='', id=cp.seq, partial=True, part=cp.part))
                    return
                cp.state = whole
            if problem is None:
                problem = self._fence(cp.seq)
            if problem is None:
                try:
                    result = self.state_calls.call(self.set_state, self.state_timeout, cp.state)
                    problem = None if result.success else 'the server refused the state: %s' % result.message
                except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
                    self.set_state = self.set_state.fresh()
                    problem = 'cannot set the server state: %s' % e
            if problem is None:
                self.core.transferred(cp.seq, cp.epoch, cp.cache, time.monotonic())
                computed = self.core.computed
                self.ports.publish('stored', Checkpoint(seq=computed, sender=self.name, full=True,
                                                        cache=cp.cache, epoch=cp.epoch))
                self.ports.publish('peer_acks', Notify(origin='', id=cp.seq, seq=computed))
        if problem is not None:
            # Once per transfer of the peer (each attempt's cause is told: a fence or set_state timeout, a
            # bad state), once per any other sender (a flood raises one).
            self.side.tell('stray_checkpoint', 'state transfer %d from %s refused, nothing changed: %s'
                           % (cp.seq, cp.sender, problem),
                           (cp.sender, cp.seq) if self.core.from_peer(cp.sender) else cp.sender)
        else:
            rospy.loginfo('%s: joined %s (state transfer %d, epoch %d)', self.name, cp.sender, cp.seq, cp.epoch)

    def _fence(self, seq):
        """Before the state of transfer seq is set (self.lock held): make the Before refuse the
        requests forwarded before it, and wait until those it passed on are computed. Why not, or None."""
        try:
            answer = self.state_calls.call(
                lambda: self.before_role(role=Role.BACKUP.value, last_seq=seq), self.ack_timeout)
        except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
            self.before_role = self.before_role.fresh()
            return 'cannot fence Before %s against the requests forwarded before the transfer: %s' % (
                self.before_name, e)
        if not answer.success:
            return 'Before %s does not follow the transfer: %s' % (self.before_name, answer.message)
        passed = answer.last_seq
        if not self.lock.wait_for(lambda: self.core.in_flight(passed) == 0, timeout=self.ack_timeout):
            return ('%d of the %d requests Before passed on before the transfer are still not computed after %.1f s'
                    % (self.core.in_flight(passed), passed, self.ack_timeout))
        return None

    # -- the witness's configuration ----------------------------------------------------
    def _on_configuration(self, conf):
        with self.lock:
            change = self.core.on_configuration(conf)
        if change == ConfChange.DEPOSED:
            self._deposed('%s is the primary of epoch %d (%s)' % (conf.primary, conf.epoch, conf.reason))
        elif change == ConfChange.EXCLUDED:
            self.side.tell('excluded', '%s was excluded at epoch %d (%s): it cannot take over and joins again'
                           % (self.site, conf.epoch, conf.reason))

    # -- role changes (Recovery) ----------------------------------------------------------
    def _on_set_role(self, req):
        role = Role(req.role)
        with self.lock:
            core = self.core
            try:
                core.check_role(role, req.initial)
                if core.role == Role.BACKUP and role == Role.ALONE and \
                        not self.lock.wait_for(lambda: core.computed >= req.last_seq, timeout=2.0):
                    # The results of every forwarded request Before passed on (fenced now) are needed.
                    return SetRoleResponse(success=False, message='computed %d of the %d forwarded requests'
                                           % (core.computed, req.last_seq))
                leading = core.role == Role.PRIMARY
                took_over = core.role == Role.BACKUP and role == Role.ALONE and not req.initial
                released, kept = core.set_role(role, req.epoch, req.initial)
            except RoleError as e:
                return SetRoleResponse(success=False, message=str(e))
            last_seq = core.computed
        if kept:
            return SetRoleResponse(success=True, message=kept, last_seq=last_seq)
        for reply in released:
            self.ports.publish('out', reply)
        if leading and role == Role.ALONE:   # Recovery's order after the follower failed: never silent
            self.side.tell('alone', '%s goes on ALONE at epoch %d: its follower failed%s' % (
                self.site or self.name, req.epoch, ' and the witness excluded it' if self.witness else ''))
        elif took_over:   # its leader failed: it serves with no follower until a site joins, never silently
            self.side.tell('took_over', '%s is promoted at epoch %d and goes on ALONE: its leader failed; no follower until '
                           'a site joins' % (self.site or self.name, req.epoch))
        rospy.loginfo('%s: role is now %s (epoch %d)', self.name, role.name, req.epoch)
        return SetRoleResponse(success=True, message='role %s' % role.name, last_seq=last_seq)
