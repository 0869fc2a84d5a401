"""Protocol: duplicate detection and sequencing, the entry of a replica's FTM graph."""
import threading
import time

import rospy
from aft_msgs.msg import Reply
from aft_msgs.srv import SetRole, SetRoleResponse

from .. import config
from ..errors import RoleError
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import Answer, Forward, ProtocolCore, Role
from .params import param
from .ports import Ports, wait_for_connections

ROLES = {'primary': Role.PRIMARY, 'backup': Role.BACKUP, 'alone': Role.ALONE}


class ProtocolNode(object):
    """Answers duplicate requests from its reply cache and hands the others, one at a time,
    to Before. As a backup it executes nothing and stores the replies checkpoints carry.

    Parameters:
        ~role (primary | backup | alone, default primary): a backup starts with ``requests`` unbound.
        ~processing_timeout (float, 10 s): an executing request with no result after this long
            is answered with an error.
        ~cache_capacity (int, 100000): safety limit of the reply cache.
        ~listen_as_backup (bool, false): bind ``requests`` even as a backup (queued, not executed,
            until promoted): for a Protocol behind an entry node (a SEC gate) that Recovery binds.
        ~bind_input (bool, true): false starts with ``requests`` unbound, whatever the role (a
            mechanism the Adaptation Engine launches ahead and binds in the pause).
    Subscribes:
        pxy2pro (aft_msgs/Request), port ``requests``: from the Proxies.
        aft2pro (aft_msgs/Reply), port ``from_after``: results of executed requests.
        aft2pro_s (aft_msgs/Checkpoint), port ``stored``: replies carried by checkpoints (backup).
    Publishes:
        pro2pxy (aft_msgs/Reply), port ``replies``: to the Proxies.
        pro2bfr (aft_msgs/Request), port ``to_before``.
    Services:
        ~rebind (aft_msgs/Rebind), ~set_role (aft_msgs/SetRole), ~suspend and ~resume (aft_msgs/Suspend):
        suspended, it holds the requests arriving and answers once nothing is executing.
    """

    def __init__(self):
        role_name = param('role', lambda n, v: config.one_of(n, v, ROLES), 'primary')
        self.processing_timeout = param('processing_timeout', config.positive_float, 10.0)
        capacity = param('cache_capacity', config.non_negative_int, 100000)
        self.listen_as_backup = param('listen_as_backup', lambda n, v: bool(v), False)
        self.bind_input = param('bind_input', lambda n, v: bool(v), True)
        self.core = ProtocolCore(ROLES[role_name], capacity)
        self.lock = threading.Condition()
        self.ports = Ports(
            [PortSpec('requests', SUBSCRIBE, 'aft_msgs/Request'),
             PortSpec('replies', PUBLISH, 'aft_msgs/Reply'),
             PortSpec('to_before', PUBLISH, 'aft_msgs/Request'),
             PortSpec('from_after', SUBSCRIBE, 'aft_msgs/Reply'),
             PortSpec('stored', SUBSCRIBE, 'aft_msgs/Checkpoint')],
            {'requests': self._on_request, 'from_after': self._on_result, 'stored': self._on_stored})
        # Suspended (adaptation), it holds new requests and is quiescent once nothing executes.
        self.ports.suspension(hold=['requests'], quiescent=self._quiescent)
        self.name = rospy.get_name()

    def _quiescent(self):
        with self.lock:
            # A backup's queue waits for a promotion, not for this component: it is not "inside".
            return self.core.current is None and (self.core.role == Role.BACKUP or not self.core.queue)

    def setup(self, timeout):
        self.ports.bind('replies', 'pro2pxy')
        self.ports.bind('to_before', 'pro2bfr')
        self.ports.bind('from_after', 'aft2pro')
        self.ports.bind('stored', 'aft2pro_s')
        missing = wait_for_connections(self.ports, ['to_before', 'from_after'], timeout)
        if missing:
            rospy.logerr('%s: Before/After not connected within %.1f s (ports %s)', self.name, timeout, missing)
            return False
        if self.bind_input and (self.core.role != Role.BACKUP or self.listen_as_backup):
            self.ports.bind('requests', 'pxy2pro')
        self.timer = rospy.Timer(rospy.Duration(min(1.0, self.processing_timeout / 4)), self._check_overdue)
        rospy.Service('~set_role', SetRole, self._on_set_role)
        self.ports.advertise_service()
        rospy.loginfo('%s: ready as %s', self.name, self.core.role.name)
        return True

    def _act(self, actions):
        for action in actions:
            if isinstance(action, Forward):
                self.ports.publish('to_before', action.request)
            elif isinstance(action, Answer):
                self.ports.publish('replies', action.reply)

    def _on_request(self, request):
        with self.lock:
            self._act(self.core.on_request(request, time.monotonic()))
            evicted = self.core.cache.evicted
        if evicted:
            rospy.logwarn_throttle(10, '%s: reply cache over capacity, %d replies evicted' % (self.name, evicted))

    def _on_result(self, reply):
        with self.lock:
            before = self.core.stats.stray_results
            self._act(self.core.on_result(reply, time.monotonic()))
            stray = self.core.stats.stray_results > before
        if stray:
            rospy.logwarn('%s: result of %s/%d matches no executing request', self.name, reply.origin, reply.id)

    def _on_stored(self, checkpoint):
        with self.lock:
            self.core.on_stored(checkpoint.reply, checkpoint.seq, checkpoint.sender)
            self.lock.notify_all()

    def _check_overdue(self, _event):
        with self.lock:
            request = self.core.overdue(time.monotonic(), self.processing_timeout)
            if request is None:
                return
            rospy.logerr('%s: no result for %s/%d after %.1f s: answering with an error',
                         self.name, request.origin, request.id, self.processing_timeout)
            error = Reply(id=request.id, origin=request.origin, client=request.client,
                          oldest_pending=request.oldest_pending, attempt=request.attempt, status=Reply.ERROR,
                          error='no result within %.1f s' % self.processing_timeout)
            self._act(self.core.on_result(error, time.monotonic()))

    def _on_set_role(self, req):
        role = Role(req.role)
        with self.lock:
            if not self.lock.wait_for(lambda: self.core.can_take_over(req.last_seq), timeout=2.0):
                return SetRoleResponse(success=False, message='replies up to checkpoint %d not stored (have %d)'
                                       % (req.last_seq, self.core.last_stored_seq))
            try:
                actions = self.core.set_role(role, time.monotonic())
            except RoleError as e:
                return SetRoleResponse(success=False, message=str(e))
            self._act(actions)
        rospy.loginfo('%s: role is now %s', self.name, role.name)
        return SetRoleResponse(success=True, message='role %s' % role.name, last_seq=self.core.last_stored_seq)
