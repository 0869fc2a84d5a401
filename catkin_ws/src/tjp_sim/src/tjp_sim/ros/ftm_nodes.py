"""The fault tolerance mechanisms of the car's FMECA (second paper, Fig. 6) as ROS nodes, each
put between a sensor and the TJP without changing the TJP (a remapping at launch, or a rebind at
run time by the adaptation engine):

- :class:`ImuTrNode`: time redundancy on the IMU speed, an average over a sliding window;
- :class:`LaserVoteNode`: triplicated lasers and majority voting;
- :class:`AlarmManagerNode`: alarm message and controlled stop when the simulator, the ROS master
  or a sensor without redundancy stops.
"""
import math
import socket
import threading
import time

import rosgraph
import rospy
from aft_msgs.msg import Alarm
from std_msgs.msg import String

from aft_ftm import config
from aft_ftm.ports import PUBLISH, SUBSCRIBE, PortSpec
from aft_ftm.ros.params import param

from ..errors import TjpConfigError
from ..filters import LaserVoter, SlidingAverage
from .tjp_nodes import PortedNode, _range


class ImuTrNode(PortedNode):
    """Time redundancy on the IMU: each speed passed on is the mean of a sliding window of readings;
    a reading far from the window's median is a transient value fault: masked and reported.

    Parameters: ~window (int, 5), ~tolerance (float, 1.0 m/s), ~persist (int, 10): readings in a row
        agreeing among themselves that far from the window make it follow (the speed really changed,
        e.g. a crash). A car cannot change its speed by 1 m/s in one 20 ms reading, so a burst of
        faulty readings shorter than 10 (200 ms) is masked, whatever they agree on.
    Subscribes: inp (geometry_msgs/TwistStamped), port ``inp``
    Publishes: out (geometry_msgs/TwistStamped), port ``out``; alarms (aft_msgs/Alarm), port ``alarms``:
        value_fault_masked (a NaN or inf reading too), speed_jump_followed (the window followed a lasting change)
    Services: ~rebind, ~suspend, ~resume
    """

    def __init__(self):
        try:
            self.filter = SlidingAverage(param('window', config.non_negative_int, 5),
                                         param('tolerance', config.positive_float, 1.0),
                                         param('persist', config.non_negative_int, 10))
        except TjpConfigError as e:
            raise config.ConfigError('%s: %s' % (rospy.get_name(), e))
        super(ImuTrNode, self).__init__(
            [PortSpec('inp', SUBSCRIBE, 'geometry_msgs/TwistStamped'), PortSpec('out', PUBLISH, 'geometry_msgs/TwistStamped'),
             PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
            {'inp': self._on_reading})

    def _on_reading(self, msg):
        raw = msg.twist.linear.x
        with self.lock:
            followed, given_up = self.filter.followed, self.filter.given_up
            value, masked = self.filter.add(raw)
            jump = self.filter.jump if self.filter.followed > followed else None
            gave_up = self.filter.given_up > given_up
        if gave_up:
            finite = math.isfinite(raw)
            self.ports.publish('alarms', Alarm(source=self.name, mechanism='tr', kind='imu_invalid',
                                               detail='IMU speed %s (last %r): no longer masked; %s' % (
                                                   self.filter.why, raw,
                                                   'nothing passed on until %d readings in a row agree (the safety '
                                                   'distance is not renewed meanwhile)' % self.filter.persist
                                                   if finite else 'passed on as it comes until a valid one'),
                                               stamp=msg.header.stamp))
        if jump is not None:
            # A lasting change the window followed: a collision, or a stuck or offset IMU it cannot
            # tell from one. Never silent (a stuck-at-zero IMU was followed after 10 readings, and the
            # safety distance collapsed with nothing said).
            self.ports.publish('alarms', Alarm(source=self.name, mechanism='tr', kind='speed_jump_followed',
                                               detail='IMU speed went from %.2f to %.2f m/s and stayed there: followed '
                                               '(a collision, or a stuck or offset IMU)' % jump,
                                               stamp=msg.header.stamp))
        if value is None:
            if not math.isfinite(raw):
                # Nothing to mask it with (none valid yet, or given up): passed on, for measureManager to
                # refuse it, alarmed, and not renew the safety distance, rather than a stale mean.
                self.ports.publish('out', msg)
            return
        if masked:
            self.ports.publish('alarms', Alarm(source=self.name, mechanism='tr', kind='value_fault_masked',
                                               detail='IMU speed %r m/s, window mean %.2f m/s' % (raw, value),
                                               stamp=msg.header.stamp))
        msg.twist.linear.x = value
        self.ports.publish('out', msg)


class LaserVoteNode(PortedNode):
    """Triplicated lasers, majority vote: one laser stuck, offset, noisy or silent is masked.

    Parameters: ~tolerance (float, 0.2 m): readings this close agree; ~silent_after (int, 5):
        instants missed in a row before a laser is reported silent
    Subscribes: laser_0, laser_1, laser_2 (sensor_msgs/Range), ports of the same names
    Publishes: out (sensor_msgs/Range): the voted gap, port ``out``, instants in the order decided;
        alarms (aft_msgs/Alarm), port ``alarms``:
        a laser disagreeing (laser_disagrees), a laser silent (laser_silent), no majority (no_majority,
        nothing is published for that instant: the TJP keeps its last gap), a laser whose readings are
        stamped 0 (unstamped, once: they are not voted), the clock gone back (clock_reset), a reading
        more than 1 s old while the clock goes on (stale_reading, at most once a second: refused), a
        reading stamped more than 0.5 s after this node's clock (future_reading, at most once a second:
        refused)
    Services: ~rebind, ~suspend, ~resume
    """

    def __init__(self):
        self.voter = LaserVoter(tolerance=param('tolerance', config.positive_float, 0.2),
                                silent_after=param('silent_after', config.non_negative_int, 5),
                                reset_after=int(1e9),   # ns: stamps a second back are a clock gone back, or old
                                ahead_max=int(0.5e9))   # ns: stamps half a second ahead of the clock are refused
        self.stale_told = -1e9   # when stale_reading was last raised (at most once a second)
        self.ahead_told = -1e9   # when future_reading was last raised (at most once a second)
        ports = [PortSpec('laser_%d' % i, SUBSCRIBE, 'sensor_msgs/Range') for i in range(3)]
        super(LaserVoteNode, self).__init__(
            ports + [PortSpec('out', PUBLISH, 'sensor_msgs/Range'), PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
            {'laser_%d' % i: (lambda msg, i=i: self._on_laser(i, msg)) for i in range(3)})

    def _on_laser(self, index, msg):
        # One hold of the lock from the vote to the last publication. Each laser has its own subscriber
        # thread: published after the lock was let go, one thread's decision could leave after a later
        # one another thread decided meanwhile, and distanceSecurityCalculator took the older gap last.
        with self.lock:
            self._vote(index, msg)

    def _vote(self, index, msg):
        """One reading: voted, and every instant it decides published, in order. Called under the lock."""
        late, resets, stale, ahead = self.voter.late, self.voter.resets, self.voter.stale, self.voter.ahead
        clock = rospy.get_rostime()
        decided = self.voter.add(index, msg.header.stamp.to_nsec(), _range(msg), clock=clock.to_nsec())
        late, reset = self.voter.late - late, self.voter.resets > resets
        first_stale = self.voter.stale > stale and time.monotonic() - self.stale_told > 1.0
        if first_stale:
            self.stale_told = time.monotonic()
        first_ahead = self.voter.ahead > ahead and time.monotonic() - self.ahead_told > 1.0
        if first_ahead:
            self.ahead_told = time.monotonic()
        if first_ahead:
            self._alarm('future_reading', 'laser %d stamped %.3f s, more than 0.5 s after this node\'s clock (%.3f s): '
                        'refused, a glitched or forged stamp (%d so far)' % (index, msg.header.stamp.to_sec(),
                                                                             clock.to_sec(), self.voter.ahead),
                        rospy.Time.now())
        if decided is LaserVoter.UNSTAMPED:
            self._alarm('unstamped', 'laser %d publishes readings stamped 0 (unset): they name no sensing instant and '
                        'are not voted; the other lasers vote without it' % index, rospy.Time.now())
            return
        if reset:
            self._alarm('clock_reset', 'laser %d stamped %.3f s, more than 1 s before the last instant voted: the '
                        'clock went back, voting starts afresh' % (index, msg.header.stamp.to_sec()), msg.header.stamp)
        if first_stale:
            self._alarm('stale_reading', 'laser %d stamped %.3f s, more than 1 s before the last instant voted while '
                        'the clock goes on: a replayed or delayed reading, refused (%d so far)'
                        % (index, msg.header.stamp.to_sec(), self.voter.stale), rospy.Time.now())
        if late:
            rospy.logwarn_throttle(1.0, '%s: a reading of laser %d came after its instant was voted (%d so far)'
                                   % (self.name, index, self.voter.late))
        for stamp, result, silent in decided:
            when = rospy.Time(nsecs=stamp)
            for i in silent:
                self._alarm('laser_silent', 'laser %d gave no reading for %d instants' % (i, self.voter.silent_after), when)
            if not result.ok:
                self._alarm('no_majority', 'no two lasers agree within %.2f m' % self.voter.tolerance, when)
                continue
            for i in result.faulty:
                self._alarm('laser_disagrees', 'laser %d disagrees with the majority (%.2f m)'
                            % (i, result.value if result.value is not None else float('inf')), when)
            out = msg.__class__()
            out.header.stamp = when
            out.header.frame_id = 'laser_voted'
            out.radiation_type, out.field_of_view = msg.radiation_type, msg.field_of_view
            out.min_range, out.max_range = msg.min_range, msg.max_range
            out.range = float('inf') if result.value is None else result.value
            self.ports.publish('out', out)

    def _alarm(self, kind, detail, stamp):
        self.ports.publish('alarms', Alarm(source=self.name, mechanism='vote', kind=kind, detail=detail, stamp=stamp))


class AlarmManagerNode(PortedNode):
    """Alarm message and controlled stop (the FMECA's answer to a crash without redundancy).

    Watches, on the wall clock: the simulator's /clock, and the ROS master; on ROS time (the
    simulator's): the inputs named in ~watch. When one stops, it raises an alarm and asks
    commandManager for a controlled stop, once.

    Parameters:
        ~watch (dict port -> timeout in s of ROS time, default {imu: 0.3, ultrasonic: 0.3, gap: 0.5}); also
            safety_distance (distanceSecurityCalculator's, renewed from measureManager's speed) and emergency
            (Emergency Braking's decisions): car.launch watches them when no service manager restarts those nodes
        ~clock_timeout (float, 0.5 s of wall clock), ~master_period (float, 0.25 s of wall clock),
        ~master_timeout (float, 2 s of wall clock: the master asked from a thread of its own, so that
            a hung master neither holds the other watches nor is waited for past it)
    Subscribes: clock (rosgraph_msgs/Clock), port ``clock``; imu (geometry_msgs/TwistStamped),
        ultrasonic (sensor_msgs/Range), gap, safety_distance (aft_msgs/Measure), emergency (std_msgs/Bool):
        ports of the same names (liveness only)
    Publishes: alarms (aft_msgs/Alarm), port ``alarms``; safe_stop (std_msgs/String), port ``safe_stop``
    Services: ~rebind, ~suspend, ~resume
    """

    TYPES = {'imu': 'geometry_msgs/TwistStamped', 'ultrasonic': 'sensor_msgs/Range', 'gap': 'aft_msgs/Measure',
             'safety_distance': 'aft_msgs/Measure', 'emergency': 'std_msgs/Bool'}

    def __init__(self):
        self.watch = param('watch', config.number_map, {'imu': 0.3, 'ultrasonic': 0.3, 'gap': 0.5})
        if any(k not in self.TYPES for k in self.watch):
            raise config.ConfigError('parameter %s must map some of %s to timeouts > 0, got %r'
                                     % (rospy.resolve_name('~watch'), ', '.join(self.TYPES), self.watch))
        self.clock_timeout = param('clock_timeout', config.positive_float, 0.5)
        self.master_period = param('master_period', config.positive_float, 0.25)
        self.master_timeout = param('master_timeout', config.positive_float, 2.0)
        self.master_down = None   # why the master's watch gave up on it (its thread sets it)
        specs = [PortSpec('clock', SUBSCRIBE, 'rosgraph_msgs/Clock'), PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm'),
                 PortSpec('safe_stop', PUBLISH, 'std_msgs/String')]
        specs += [PortSpec(k, SUBSCRIBE, self.TYPES[k]) for k in self.watch]
        callbacks = {'clock': self._on_clock}
        callbacks.update({k: (lambda _msg, k=k: self._heard(k)) for k in self.watch})
        super(AlarmManagerNode, self).__init__(specs, callbacks)
        self.last_clock_wall = None
        self.last_heard = {}
        self.stopped = None

    def setup(self, timeout):
        # Latched: a commandManager started again after the stop (the service manager restarts it), or
        # not yet connected when it was asked, gets it all the same: it started in TJP mode and the car
        # drove on (review of session 36).
        self.ports.bind('safe_stop', latch=True)
        self.bind_all()
        threading.Thread(target=self._loop, name='alarm_manager', daemon=True).start()
        threading.Thread(target=self._watch_master, name='alarm_manager_master', daemon=True).start()
        return True

    def _watch_master(self):
        """The ROS master asked every master_period, each call bounded by master_timeout. It ran in the
        loop of the other watches, without a bound of its own: a hung master held them all for rospy's
        60 s socket timeout, a simulator crash or a silent sensor unseen meanwhile (review of session 36)."""
        from aft_ftm.ros.fencing import node_api
        master = node_api(rosgraph.get_master_uri(), self.master_timeout)
        slow = 0   # calls in a row that timed out: one slow answer (a registration burst) is no crash
        while not rospy.is_shutdown() and self.stopped is None:
            try:
                master.getPid(self.name)
                slow = 0
            except (socket.timeout, TimeoutError) as e:
                slow += 1
                if slow >= 2:
                    self.master_down = 'the ROS master did not answer twice in a row within %.1f s: %s' % (
                        self.master_timeout, e or type(e).__name__)
                    return
                continue
            except Exception as e:   # any other failure to reach it: refused, reset
                self.master_down = 'the ROS master does not answer: %s' % (e or type(e).__name__)
                return
            time.sleep(self.master_period)

    def _on_clock(self, msg):
        with self.lock:
            self.last_clock_wall = time.monotonic()

    def _heard(self, port):
        with self.lock:
            self.last_heard[port] = rospy.get_time()

    def _loop(self):
        while not rospy.is_shutdown() and self.stopped is None:
            wall = time.monotonic()
            reason = None
            with self.lock:
                now = rospy.get_time()
                if self.last_clock_wall is not None and wall - self.last_clock_wall > self.clock_timeout:
                    reason = ('simulator_crash', 'no clock from the simulator for %.2f s' % (wall - self.last_clock_wall))
                elif now > 0:
                    for port, timeout in sorted(self.watch.items()):
                        since = self.last_heard.setdefault(port, now)   # watched from the first tick on
                        if since > now:   # the clock went back (a /clock reset): watched afresh from now; the
                            since = self.last_heard[port] = now   # silence went unseen until it caught up
                        if now - since > timeout:
                            reason = ('%s_silent' % port, 'nothing on %s for %.2f s' % (self.ports.topic(port), now - since))
                            break
            if reason is None and self.master_down is not None:
                reason = ('master_crash', self.master_down)
            if reason is not None:
                self._stop(*reason)
                return
            time.sleep(0.02)

    def _stop(self, kind, detail):
        self.stopped = kind
        rospy.logerr('%s: %s: %s; controlled stop', self.name, kind, detail)
        self.ports.publish('alarms', Alarm(source=self.name, mechanism='alarm_and_stop', kind=kind, detail=detail,
                                           stamp=rospy.Time.now()))
        self.ports.publish('safe_stop', String(data='%s: %s' % (kind, detail)))
