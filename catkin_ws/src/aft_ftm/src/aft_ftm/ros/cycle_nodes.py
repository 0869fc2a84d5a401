"""Before-Proceed-After for publish/subscribe nodes (the second paper's on-going work, section III.D).

A pub/sub node has no request whose reply marks the end of its work: the end of each processing
cycle is captured instead, by a Terminate statement the node calls at the end of every iteration of
its main loop (:class:`Terminate`, a library function as in the paper). It publishes the node's
state after the cycle on ``cycle_end``. The node's outputs are remapped to its After.

:class:`CycleAfterNode` is PBR's After for such a node, on each replica:

- primary: passes every output on at once (a control loop cannot wait for a round trip), and at
  each cycle end checkpoints the state to the backup's After, which acknowledges it;
- backup: its own node runs on the same inputs, but its outputs are not the system's (they are
  counted, not passed on); each checkpoint's state is set into its node (its ~set_state), so that
  the node continues from the primary's state when it takes over;
- ``~set_role`` ALONE (the watchdog, at failover): the backup passes its node's outputs on from
  then on; the primary goes on without checkpoints.

If the primary dies between a cycle's output and that cycle's checkpoint, the backup resumes from
the previous cycle's state: one cycle is computed again, which for a controller means one more
integration step of its error, not a lost or duplicated command.
"""
import threading
import time

import rospy
import roslib.message
from aft_msgs.msg import Checkpoint, CheckpointAck, CycleEnd
from aft_msgs.srv import SetRole, SetRoleResponse, SetState

from .. import config
from ..checkpoint import CheckpointReceiver, CheckpointSender, Decision
from ..errors import RoleError
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import Role, check_role_change
from .params import param
from .ports import Ports, wait_for_connections
from .protocol_node import ROLES


class Terminate(object):
    """The Terminate statement of a pub/sub node: call it at the end of each cycle.

    ``get_state()`` returns the node's state as bytes. Publishes on ``cycle_end``
    (aft_msgs/CycleEnd; remap it to the replica's After).
    """

    def __init__(self, get_state, topic='cycle_end'):
        self.get_state = get_state
        self.cycle = 0
        self.publisher = rospy.Publisher(topic, CycleEnd, queue_size=None, tcp_nodelay=True)

    def __call__(self, stamp=None):
        self.cycle += 1
        self.publisher.publish(CycleEnd(node=rospy.get_name(), cycle=self.cycle, stamp=stamp or rospy.Time.now(),
                                        state=self.get_state()))
        return self.cycle


class CycleAfterNode(object):
    """PBR's After for a publish/subscribe node (see the module's docstring).

    Parameters:
        ~role (primary | backup | alone, default primary)
        ~msg_type (str, required): the type of the node's output, e.g. aft_msgs/CarCommand
        ~ack_timeout (float, 0.5 s): a checkpoint unacknowledged this long means the backup is lost:
            the primary goes on alone.
        ~connect_timeout (float, 10 s): how long set-up waits for the peer's After.
    Subscribes:
        raw (~msg_type), port ``raw``: the node's outputs
        cycle_end (aft_msgs/CycleEnd), port ``cycle_end``: the node's Terminate statements
        peer_checkpoints (aft_msgs/Checkpoint), port ``peer_checkpoints``: the primary's checkpoints
        peer_acks (aft_msgs/CheckpointAck), port ``peer_acks``: the backup's acknowledgments
    Publishes:
        out (~msg_type), port ``out``: the replicated node's outputs, for the rest of the system
        checkpoints (aft_msgs/Checkpoint), port ``checkpoints``
        acks (aft_msgs/CheckpointAck), port ``acks``
    Services called:
        set_state (aft_msgs/SetState): the node's state manager (backup)
    Services:
        ~set_role (aft_msgs/SetRole), ~rebind (aft_msgs/Rebind), ~suspend/~resume (aft_msgs/Suspend)
    """

    def __init__(self):
        self.name = rospy.get_name()
        self.role = ROLES[param('role', lambda n, v: config.one_of(n, v, ROLES), 'primary')]
        msg_type = param('msg_type', config.service_type, required=True)
        if roslib.message.get_message_class(msg_type) is None:
            raise config.ConfigError('parameter %s: unknown message type %s'
                                     % (rospy.resolve_name('~msg_type'), msg_type))
        self.ack_timeout = param('ack_timeout', config.positive_float, 0.5)
        self.connect_timeout = param('connect_timeout', config.positive_float, 10.0)
        self.first_seq = int(time.time() * 1e6)   # numbered from the clock, as PBR's After
        self.sender = CheckpointSender(self.role, self.first_seq) if self.role != Role.BACKUP else None
        self.receiver = CheckpointReceiver() if self.role == Role.BACKUP else None
        self.lock = threading.Lock()
        self.forwarded = 0
        self.withheld = 0        # a backup's own outputs, not passed on
        self.checkpoints = 0
        self.ports = Ports([PortSpec('raw', SUBSCRIBE, msg_type), PortSpec('out', PUBLISH, msg_type),
                            PortSpec('cycle_end', SUBSCRIBE, 'aft_msgs/CycleEnd'),
                            PortSpec('checkpoints', PUBLISH, 'aft_msgs/Checkpoint'),
                            PortSpec('acks', PUBLISH, 'aft_msgs/CheckpointAck'),
                            PortSpec('peer_checkpoints', SUBSCRIBE, 'aft_msgs/Checkpoint'),
                            PortSpec('peer_acks', SUBSCRIBE, 'aft_msgs/CheckpointAck')],
                           {'raw': self._on_output, 'cycle_end': self._on_cycle_end,
                            'peer_checkpoints': self._on_checkpoint, 'peer_acks': self._on_ack})
        self.ports.suspension(['raw', 'cycle_end'])
        self.set_state = rospy.ServiceProxy('set_state', SetState, persistent=True)

    def setup(self, timeout):
        for name in ('out', 'checkpoints', 'acks', 'peer_checkpoints', 'peer_acks', 'raw', 'cycle_end'):
            self.ports.bind(name)
        if self.role == Role.BACKUP:
            try:
                rospy.wait_for_service('set_state', timeout)
            except rospy.ROSException:
                rospy.logerr('%s: the node\'s state manager (%s) is not available', self.name,
                             rospy.resolve_name('set_state'))
                return False
        peers = {Role.PRIMARY: ['checkpoints', 'peer_acks'], Role.BACKUP: ['peer_checkpoints', 'acks'],
                 Role.ALONE: []}[self.role]
        missing = wait_for_connections(self.ports, peers, self.connect_timeout)
        if missing:
            rospy.logerr('%s: the peer After is not connected on %s within %.1f s', self.name,
                         [self.ports.topic(n) for n in missing], self.connect_timeout)
            return False
        rospy.Service('~set_role', SetRole, self._on_set_role)
        self.ports.advertise_service()
        if self.sender is not None:
            # On the wall clock, as the acknowledgments' deadlines: simulated time may run at any rate.
            threading.Thread(target=self._watch_acks, name='acks', daemon=True).start()
        return True

    # -- outputs and cycles ----------------------------------------------------------------------
    def _on_output(self, msg):
        with self.lock:
            passing = self.role != Role.BACKUP
            if passing:
                self.forwarded += 1
            else:
                self.withheld += 1
        if passing:
            self.ports.publish('out', msg)

    def _on_cycle_end(self, end):
        with self.lock:
            if self.sender is None or not self.sender.needs_checkpoint():
                return
            seq = self.sender.hold(end.cycle, time.monotonic())
            self.checkpoints += 1
            checkpoint = Checkpoint(seq=seq, first_seq=self.first_seq, sender=self.name, state=end.state)
        self.ports.publish('checkpoints', checkpoint)

    def _on_ack(self, ack):
        with self.lock:
            if self.sender is None or self.sender.role != Role.PRIMARY:
                return
            _, lost = self.sender.on_ack(ack.seq, ack.ok)
            if lost:   # outputs are never held here (a control loop cannot wait): no witness to ask
                self.sender.go_alone()
                self.role = Role.ALONE
        if lost:
            rospy.logerr('%s: the backup refused checkpoint %d (%s): going on alone', self.name, ack.seq, ack.error)

    def _watch_acks(self):
        while not rospy.is_shutdown() and self.role == Role.PRIMARY:
            time.sleep(self.ack_timeout / 4.0)
            self._check_acks()

    def _check_acks(self):
        with self.lock:
            if self.sender is None or self.sender.role != Role.PRIMARY:
                return
            if not self.sender.overdue(time.monotonic(), self.ack_timeout):
                return
            self.sender.go_alone()
            self.role = Role.ALONE
        rospy.logerr('%s: a checkpoint was not acknowledged within %.2f s: the backup is lost, going on alone',
                     self.name, self.ack_timeout)

    # -- backup ----------------------------------------------------------------------------------
    def _on_checkpoint(self, cp):
        # Checkpoints arrive one at a time (one subscription, one thread), in order. The node's
        # set_state is called outside the lock, so that a slow node never delays a promotion.
        with self.lock:
            if self.receiver is None:
                return
            decision = self.receiver.decide(cp.seq, cp.sender, cp.first_seq, cp.replaces)
            if decision == Decision.GAP:
                self.receiver.failed(cp.seq, 'a checkpoint is missing before it')
        error = ''
        if decision == Decision.APPLY:
            try:
                answer = self.set_state(state=cp.state)
                ok, error = answer.success, answer.message
            except (rospy.ServiceException, rospy.ROSException) as e:
                ok, error = False, 'set_state failed: %s' % e
            with self.lock:
                if ok:
                    self.receiver.accept(cp.seq, cp.sender)
                else:
                    self.receiver.failed(cp.seq, error)
        elif decision == Decision.REACK:
            ok = True
        else:
            ok = False
            error = '%s: checkpoint %d of %s refused (%s)' % (self.name, cp.seq, cp.sender, decision.name)
        if not ok:
            rospy.logerr(error)
        self.ports.publish('acks', CheckpointAck(seq=cp.seq, ok=ok, error=error))

    def _on_set_role(self, req):
        role = Role(req.role)
        with self.lock:
            try:
                check_role_change(self.role, role)
                last_seq = 0
                if self.receiver is not None and role == Role.ALONE:
                    last_seq = self.receiver.promote()
                elif self.sender is not None and role == Role.ALONE and self.sender.role == Role.PRIMARY:
                    self.sender.go_alone()
            except RoleError as e:
                rospy.logerr('%s: role change refused: %s', self.name, e)
                return SetRoleResponse(success=False, message=str(e))
            self.role = role
        rospy.logwarn('%s: now %s (last checkpoint %d)', self.name, role.name, last_seq)
        return SetRoleResponse(success=True, message='role %s' % role.name, last_seq=last_seq)
