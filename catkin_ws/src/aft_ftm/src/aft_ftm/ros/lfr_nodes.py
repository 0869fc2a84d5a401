"""Leader-Follower Replication (paper Table II): the leader forwards each request to the follower,
both compute, the leader replies once the follower computed it too, then notifies it. No state is
transferred (bandwidth low), but the server must be deterministic."""
import threading
import time

import rospy
from aft_msgs.msg import Checkpoint, Notify
from aft_msgs.srv import SetRole, SetRoleResponse

from .. import config, mechanisms
from ..errors import RoleError
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import Role, check_role_change
from .bpa_nodes import AfterNode, BeforeNode
from .params import param
from .ports import wait_for_connections
from .protocol_node import ROLES


def _role():
    return ROLES[param('role', lambda n, v: config.one_of(n, v, ROLES), 'primary')]


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

    Parameters: ~role (primary | backup | alone)
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
            self.role = role
            return SetRoleResponse(success=True, message='role %s' % role.name, last_seq=self.passed)


class LfrAfterNode(AfterNode):
    """LFR's After. Leader: holds each reply until the follower says it computed the request, then
    passes it on and notifies the follower. Follower: stores each computed reply in its Protocol
    (for the requests the Proxy re-sends after a failover) and tells the leader.

    Parameters:
        ~role (primary | backup | alone)
        ~server_deterministic (bool, required): the application's declaration; LFR refuses to start
            on a non-deterministic server.
        ~ack_timeout (float, 1 s): the follower silent this long about a request means it is lost.
        ~connect_timeout (float, 10 s)
    Subscribes: prd2aft (aft_msgs/Reply), port ``inp``; acks (aft_msgs/Notify), port ``acks``;
        peer_notify (aft_msgs/Notify), port ``notifications``.
    Publishes: aft2pro (aft_msgs/Reply), port ``out``; peer_acks (aft_msgs/Notify), port ``peer_acks``;
        notify (aft_msgs/Notify), port ``notify``; aft2pro_s (aft_msgs/Checkpoint), port ``stored``.
    Services: ~set_role (aft_msgs/SetRole), ~rebind (aft_msgs/Rebind)
    """

    def __init__(self):
        mechanisms.check_application('lfr', param('server_deterministic', config.boolean, required=True),
                                     state_access=False)
        self.role = _role()
        self.ack_timeout = param('ack_timeout', config.positive_float, 1.0)
        self.connect_timeout = param('connect_timeout', config.positive_float, 10.0)
        super(LfrAfterNode, self).__init__(
            extra_ports=[PortSpec('acks', SUBSCRIBE, 'aft_msgs/Notify'),
                         PortSpec('peer_acks', PUBLISH, 'aft_msgs/Notify'),
                         PortSpec('notify', PUBLISH, 'aft_msgs/Notify'),
                         PortSpec('notifications', SUBSCRIBE, 'aft_msgs/Notify'),
                         PortSpec('stored', PUBLISH, 'aft_msgs/Checkpoint')],
            extra_callbacks={'acks': self._on_ack, 'notifications': self._on_notify})
        self.lock = threading.Condition()
        self.held = {}          # leader: (origin, id) -> (reply, since)
        self.acked = set()      # leader: acks that came before our own result
        self.computed = 0       # follower: results of forwarded requests
        self.notified = 0

    def setup(self, timeout):
        for name in ('acks', 'peer_acks', 'notify'):
            self.ports.bind(name)
        self.ports.bind('notifications', 'peer_notify')
        self.ports.bind('stored', 'aft2pro_s')
        peer = {Role.PRIMARY: ['notify', 'acks'], Role.BACKUP: ['peer_acks', 'notifications'], Role.ALONE: []}
        missing = wait_for_connections(self.ports, peer[self.role], self.connect_timeout)
        if missing:
            rospy.logerr('%s: the peer After is not connected on %s', self.name,
                         [self.ports.topic(n) for n in missing])
            return False
        if not super(LfrAfterNode, self).setup(timeout):
            return False
        self.timer = rospy.Timer(rospy.Duration(min(0.1, self.ack_timeout / 4)), self._check_acks)
        rospy.Service('~set_role', SetRole, self._on_set_role)
        return True

    def quiescent(self):
        """Leader: no reply waiting for the follower (checked by ~suspend)."""
        with self.lock:
            return not self.held

    def handle(self, reply):
        key = (reply.origin, reply.id)
        with self.lock:
            if self.role == Role.BACKUP:
                self.computed += 1
                self.ports.publish('stored', Checkpoint(seq=self.computed, sender=self.name, reply=reply))
                self.ports.publish('peer_acks', Notify(origin=reply.origin, id=reply.id, seq=self.computed))
                self.lock.notify_all()
                return None
            if self.role == Role.PRIMARY:
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
            held = self.held.pop(key, None)
            if held is None:
                if self.role == Role.PRIMARY:
                    self.acked.add(key)
                return
        self._release(held[0])

    def _on_notify(self, _notification):
        self.notified += 1   # the leader replied: nothing more to do for it (the Protocol's cache is GC'd by watermark)

    def _go_alone(self):
        self.role = Role.ALONE
        released = [r for r, _ in sorted(self.held.values(), key=lambda h: h[1])]
        self.held.clear()
        self.acked.clear()
        return released

    def _check_acks(self, _event):
        with self.lock:
            now = time.monotonic()
            if self.role != Role.PRIMARY or not any(now - t > self.ack_timeout for _, t in self.held.values()):
                return
            rospy.logerr('%s: the follower did not compute a request for %.1f s: going on ALONE', self.name,
                         self.ack_timeout)
            released = self._go_alone()
        for reply in released:
            self.ports.publish('out', reply)

    def _on_set_role(self, req):
        role = Role(req.role)
        with self.lock:
            refused = _refused(self.role, role)
            if refused:
                return refused
            released = []
            if self.role == Role.BACKUP and role == Role.ALONE:
                # Wait for the results of every forwarded request Before passed on (fenced now).
                if not self.lock.wait_for(lambda: self.computed >= req.last_seq, timeout=2.0):
                    return SetRoleResponse(success=False, message='computed %d of the %d forwarded requests'
                                           % (self.computed, req.last_seq))
                self.role = role
            elif self.role == Role.PRIMARY and role == Role.ALONE:
                released = self._go_alone()
            last_seq = self.computed
        for reply in released:
            self.ports.publish('out', reply)
        rospy.loginfo('%s: role is now %s', self.name, role.name)
        return SetRoleResponse(success=True, message='role %s' % role.name, last_seq=last_seq)
