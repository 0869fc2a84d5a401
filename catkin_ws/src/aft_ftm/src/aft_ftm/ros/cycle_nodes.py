"""Before-Proceed-After for publish/subscribe nodes (the second paper's on-going work, section III.D).

A pub/sub node has no request whose reply marks the end of its work: the end of each processing
cycle is captured instead, by a Terminate statement the node calls at the end of every iteration of
its main loop (:class:`Terminate`, a library function as in the paper). It publishes the node's
state after the cycle on ``cycle_end``. The node's outputs are remapped to its After.

:class:`CycleAfterNode` is PBR's After for such a node, on each replica (the logic, without
rospy, is :class:`aft_ftm.cycle_replica.CycleReplica`):

- primary: passes every output on at once (a control loop cannot wait for a round trip), and at
  each cycle end checkpoints the whole state to the backup's After, which acknowledges it; every
  checkpoint is a state transfer (``full``);
- backup: its own node runs on the same inputs, but its outputs are not the system's (they are
  counted, not passed on); each checkpoint's state is set into its node (its ~set_state), so that
  the node continues from the primary's state when it takes over. A backup that holds no state
  (it started, came back after a power loss, or its primary stopped checkpointing to it) asks to
  join on ``join``, every ``~join_period``, and follows from the next checkpoint;
- ``~set_role`` ALONE (the watchdog, at failover): the backup passes its node's outputs on from
  then on; a primary goes on without checkpoints. A replica running alone becomes primary again
  when a backup asks to join it.

If the primary dies between a cycle's output and that cycle's checkpoint, the backup resumes from
the previous cycle's state: one cycle is computed again, which for a controller means one more
integration step of its error, not a lost or duplicated command.
"""
import os
import threading
import time

import rospy
import roslib.message
from aft_msgs.msg import Alarm, Checkpoint, CheckpointAck, CycleEnd, Join
from aft_msgs.srv import SetRole, SetRoleResponse, SetState
from std_msgs.msg import Bool

from .. import config, health
from ..checkpoint import Decision
from ..cycle_replica import CycleReplica
from ..errors import RoleError
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import Role
from .alarms import alarm
from .diagnostics import Diagnostics
from .fail_stop import fail_stop
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
            the primary goes on alone (alarm ``backup_lost``) until a backup joins.
        ~connect_timeout (float, 10 s): how long set-up waits for the peer's After.
        ~peer_after (str, default '' = any): a backup follows only an After whose name starts so.
        ~join_period (float, 0.25 s): a backup that holds no state asks to join this often.
        ~stale_after (float, 1 s), ~stale_cycles (int, 3): a backup whose own node ran this many cycles
            over this long without a checkpoint no longer mirrors its primary: it joins again
            (alarm ``backup_invalid``).
        ~site (str, default: the node's name): the replica's site, in join requests and fail-stops.
        ~site_detector (str, default '' = any of this launcher's): the site's crash detector, whose
            last heartbeat alone stops this After.
        ~cycle_timeout (float, 0 = off): a node that ended a cycle and then none for this long on
            its own clock (ROS time: simulated time stops with the simulator) hangs: a primary
            fail-stops its site (``fail_stop``, alarm ``node_hung``), so that the watchdog promotes
            the backup; a following backup no longer mirrors (``backup_invalid``); a replica alone
            raises ``node_hung``. Its site's crash detector must subscribe to ``fail_stop``.
        ~suspend_lease (float, 10 s), ~suspend_buffer_bytes (int, 64 MiB): the lease of a suspension
            and the bound of what it holds (every FTM node: see aft_ftm.ros.ports.Ports).
    Subscribes:
        raw (~msg_type), port ``raw``: the node's outputs
        cycle_end (aft_msgs/CycleEnd), port ``cycle_end``: the node's Terminate statements
        peer_checkpoints (aft_msgs/Checkpoint), port ``peer_checkpoints``: the primary's checkpoints
        peer_acks (aft_msgs/CheckpointAck), port ``peer_acks``: the backup's acknowledgments
        join_requests (aft_msgs/Join), port ``join_requests``: the peer backup asking to join
        site_heartbeat (aft_msgs/Heartbeat), port ``site_heartbeat``: this site's own heartbeats (its
            crash detector's, ~site_detector, from this node's own launcher): the last one, saying the
            site fail-stops (``stopping``, ``site`` equal to ~site), stops a backup After for good
            (aft_ftm.cycle_replica.CycleReplica.site_stopped)
        primary (aft_msgs/PrimaryBoard), port ``primary``: the watchdog's word on the primary board: a
            primary or lone After of another board (~site) was deposed while it could not hear, and
            nobody could fence it: it passes nothing on from then and its site fail-stops (alarm
            ``deposed``; CycleReplica.primary_named); only ~watchdog's word is heard where it is set
    Publishes:
        out (~msg_type), port ``out``: the replicated node's outputs, for the rest of the system
        checkpoints (aft_msgs/Checkpoint), port ``checkpoints``
        acks (aft_msgs/CheckpointAck), port ``acks``
        join (aft_msgs/Join), port ``join``: this backup asking to join, while it holds no state
        fail_stop (aft_msgs/Failure), port ``fail_stop``: to the site's crash detector (a hung node)
        alive (std_msgs/Bool), port ``alive``: a sign of life every tick of the watch (a tenth of
            ~cycle_timeout, at most 1 s, and 0.125 s at most with the defaults), sent once the tick has
            taken and left the After's lock; ``data``: whether a backup could take over now (a primary
            whose backup is admitted and acknowledged every checkpoint). The site's crash detector
            (``~alive_timeout``) fail-stops the site when they stop after one that said so, so that an
            After that hangs (stopped, or deadlocked on its lock) is failed over like a hung node
        alarms (aft_msgs/Alarm), port ``alarms``: mechanism ``pbr``, kinds ``backup_lost`` (a primary
            goes on alone), ``backup_invalid`` (a backup no longer mirrors its primary), ``node_hung``
            ``fail_stop``, ``deposed``, ``primary_disputed`` and ``primary_ignored`` (a word refused,
            aft_ftm.primary_word, or not from ~watchdog)
    Services called:
        set_state (aft_msgs/SetState): the node's state manager (backup)
    Services:
        ~set_role (aft_msgs/SetRole), ~rebind (aft_msgs/Rebind), ~suspend/~resume (aft_msgs/Suspend)
    """

    def __init__(self):
        self.name = rospy.get_name()
        role = ROLES[param('role', config.choice(*ROLES), 'primary')]
        msg_type = param('msg_type', config.service_type, required=True)
        if roslib.message.get_message_class(msg_type) is None:
            raise config.ConfigError('parameter %s: unknown message type %s'
                                     % (rospy.resolve_name('~msg_type'), msg_type))
        self.connect_timeout = param('connect_timeout', config.positive_float, 10.0)
        self.site = param('site', config.non_empty_str, self.name)
        self.first_seq = int(time.time() * 1e6)   # numbered from the clock, as PBR's After
        self.peer_after = param('peer_after', config.optional_name, '')
        self.site_detector = param('site_detector', config.optional_name, '')
        self.watchdog = param('watchdog', config.optional_name, '')
        self.watchdog = rospy.resolve_name(self.watchdog) if self.watchdog else ''
        self.replica = CycleReplica(
            self.name, role, self.first_seq, expect=self.peer_after,
            ack_timeout=param('ack_timeout', config.positive_float, 0.5),
            join_period=param('join_period', config.positive_float, 0.25),
            stale_after=param('stale_after', config.positive_float, 1.0),
            stale_cycles=param('stale_cycles', config.positive_int, 3),
            cycle_timeout=param('cycle_timeout', config.non_negative_float, 0.0))
        self.lock = threading.Lock()
        self.forwarded = 0
        self.withheld = 0        # a backup's own outputs, not passed on
        self.checkpoints = 0
        self.ports = Ports([PortSpec('raw', SUBSCRIBE, msg_type), PortSpec('out', PUBLISH, msg_type),
                            PortSpec('cycle_end', SUBSCRIBE, 'aft_msgs/CycleEnd'),
                            PortSpec('checkpoints', PUBLISH, 'aft_msgs/Checkpoint'),
                            PortSpec('acks', PUBLISH, 'aft_msgs/CheckpointAck'),
                            PortSpec('peer_checkpoints', SUBSCRIBE, 'aft_msgs/Checkpoint'),
                            PortSpec('peer_acks', SUBSCRIBE, 'aft_msgs/CheckpointAck'),
                            PortSpec('join', PUBLISH, 'aft_msgs/Join'),
                            PortSpec('join_requests', SUBSCRIBE, 'aft_msgs/Join'),
                            PortSpec('fail_stop', PUBLISH, 'aft_msgs/Failure'),
                            PortSpec('alive', PUBLISH, 'std_msgs/Bool'),
                            PortSpec('site_heartbeat', SUBSCRIBE, 'aft_msgs/Heartbeat'),
                            PortSpec('primary', SUBSCRIBE, 'aft_msgs/PrimaryBoard'),
                            PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
                           {'raw': self._on_output, 'cycle_end': self._on_cycle_end,
                            'peer_checkpoints': self._on_checkpoint, 'peer_acks': self._on_ack,
                            'join_requests': self._on_join, 'site_heartbeat': self._on_site_beat,
                            'primary': self._on_primary})
        self.ports.suspension(['raw', 'cycle_end'])
        self.set_state = rospy.ServiceProxy('set_state', SetState, persistent=True)
        self.diagnostics = None

    def setup(self, timeout):
        for name in ('out', 'checkpoints', 'acks', 'join', 'fail_stop', 'alive', 'alarms', 'peer_checkpoints',
                     'peer_acks', 'join_requests', 'site_heartbeat', 'primary', 'raw', 'cycle_end'):
            self.ports.bind(name)
        role = self.replica.role
        if role == Role.BACKUP:
            try:
                rospy.wait_for_service('set_state', timeout)
            except rospy.ROSException:
                rospy.logerr('%s: the node\'s state manager (%s) is not available', self.name,
                             rospy.resolve_name('set_state'))
                return False
        peers = {Role.PRIMARY: ['checkpoints', 'peer_acks', 'join_requests'],
                 Role.BACKUP: ['peer_checkpoints', 'acks', 'join'], Role.ALONE: []}[role]
        if self.replica.cycle_timeout:   # a hang is told to the crash detector: it must hear it
            peers = peers + ['fail_stop']
        missing = wait_for_connections(self.ports, peers, self.connect_timeout)
        if missing:
            rospy.logerr('%s: the peer After is not connected on %s within %.1f s', self.name,
                         [self.ports.topic(n) for n in missing], self.connect_timeout)
            return False
        rospy.Service('~set_role', SetRole, self._on_set_role)
        self.ports.advertise_service()
        self.diagnostics = Diagnostics(self._health)
        # On the wall clock, as the acknowledgments' deadlines: simulated time may run at any rate.
        threading.Thread(target=self._tick, name='pbr', daemon=True).start()
        return True

    def _report(self, notes):
        for note in notes:
            if note.alarm:
                rospy.logwarn('%s: pbr %s: %s', self.name, note.kind, note.detail)
                self.ports.publish('alarms', Alarm(source=self.name, mechanism='pbr', kind=note.kind,
                                                   detail=note.detail, stamp=rospy.Time.now()))
            else:
                rospy.loginfo('%s: %s', self.name, note.detail)

    # -- outputs and cycles ----------------------------------------------------------------------
    def _on_output(self, msg):
        with self.lock:
            passing = self.replica.passes_outputs()
            if passing:
                self.forwarded += 1
            else:
                self.withheld += 1
        if passing:
            self.ports.publish('out', msg)

    def _on_cycle_end(self, end):
        # Cycle ends arrive one at a time (one subscription, one thread): checkpoints leave in order.
        with self.lock:
            notes = self.replica.node_cycled(end.stamp.to_sec(), time.monotonic())
            out, more = self.replica.cycle_end(end.state, time.monotonic())
            notes += more
            if out is not None:
                self.checkpoints += 1
        self._report(notes)
        if out is not None:
            self.ports.publish('checkpoints', Checkpoint(seq=out.seq, first_seq=out.first_seq, sender=self.name,
                                                         state=out.state, full=True))

    def _on_ack(self, ack):
        with self.lock:
            notes = self.replica.on_ack(ack.seq, ack.ok, ack.error, ack.to)
        self._report(notes)

    def _on_join(self, join):
        if join.after == self.name:
            return
        if self.ports.connections('peer_acks') < 1:
            # Its acknowledgments could not reach us yet: it asks again in a join period.
            rospy.loginfo('%s: %s asks to join; waiting until its acknowledgments are connected', self.name, join.after)
            return
        with self.lock:
            notes = self.replica.on_join(join.after)
        self._report(notes)

    def _tick(self):
        period = min(self.replica.ack_timeout / 4.0, self.replica.join_period / 2.0,
                     self.replica.cycle_timeout / 10.0 or 1.0)   # (the hang watch: within a tenth of it)
        while not rospy.is_shutdown():
            time.sleep(period)
            held = self.ports.gate.state.name != 'OPEN'
            with self.lock:
                stop, notes = self.replica.check_node(rospy.get_time(), time.monotonic(), held)
                ask, more = self.replica.check(time.monotonic())
                notes += more
                last_seq = self.replica.receiver.last_seq if ask else 0
                replaceable = self.replica.replaceable(time.monotonic())
            self.ports.publish('alive', Bool(data=replaceable))   # the lock was taken and left: this After works
            self._report(notes)
            if stop:
                fail_stop(self.ports, self.site, '%s: %s' % (self.name, stop))
            if ask:
                self.ports.publish('join', Join(site=self.site, after=self.name, incarnation=str(self.first_seq),
                                                last_seq=last_seq, stamp=rospy.Time.now()))

    def _on_site_beat(self, beat):
        """This site's own heartbeats: its last one, saying the site fail-stops, stops this After if
        a backup (CycleReplica.site_stopped). Only one of its own launcher's (the beat's pid is this
        node's parent), from ~site_detector where set: another's would stop it for nothing."""
        if not beat.stopping or beat.site != self.site:
            return
        sender = getattr(beat, '_connection_header', {}).get('callerid', '')
        if beat.pid != os.getppid() or (self.site_detector and sender != self.site_detector):
            rospy.logwarn_throttle(10.0, '%s: a heartbeat of site %s saying it fail-stops from %s (launcher pid %d; '
                                   'ours is %d): not our own detector\'s, ignored' % (
                                       self.name, beat.site, sender or 'an unnamed node', beat.pid, os.getppid()))
            return
        with self.lock:
            notes = self.replica.site_stopped(beat.stopping)
        self._report(notes)

    def _on_primary(self, msg):
        """The watchdog's word on the primary board: a primary or lone After of another board was deposed
        while it could not hear, and nobody fenced it; it stops passing anything on and its site
        fail-stops (CycleReplica.primary_named)."""
        sender = (getattr(msg, '_connection_header', None) or {}).get('callerid', '')
        if self.watchdog and sender != self.watchdog:
            alarm(self.ports, 'pbr', 'primary_ignored', '%s: a word naming board %s the primary (term %d) from %s, '
                  'not the watchdog %s: ignored' % (self.name, msg.board, msg.term, sender or 'an unnamed node',
                                                    self.watchdog))
            return
        with self.lock:
            stop, notes = self.replica.primary_named(self.site, msg.board, msg.term, msg.incarnation, bool(msg.nodes))
        self._report(notes)
        if stop:
            fail_stop(self.ports, self.site, '%s: %s' % (self.name, stop))

    # -- backup ----------------------------------------------------------------------------------
    def _on_checkpoint(self, cp):
        # Checkpoints arrive one at a time (one subscription, one thread), in order. The node's
        # set_state is called outside the lock, so that a slow node never delays a promotion.
        with self.lock:
            decision, notes = self.replica.on_checkpoint(cp.seq, cp.sender, cp.first_seq, cp.full)
        self._report(notes)
        error = ''
        if decision in (Decision.APPLY, Decision.APPLY_FULL):
            try:
                answer = self.set_state(state=cp.state)
                ok, error = answer.success, answer.message
            except (rospy.ServiceException, rospy.ROSException) as e:
                ok, error = False, 'set_state failed: %s' % e
            with self.lock:
                refusal = self.replica.refusal(cp.seq) if ok else None
                if refusal:
                    ok, error = False, refusal   # (acknowledged as refused: it does not mirror)
                notes = self.replica.applied(cp.seq, cp.sender, ok, error, time.monotonic(), cp.first_seq)
            self._report(notes)
        elif decision == Decision.REACK:
            ok = True
        else:
            ok = False
            error = '%s: checkpoint %d of %s refused (%s)' % (self.name, cp.seq, cp.sender, decision.name)
            rospy.logerr(error)
        self.ports.publish('acks', CheckpointAck(seq=cp.seq, ok=ok, error=error, to=cp.sender))

    def _health(self):
        with self.lock:
            replica = self.replica
            sender = replica.sender
            held = len(sender.held) if sender is not None else 0
            report = health.replica_after(
                self.site, 'pbr', replica.role, 0, self.peer_after or 'any peer After', held=held,
                stopped='deposed: %s' % sender.deposed if sender is not None and sender.deposed else
                ('fail-stopped: %s' % replica.stopped if replica.stopped else None),
                cannot_take_over=None if replica.following or replica.role != Role.BACKUP
                else 'holds no state of its primary yet: it is joining',
                extra=[('forwarded', self.forwarded), ('withheld', self.withheld), ('checkpoints', self.checkpoints)])
        return health.with_suspension(report, self.ports.gate.state.name, self.ports.gate.held)

    def _on_set_role(self, req):
        role = Role(req.role)
        with self.lock:
            try:
                last_seq = self.replica.set_role(role, int(time.time() * 1e6))
            except RoleError as e:
                rospy.logerr('%s: role change refused: %s', self.name, e)
                return SetRoleResponse(success=False, message=str(e))
        rospy.logwarn('%s: now %s (last checkpoint %d)', self.name, self.replica.role.name, last_seq)
        return SetRoleResponse(success=True, message='role %s' % self.replica.role.name, last_seq=last_seq)
