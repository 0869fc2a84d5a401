"""Leader-Follower Replication (paper Table II): the leader forwards each request to the follower,
both compute, the leader replies once the follower computed it too, then notifies it. No state is
transferred while both serve (bandwidth low), but the server must be deterministic. With a witness,
a follower joins by one state transfer (the server's getState/setState), as a PBR backup does."""
import json
import threading
import time

import rospy
from aft_msgs.msg import Checkpoint, Join, Notify, Reply
from aft_msgs.srv import GetState, SetRole, SetRoleResponse, SetState
from std_msgs.msg import String

from .. import config, health, mechanisms
from ..errors import RoleError
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import DuplicateCache, Role, check_role_change
from ..witness import Op
from .bpa_nodes import AfterNode, BeforeNode
from .deadline import CallTimeout, Deadline
from .diagnostics import Diagnostics
from .params import param
from .ports import wait_for_connections
from .protocol_node import ROLES
from .replica_side import SIDE_PORTS, ReplicaSide
from .witness_client import site_launcher_pid


def _role():
    return ROLES[param('role', config.choice(*ROLES), 'primary')]


def _refused(current, new):
    """A SetRole refusal if current -> new is not an allowed role change, else None."""
    try:
        check_role_change(current, new)
    except RoleError as e:
        return SetRoleResponse(success=False, message=str(e))
    return None


class LfrBeforeNode(BeforeNode):
    """LFR's Before. Leader: forwards each request to the follower, then to its own Proceed.
    Follower: passes the leader's forwarded requests to its Proceed, in the leader's order; once
    promoted (fenced) it refuses them.

    Parameters: ~role (primary | backup | alone). With a witness, the After makes a leader's Before
    PRIMARY once a follower is admitted and ALONE once it is excluded.
    Subscribes: pro2bfr (aft_msgs/Request), port ``inp``; peer_forward (aft_msgs/Request), port ``forwarded``.
    Publishes: bfr2prd (aft_msgs/Request), port ``out``; forward (aft_msgs/Request), port ``forward``.
    Services: ~set_role (aft_msgs/SetRole: returns the number of forwarded requests passed on),
        ~rebind (aft_msgs/Rebind)
    """

    def __init__(self):
        self.role = _role()
        super(LfrBeforeNode, self).__init__(
            extra_ports=[PortSpec('forward', PUBLISH, 'aft_msgs/Request'),
                         PortSpec('forwarded', SUBSCRIBE, 'aft_msgs/Request')],
            extra_callbacks={'forwarded': self._on_forwarded})
        self.lock = threading.Lock()
        self.passed = 0      # forwarded requests passed to Proceed (the follower's execution order)
        self.epoch = 0       # the witness's epoch of the last role given (a late, older order changes nothing)
        self.refused = 0

    def setup(self, timeout):
        self.ports.bind('forward')
        self.ports.bind('forwarded', 'peer_forward')
        rospy.Service('~set_role', SetRole, self._on_set_role)
        return super(LfrBeforeNode, self).setup(timeout)

    def handle(self, request):
        if self.role == Role.PRIMARY:
            self.ports.publish('forward', request)
        return request

    def _on_forwarded(self, request):
        with self.lock:
            if self.role != Role.BACKUP:
                self.refused += 1
                rospy.logwarn('%s: forwarded request %s/%d refused: no longer a follower', self.name,
                              request.origin, request.id)
                return
            self.passed += 1
            self.ports.publish('out', request)

    def _on_set_role(self, req):
        role = Role(req.role)
        with self.lock:
            refused = _refused(self.role, role)
            if refused:
                return refused
            if self.role == Role.PRIMARY and role == Role.ALONE and req.epoch and req.epoch < self.epoch:
                # A late order (Recovery stalled) about a follower that has joined again since.
                return SetRoleResponse(success=True, message='role PRIMARY kept: epoch %d is newer than %d'
                                       % (self.epoch, req.epoch), last_seq=self.passed)
            self.role = role
            self.epoch = max(self.epoch, req.epoch)
            return SetRoleResponse(success=True, message='role %s' % role.name, last_seq=self.passed)


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
    Services called (with a witness): get_state, set_state (the server's state manager), the witness,
        the Protocol's ~suspend/~resume, the Before's ~set_role.
    Subscribes: prd2aft (aft_msgs/Reply), port ``inp``; acks (aft_msgs/Notify), port ``acks``;
        peer_notify (aft_msgs/Notify), port ``notifications``; peer_refusals (aft_msgs/Reply), port
        ``peer_refusals``; peer_transfers (aft_msgs/Checkpoint), port ``transfers``: state transfers
        from the leader; join_requests (aft_msgs/Join), port ``join_requests``;
        /aft/witness/configuration (aft_msgs/Configuration).
    Publishes: aft2pro (aft_msgs/Reply), port ``out``; peer_acks (aft_msgs/Notify), port ``peer_acks``;
        notify (aft_msgs/Notify), port ``notify``; aft2pro_s (aft_msgs/Checkpoint), port ``stored``;
        refusals (aft_msgs/Reply), port ``refusals``; transfers (aft_msgs/Checkpoint), port
        ``transfer``: state transfers to a joining follower; join (aft_msgs/Join), port ``join``;
        fail_stop (aft_msgs/Failure), alarms (aft_msgs/Alarm); ~events (std_msgs/String, latched): one
        JSON record per state transfer (bytes, replies; admitted_s: how long the Protocol was suspended);
        /diagnostics (diagnostic_msgs/DiagnosticArray): role, epoch, held replies (aft_ftm.health).
    Services: ~set_role (aft_msgs/SetRole), ~rebind (aft_msgs/Rebind)
    """

    def __init__(self):
        mechanisms.check_application('lfr', param('server_deterministic', config.flag, required=True),
                                     state_access=False)
        self.role = _role()
        self.ack_timeout = param('ack_timeout', config.positive_float, 1.0)
        self.connect_timeout = param('connect_timeout', config.positive_float, 10.0)
        witness = param('witness', config.optional_name, '')
        self.site = param('site', config.non_empty_str, required=bool(witness)) or ''
        self.peer = param('peer', config.non_empty_str, required=bool(witness)) or ''
        site_pid = param('site_pid', config.non_negative_int, site_launcher_pid())
        self.join_period = param('join_period', config.positive_float, 0.5)
        self.state_timeout = param('state_timeout', config.positive_float, 5.0)
        protocol = param('protocol', config.non_empty_str, 'protocol') if witness else ''
        before = param('before', config.non_empty_str, 'before')
        cache_bytes = param('cache_bytes', config.non_negative_int, 64 << 20)
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
        self.lock = threading.Condition()
        self.held = {}          # leader: (origin, id) -> (reply, since)
        self.acked = set()      # leader: acks that came before our own result
        self.computed = 0       # follower: results of forwarded requests
        self.notified = 0
        self.epoch = 0          # the witness's epoch of this replica's role
        self.deposed = None     # leader: why the witness deposed it (it answers nothing more)
        self.recent = DuplicateCache(max_bytes=cache_bytes)   # replies a state transfer carries
        # A follower with a witness holds nothing until a state transfer: it joins.
        self.in_sync = param('in_sync', config.flag, False)
        self.joined = self.witness is None or self.role != Role.BACKUP or self.in_sync
        self.joined_since = 0.0
        self.follower = None    # leader: the follower admitted: (After, site incarnation, transfer seq)
        self.transfer = None    # leader: the state transfer waiting for its acknowledgment
        # State transfers are numbered from the wall clock (microseconds), so that a follower's
        # Join sent before it accepted a transfer (last_seq below it) is told from one sent after.
        self.join_seq = int(time.time() * 1e6)
        self.accepted = 0       # follower: the seq of the last state transfer it accepted
        self.configuration_seen = None
        self.state_calls = Deadline('state')
        self.before_role = rospy.ServiceProxy(before + '/set_role', SetRole, persistent=True)
        self.before_name = before
        self.get_state = rospy.ServiceProxy('get_state', GetState, persistent=True)
        self.set_state = rospy.ServiceProxy('set_state', SetState, persistent=True)

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
            except rospy.ROSException:
                rospy.logerr('%s: LFR with a witness joins a follower by a state transfer: the server state '
                             'manager (%s, %s) is not available', self.name, rospy.resolve_name('get_state'),
                             rospy.resolve_name('set_state'))
                return False
        if self.witness is None or self.in_sync:
            peer = {Role.PRIMARY: ['notify', 'acks'], Role.BACKUP: ['peer_acks', 'notifications'],
                    Role.ALONE: []}
            missing = wait_for_connections(self.ports, peer[self.role], self.connect_timeout)
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
            self.configuration = self.witness.subscribe(self._on_configuration)
        rospy.Service('~set_role', SetRole, self._on_set_role)
        self.diagnostics = Diagnostics(self._health, self.site)
        return True

    def _health(self):
        with self.lock:
            return health.replica_after(
                self.site, 'lfr', self.role, self.epoch, self.peer, held=len(self.held),
                stopped='deposed: %s' % self.deposed if self.deposed else None,
                cannot_take_over=None if self.joined else 'holds no state: it is joining',
                extra=[('computed', self.computed)])

    def quiescent(self):
        """Leader: no reply waiting for the follower (checked by ~suspend)."""
        with self.lock:
            return not self.held

    # -- replies ------------------------------------------------------------------------
    def _remember(self, reply):
        self.recent.forget_below(reply.origin, reply.oldest_pending)
        self.recent.store(reply)

    def handle(self, reply):
        key = (reply.origin, reply.id)
        with self.lock:
            if self.role == Role.BACKUP:
                if reply.status == Reply.NOT_EXECUTED:
                    return None   # a follower's Protocol refuses nothing (nor does it get requests)
                self.computed += 1
                self._remember(reply)
                self.ports.publish('stored', Checkpoint(seq=self.computed, sender=self.name, reply=reply,
                                                        epoch=self.epoch))
                self.ports.publish('peer_acks', Notify(origin=reply.origin, id=reply.id, seq=self.computed))
                self.lock.notify_all()
                return None
            if self.deposed:
                return None       # a deposed leader answers nothing
            reply.epoch = self.epoch
            self._remember(reply)
            if self.role == Role.PRIMARY:
                if reply.status == Reply.NOT_EXECUTED:
                    self.held[key] = (reply, time.monotonic())
                    self.ports.publish('refusals', reply)
                    return None
                if key not in self.acked:
                    self.held[key] = (reply, time.monotonic())
                    return None
                self.acked.discard(key)
        self._release(reply)
        return None

    def _release(self, reply):
        self.ports.publish('out', reply)
        if self.role == Role.PRIMARY:
            self.ports.publish('notify', Notify(origin=reply.origin, id=reply.id))

    def _on_ack(self, ack):
        key = (ack.origin, ack.id)
        with self.lock:
            if not ack.origin:
                if self.transfer is not None and ack.id == self.transfer['seq']:
                    self.transfer['acknowledged_s'] = time.monotonic() - self.transfer['t0']
                    self.lock.notify_all()
                return
            held = self.held.pop(key, None)
            if held is None:
                if self.role == Role.PRIMARY:
                    self.acked.add(key)
                return
        self._release(held[0])

    def _on_peer_refusal(self, refusal):
        """Follower: the leader refused a request; a copy sent here after a failover gets the same answer."""
        with self.lock:
            if self.role != Role.BACKUP or not self.joined:
                return
            self._remember(refusal)
            self.ports.publish('stored', Checkpoint(seq=self.computed, sender=self.name, reply=refusal,
                                                    epoch=self.epoch))
            self.ports.publish('peer_acks', Notify(origin=refusal.origin, id=refusal.id, seq=self.computed))

    def _on_notify(self, _notification):
        self.notified += 1   # the leader replied: nothing more to do for it (the Protocol's cache is GC'd by watermark)

    # -- losing the follower -----------------------------------------------------------
    def _go_alone(self, epoch=0):
        self.role = Role.ALONE
        self.epoch = max(self.epoch, epoch)
        self.follower = None
        released = [r for r, _ in sorted(self.held.values(), key=lambda h: h[1])]
        self.held.clear()
        self.acked.clear()
        for reply in released:
            reply.epoch = self.epoch
        return released

    def _check_acks(self, _event):
        with self.lock:
            now = time.monotonic()
            if self.role != Role.PRIMARY or self.deposed \
                    or not any(now - t > self.ack_timeout for _, t in self.held.values()):
                return
        why = 'the follower did not compute a request for %.1f s' % self.ack_timeout
        if self.witness is None:
            rospy.logerr('%s: %s: going on ALONE', self.name, why)
            with self.lock:
                released = self._go_alone()
            for reply in released:
                self.ports.publish('out', reply)
            return
        self.side.alone(self._exclude, why)

    def _exclude(self, why):
        """Ask the witness to exclude the follower; release the held replies only once it did."""
        grant = self.side.exclusion(self._deposed)
        if grant is None:
            return
        self._forwarding(Role.ALONE, grant.epoch)
        with self.lock:
            if self.role != Role.PRIMARY:
                return
            released = self._go_alone(grant.epoch)
        for reply in released:
            self.ports.publish('out', reply)
        self.side.tell('alone', '%s goes on ALONE at epoch %d (%s); %s' % (self.site, grant.epoch, why, grant.message))

    def _forwarding(self, role, epoch):
        """Tell this replica's Before to forward (PRIMARY) or not (ALONE); True if it did."""
        try:
            answer = self.state_calls.call(lambda: self.before_role(role=role.value, epoch=epoch), self.state_timeout)
        except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
            self.before_role = rospy.ServiceProxy(self.before_name + '/set_role', SetRole, persistent=True)
            answer, error = None, str(e)
        else:
            error = answer.message
        if answer is None or not answer.success:
            self.side.tell('forwarding_failed', 'cannot make Before %s: %s' % (role.name, error))
            return False
        return True

    def _deposed(self, why):
        with self.lock:
            self.deposed = why
            withheld = len(self.held)
            self.held.clear()
        self.side.fail_stop('deposed by the witness (%s): %d replies withheld' % (why, withheld))

    # -- joins (leader side) -----------------------------------------------------------
    def _on_join(self, join):
        if join.site == self.site:
            return
        with self.lock:
            if self.role == Role.BACKUP or self.deposed:
                return
            # A follower that accepted our transfer and asks again lost its state (or was restarted):
            # exclude it first. A Join it sent before it accepted the transfer is late: ignored.
            follower = self.follower
            if self.role == Role.PRIMARY and follower is not None and (join.after, join.incarnation) == follower[:2] \
                    and join.last_seq < follower[2]:
                return
            restarted = self.role == Role.PRIMARY
        # One decision at a time: a follower asking while another is under way asks again later.
        if restarted:
            self.side.alone(self._exclude, '%s asks to join again: it restarted' % join.site)
        else:
            self.side.alone(self._transfer, join)

    def _transfer(self, join):
        if self.role == Role.ALONE and self.side.quiesce_protocol(True):
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
            self.get_state = rospy.ServiceProxy('get_state', GetState, persistent=True)
            self.side.tell('join_failed', 'cannot transfer the state to %s: %s' % (join.site, e))
            return
        with self.lock:
            if self.role != Role.ALONE or self.deposed:
                return
            self.join_seq += 1
            cache = self.recent.replies()
            self.transfer = record = {'event': 'join', 'joiner': join.site, 'seq': self.join_seq,
                                      'state_bytes': len(state), 'replies': len(cache), 't0': t0,
                                      'sent_wall': time.time()}
            self.ports.publish('transfer', Checkpoint(seq=self.join_seq, first_seq=self.join_seq, sender=self.name,
                                                      epoch=self.epoch, full=True, state=state, cache=cache))
            acknowledged = self.lock.wait_for(lambda: 'acknowledged_s' in record, timeout=self.ack_timeout)
            self.transfer = None
        if not acknowledged:
            self.side.tell('join_failed', '%s did not acknowledge the state transfer within %.1f s'
                           % (join.site, self.ack_timeout))
            return
        grant = self.side.ask(Op.ADMIT, peer=join.site, peer_incarnation=join.incarnation)
        if grant is None:
            return
        if not grant.granted:
            if grant.primary != self.site:
                self._deposed(grant.message)
            else:
                self.side.tell('join_failed', 'the witness refused to admit %s: %s' % (join.site, grant.message))
            return
        if not self._forwarding(Role.PRIMARY, grant.epoch):
            self._exclude('Before cannot forward to the admitted follower %s' % join.site)
            return
        with self.lock:
            self.role = Role.PRIMARY
            self.epoch = max(self.epoch, grant.epoch)
            self.follower = (join.after, join.incarnation, record['seq'])
        record.update(admitted_s=time.monotonic() - record.pop('t0'), admitted_wall=time.time(), epoch=grant.epoch)
        self.events.publish(String(data=json.dumps(record, sort_keys=True)))
        self.side.told.clear()
        rospy.loginfo('%s: %s is the follower again (epoch %d)', self.name, join.site, grant.epoch)

    # -- joins (follower side) ---------------------------------------------------------
    def _ask_to_join(self, _event):
        with self.lock:
            if self.role != Role.BACKUP:
                return
            if self.joined:
                conf = self.configuration_seen
                waited = time.monotonic() - self.joined_since
                if conf is None or self.site in (conf.primary, conf.backup) \
                        or waited < max(2 * self.ack_timeout, 4 * self.join_period):
                    return
        if self.joined:
            # Joined, but never admitted (the witness refused it, or its configuration was missed): ask.
            status = self.side.ask(Op.STATUS)
            if status is None or status.backup == self.site:
                return
            with self.lock:
                self.joined = False
            self.side.tell('backup_invalid', '%s: not admitted by the witness after its state transfer '
                           '(epoch %d); it joins again' % (self.site, status.epoch))
            return
        if self.ports.connections('transfers'):
            self.ports.publish('join', Join(site=self.site, after=self.name, incarnation=self.witness.incarnation,
                                            last_seq=self.accepted, stamp=rospy.Time.now()))

    def _on_transfer(self, cp):
        with self.lock:
            problem = None
            if self.role != Role.BACKUP or self.joined:
                problem = '%s is not joining' % self.name
            elif not cp.full or not cp.sender.startswith('/%s/' % self.peer):
                problem = '%s does not follow %s' % (self.name, cp.sender)
            elif cp.epoch < self.epoch:
                problem = 'state transfer of epoch %d, older than epoch %d' % (cp.epoch, self.epoch)
            if problem is None:
                try:
                    result = self.state_calls.call(self.set_state, self.state_timeout, cp.state)
                    error = '' if result.success else 'the server refused the state: %s' % result.message
                except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
                    self.set_state = rospy.ServiceProxy('set_state', SetState, persistent=True)
                    error = 'cannot set the server state: %s' % e
                if error:
                    problem = error
                else:
                    for reply in cp.cache:
                        self._remember(reply)
                    self.ports.publish('stored', Checkpoint(seq=self.computed, sender=self.name, full=True,
                                                            cache=cp.cache, epoch=cp.epoch))
                    self.joined = True
                    self.accepted = cp.seq
                    self.joined_since = time.monotonic()
                    self.epoch = max(self.epoch, cp.epoch)
                    self.ports.publish('peer_acks', Notify(origin='', id=cp.seq, seq=self.computed))
        if problem is not None:
            self.side.tell('stray_checkpoint', 'state transfer %d from %s refused, nothing changed: %s'
                           % (cp.seq, cp.sender, problem), cp.sender)
        else:
            rospy.loginfo('%s: joined %s (state transfer %d, epoch %d)', self.name, cp.sender, cp.seq, cp.epoch)

    # -- the witness's configuration ----------------------------------------------------
    def _on_configuration(self, conf):
        deposed = excluded = False
        with self.lock:
            if self.configuration_seen is None or conf.epoch >= self.configuration_seen.epoch:
                self.configuration_seen = conf
            if conf.epoch <= self.epoch:
                return
            if (conf.primary == self.site and self.role != Role.BACKUP) or \
                    (conf.backup == self.site and self.role == Role.BACKUP and self.joined):
                self.epoch = conf.epoch   # this replica's own configuration (an After an adaptation started)
                return
            if self.role != Role.BACKUP and not self.deposed and conf.primary != self.site:
                deposed = True
            elif self.role == Role.BACKUP and self.joined and self.site not in (conf.primary, conf.backup):
                self.joined = False
                excluded = True
        if deposed:
            self._deposed('%s is the primary of epoch %d (%s)' % (conf.primary, conf.epoch, conf.reason))
        if excluded:
            self.side.tell('excluded', '%s was excluded at epoch %d (%s): it cannot take over and joins again'
                           % (self.site, conf.epoch, conf.reason))

    # -- role changes (Recovery) ----------------------------------------------------------
    def _on_set_role(self, req):
        role = Role(req.role)
        with self.lock:
            refused = _refused(self.role, role)
            if refused:
                return refused
            released = []
            if self.role == Role.BACKUP and role == Role.ALONE:
                if not (self.joined or req.initial):
                    return SetRoleResponse(success=False, message='%s holds no state: it never joined' % self.name)
                # Wait for the results of every forwarded request Before passed on (fenced now).
                if not self.lock.wait_for(lambda: self.computed >= req.last_seq, timeout=2.0):
                    return SetRoleResponse(success=False, message='computed %d of the %d forwarded requests'
                                           % (self.computed, req.last_seq))
                self.role = role
                self.epoch = max(self.epoch, req.epoch)
            elif self.role == Role.PRIMARY and role == Role.ALONE:
                if req.epoch and req.epoch < self.epoch:
                    return SetRoleResponse(success=True, message='role PRIMARY kept: epoch %d is newer than %d'
                                           % (self.epoch, req.epoch), last_seq=self.computed)
                released = self._go_alone(req.epoch)
            elif self.role == role:
                self.epoch = max(self.epoch, req.epoch)
            last_seq = self.computed
        for reply in released:
            self.ports.publish('out', reply)
        rospy.loginfo('%s: role is now %s (epoch %d)', self.name, role.name, req.epoch)
        return SetRoleResponse(success=True, message='role %s' % role.name, last_seq=last_seq)
