"""Primary-Backup Replication (paper section 5.2.2): the After of each replica."""
import threading
import time

import rospy
from aft_msgs.msg import Checkpoint, CheckpointAck
from aft_msgs.srv import GetState, SetRole, SetRoleResponse, SetState

from .. import config
from ..checkpoint import CheckpointReceiver, CheckpointSender, Decision
from ..errors import RoleError
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import Role, check_role_change
from .bpa_nodes import AfterNode, BeforeNode
from .params import param
from .ports import wait_for_connections
from .protocol_node import ROLES


class PbrBeforeNode(BeforeNode):
    """PBR's Before: a pass-through (PBR has no Before action) that follows the replica's role, so
    that Recovery promotes Before and After whatever the mechanism (a switch to or from LFR keeps
    Recovery's list of nodes the same shape).

    Parameters: ~role (primary | backup | alone, default primary)
    Subscribes: pro2bfr (aft_msgs/Request), port ``inp``.  Publishes: bfr2prd (aft_msgs/Request), port ``out``.
    Services: ~set_role (aft_msgs/SetRole, last_seq 0: it holds nothing), ~rebind (aft_msgs/Rebind)
    """

    def __init__(self):
        self.role = ROLES[param('role', lambda n, v: config.one_of(n, v, ROLES), 'primary')]
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


class PbrAfterNode(AfterNode):
    """PBR's After. As primary: captures the server's state after each request, checkpoints it to
    the backup's After and passes the reply on once the backup acknowledged it. As backup: sets
    its server's state from each checkpoint, stores the reply in its Protocol, acknowledges.

    Parameters:
        ~role (primary | backup | alone, default primary)
        ~ack_timeout (float, 1 s): a checkpoint not acknowledged for this long means the backup is
            lost: held replies are released and the replica goes on ALONE.
        ~connect_timeout (float, 10 s): how long set-up waits for the peer's After.
        ~apply_period (float, 0.01 s; 0 = at once): a backup applies the newest checkpointed state
            to its server at most this often, and always before it takes over.
        ~replaces (str, default none): the primary After this one replaces (an adaptation's update):
            the backup then follows this one's checkpoints instead.
    Services called:
        get_state (aft_msgs/GetState), set_state (aft_msgs/SetState): the server's state manager.
    Subscribes:
        prd2aft (aft_msgs/Reply), port ``inp``
        acks (aft_msgs/CheckpointAck), port ``acks``: the backup's acknowledgments
        peer_checkpoints (aft_msgs/Checkpoint), port ``peer_checkpoints``: the primary's checkpoints
    Publishes:
        aft2pro (aft_msgs/Reply), port ``out``
        checkpoints (aft_msgs/Checkpoint), port ``checkpoints``: to the backup's After
        peer_acks (aft_msgs/CheckpointAck), port ``peer_acks``: to the primary's After
        aft2pro_s (aft_msgs/Checkpoint), port ``stored``: replies for this replica's Protocol
    Services:
        ~rebind (aft_msgs/Rebind), ~set_role (aft_msgs/SetRole)
    """

    def __init__(self):
        role = ROLES[param('role', lambda n, v: config.one_of(n, v, ROLES), 'primary')]
        self.ack_timeout = param('ack_timeout', config.positive_float, 1.0)
        self.connect_timeout = param('connect_timeout', config.positive_float, 10.0)
        self.apply_period = param('apply_period', lambda n, v: 0.0 if v == 0 else config.positive_float(n, v),
                                  0.01)
        self.replaces = param('replaces', config.non_empty_str, '')
        # Checkpoints are numbered from the wall clock (microseconds), so that an After replacing
        # another one (an adaptation) numbers above it: the backup's Protocol compares them.
        self.first_seq = int(time.time() * 1e6)
        self.pending_state = None   # backup: the newest checkpointed state not yet applied
        super(PbrAfterNode, self).__init__(
            extra_ports=[PortSpec('checkpoints', PUBLISH, 'aft_msgs/Checkpoint'),
                         PortSpec('acks', SUBSCRIBE, 'aft_msgs/CheckpointAck'),
                         PortSpec('peer_checkpoints', SUBSCRIBE, 'aft_msgs/Checkpoint'),
                         PortSpec('peer_acks', PUBLISH, 'aft_msgs/CheckpointAck'),
                         PortSpec('stored', PUBLISH, 'aft_msgs/Checkpoint')],
            extra_callbacks={'acks': self._on_ack, 'peer_checkpoints': self._on_checkpoint})
        self.role = role
        self.sender = CheckpointSender(role, self.first_seq) if role != Role.BACKUP else None
        self.receiver = CheckpointReceiver() if role == Role.BACKUP else None
        self.lock = threading.Lock()
        self.get_state = rospy.ServiceProxy('get_state', GetState, persistent=True)
        self.set_state = rospy.ServiceProxy('set_state', SetState, persistent=True)

    def setup(self, timeout):
        for name in ('checkpoints', 'peer_acks', 'acks', 'peer_checkpoints'):
            self.ports.bind(name)
        self.ports.bind('stored', 'aft2pro_s')
        try:
            rospy.wait_for_service('get_state' if self.role != Role.BACKUP else 'set_state', timeout)
        except rospy.ROSException:
            rospy.logerr('%s: the server state manager (%s) is not available', self.name,
                         rospy.resolve_name('get_state' if self.role != Role.BACKUP else 'set_state'))
            return False
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
        if self.role == Role.BACKUP and self.apply_period > 0:
            self.applier = rospy.Timer(rospy.Duration(self.apply_period), self._apply_pending)
        rospy.Service('~set_role', SetRole, self._on_set_role)
        rospy.loginfo('%s: ready as %s', self.name, self.role.name)
        return True

    # -- suspension (adaptation) ---------------------------------------------------
    def quiescent(self):
        """Primary: every checkpoint acknowledged (no reply held)."""
        with self.lock:
            return self.sender is None or not self.sender.held

    def before_suspend(self):
        """Backup: apply the newest checkpointed state now, so a replacement After (or another
        mechanism) finds the server up to date."""
        with self.lock:
            self._apply_locked()

    # -- primary ----------------------------------------------------------------
    def handle(self, reply):
        with self.lock:
            if self.sender is None or not self.sender.needs_checkpoint():
                return reply
            try:
                state = self.get_state().state
            except (rospy.ServiceException, rospy.ROSException) as e:
                # The request ran but cannot be checkpointed: replying would leave the backup behind.
                # Fail-stop: this replica goes down (its site with it, its nodes being required), the
                # backup takes over and executes the request the Proxy re-sends.
                rospy.logfatal('%s: cannot capture the server state after %s/%d (%s): stopping this replica',
                               self.name, reply.origin, reply.id, e)
                rospy.signal_shutdown('cannot capture the server state')
                return None
            seq = self.sender.hold(reply, time.monotonic())
            self.ports.publish('checkpoints', Checkpoint(seq=seq, first_seq=self.first_seq, sender=self.name,
                                                         replaces=self.replaces, reply=reply, state=state))
        return None

    def _release(self, replies):
        for reply in replies:
            self.ports.publish('out', reply)

    def _on_ack(self, ack):
        with self.lock:
            if self.sender is None:
                return
            released, lost = self.sender.on_ack(ack.seq, ack.ok)
            self._release(released)
            if lost:
                self.role = Role.ALONE
        if lost:
            rospy.logerr('%s: the backup refused checkpoint %d (%s): going on ALONE', self.name, ack.seq, ack.error)

    def _check_acks(self, _event):
        with self.lock:
            if self.sender is None or not self.sender.overdue(time.monotonic(), self.ack_timeout):
                return
            rospy.logerr('%s: no acknowledgment from the backup for %.1f s: going on ALONE', self.name,
                         self.ack_timeout)
            self._release(self.sender.go_alone())
            self.role = Role.ALONE

    # -- backup -----------------------------------------------------------------
    def _on_checkpoint(self, cp):
        with self.lock:
            if self.receiver is None:
                decision = Decision.FENCED
            else:
                decision = self.receiver.decide(cp.seq, cp.sender, cp.first_seq, cp.replaces)
            error = ''
            if decision == Decision.GAP:
                error = 'checkpoint %d received after %d: one is missing' % (cp.seq, self.receiver.last_seq)
            elif decision == Decision.FENCED:
                error = ('%s is no longer a backup of %s%s' % (self.name, cp.sender, ': ' + self.receiver.invalid
                         if self.receiver is not None and self.receiver.invalid else ''))
            if error and self.receiver is not None and not self.receiver.invalid:
                # A backup that refuses a checkpoint no longer mirrors the primary that sent it (which
                # goes on alone): it must never take over with what it has.
                self.receiver.failed(cp.seq, error)
            if error:
                rospy.logerr('%s: checkpoint %d refused: %s', self.name, cp.seq, error)
            # Acknowledged once held. A promotion takes this lock and applies the state first.
            self.ports.publish('peer_acks', CheckpointAck(seq=cp.seq, ok=not error, error=error))
            if decision == Decision.APPLY:
                self.receiver.accept(cp.seq, cp.sender)
                self.ports.publish('stored', Checkpoint(seq=cp.seq, sender=cp.sender, reply=cp.reply))
                self.pending_state = (cp.seq, cp.state)
                if self.apply_period == 0:
                    self._apply_locked()

    def _apply_pending(self, _event=None):
        with self.lock:
            self._apply_locked()

    def _apply_locked(self):
        """Apply the newest checkpointed state to the server; on failure the backup is invalid."""
        if self.pending_state is None or self.receiver is None or self.receiver.invalid:
            return
        seq, state = self.pending_state
        try:
            result = self.set_state(state)
            error = '' if result.success else 'the server refused the state: %s' % result.message
        except (rospy.ServiceException, rospy.ROSException) as e:
            self.set_state = rospy.ServiceProxy('set_state', SetState, persistent=True)
            error = 'cannot set the server state: %s' % e
        self.pending_state = None
        if error:
            self.receiver.failed(seq, error)
            rospy.logerr('%s: %s', self.name, self.receiver.invalid)
            self.ports.publish('peer_acks', CheckpointAck(seq=seq, ok=False, error=self.receiver.invalid))

    # -- role changes -----------------------------------------------------------
    def _on_set_role(self, req):
        role = Role(req.role)
        with self.lock:
            try:
                if self.role == Role.BACKUP and role == Role.ALONE:
                    self._apply_locked()
                    last_seq = self.receiver.promote()
                    self.sender = CheckpointSender(Role.ALONE)
                elif self.role == Role.PRIMARY and role == Role.ALONE:
                    self._release(self.sender.go_alone())
                    last_seq = self.sender.seq
                elif self.role == role:
                    last_seq = self.receiver.last_seq if self.receiver else self.sender.seq
                else:
                    raise RoleError('role change %s -> %s is not allowed' % (self.role.name, role.name))
            except RoleError as e:
                return SetRoleResponse(success=False, message=str(e))
            self.role = role
        rospy.loginfo('%s: role is now %s (last checkpoint %d)', self.name, role.name, last_seq)
        return SetRoleResponse(success=True, message='role %s' % role.name, last_seq=last_seq)
