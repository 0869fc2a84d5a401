"""The Traffic Jam Pilot's ROS nodes (second paper, section III.B), named as in the paper.

Each is thin: the logic is in :mod:`tjp_sim.control`. Their ports are rebindable (aft_ftm's
``~rebind``), so that a fault tolerance mechanism can be put between a sensor and the TJP at run
time, and each offers ``~suspend``/``~resume`` for the adaptation engine. Time is ROS time: the
simulator's clock (``/use_sim_time``).
"""
import json
import math
import threading
import time

import rosgraph
import rospy
from aft_msgs.msg import Alarm, CarCommand, Measure
from aft_msgs.srv import GetState, GetStateResponse, SetState, SetStateResponse
from std_msgs.msg import Bool, String

from aft_ftm import config
from aft_ftm.ports import PUBLISH, SUBSCRIBE, PortSpec
from aft_ftm.ros.cycle_nodes import Terminate
from aft_ftm.ros.params import param
from aft_ftm.primary_word import Word
from aft_ftm.ros.ports import Ports

from ..control import CommandArbiter, EmergencyBraking, Mode, Offer, PidController, SafetyDistance, speed_refused
from ..errors import TjpConfigError


def number(name, value):
    """A parameter that must be a finite number >= 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < float('inf'):
        raise config.ConfigError('parameter %s must be a number >= 0, got %r' % (name, value))
    return float(value)


def _range(msg):
    """A sensor_msgs/Range reading in metres as REP 117 defines it: None when nothing is in range
    (+inf), the sensor's min_range when something is too close to measure (-inf), NaN for an invalid
    reading (the callers refuse it). Both were taken for a free road (review, stop 39): a -inf
    released Emergency Braking, two NaN lasers outvoted a good one."""
    if math.isnan(msg.range):
        return float('nan')
    if math.isinf(msg.range):
        return None if msg.range > 0 else max(0.0, msg.min_range)
    return msg.range


class Episodes(object):
    """Alarms raised once per run of bad readings, not once per reading: ``bad()`` is True for the
    first of a run (then raise the alarm), ``good()`` ends the run; ``count`` counts them all."""

    def __init__(self):
        self.count = 0
        self.running = False

    def bad(self):
        self.count += 1
        first, self.running = not self.running, True
        return first

    def good(self):
        self.running = False


class PortedNode(object):
    """A node whose subscriptions and publications are aft_ftm ports (rebindable, suspendable)."""

    def __init__(self, specs, callbacks):
        self.name = rospy.get_name()
        self.lock = threading.Lock()
        self.ports = Ports(specs, callbacks)
        self.ports.suspension([s.name for s in specs if s.direction == SUBSCRIBE])

    def bind_all(self):
        for name, spec in self.ports.specs.items():
            if spec.direction == PUBLISH:
                self.ports.bind(name)
        for name, spec in self.ports.specs.items():
            if spec.direction == SUBSCRIBE:
                self.ports.bind(name)
        self.ports.advertise_service()

    def setup(self, timeout):
        self.bind_all()
        return True


class MeasureManagerNode(PortedNode):
    """measureManager: the car's speed from the IMU.

    A speed that is not a finite number is refused (nothing is published for it), with an alarm at
    the first of each run of them (``invalid_speed``): the TJP's safety distance is not renewed
    meanwhile, which no watch of the IMU itself would see.

    Subscribes: imu (geometry_msgs/TwistStamped, linear.x), port ``imu``
    Publishes: speed (aft_msgs/Measure), port ``speed``; alarms (aft_msgs/Alarm), port ``alarms``
    Services: ~rebind, ~suspend, ~resume
    """

    def __init__(self):
        super(MeasureManagerNode, self).__init__(
            [PortSpec('imu', SUBSCRIBE, 'geometry_msgs/TwistStamped'), PortSpec('speed', PUBLISH, 'aft_msgs/Measure'),
             PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
            {'imu': self._on_imu})
        self.refused = Episodes()

    def _on_imu(self, msg):
        speed = msg.twist.linear.x
        why = speed_refused(speed)
        if why:
            with self.lock:
                first = self.refused.bad()
            if first:
                self.ports.publish('alarms', Alarm(source=self.name, mechanism='plausibility', kind='invalid_speed',
                                                   detail='IMU speed %r refused (%s): the safety distance is not '
                                                   'renewed until a valid one (%d refused so far)'
                                                   % (speed, why, self.refused.count), stamp=msg.header.stamp))
            return
        with self.lock:
            self.refused.good()
        self.ports.publish('speed', Measure(stamp=msg.header.stamp, value=speed, source=self.name))


class DistanceSecurityCalculatorNode(PortedNode):
    """distanceSecurityCalculator: the gap to the car ahead and the safety distance for our speed.

    It also checks the gap's plausibility (the FMECA's error message for inconsistent laser data):
    a gap changing faster than ``~max_rate`` between two readings cannot be the car ahead; it is
    reported on ``alarms`` (it is still passed on: masking is the voter's job, when composed).

    Parameters: ~standstill (float, 2 m), ~time_gap (float, 1.5 s): d(v) = standstill + time_gap * v;
        ~max_rate (float, 30 m/s): the fastest plausible change of the gap
    Subscribes: laser (sensor_msgs/Range), port ``laser``; speed (aft_msgs/Measure), port ``speed``
    Publishes: gap (aft_msgs/Measure), port ``gap``; safety_distance (aft_msgs/Measure), port ``safety_distance``;
        alarms (aft_msgs/Alarm), port ``alarms``: implausible_gap, invalid_gap (a NaN reading: refused)
    Services: ~rebind, ~suspend, ~resume
    """

    def __init__(self):
        try:
            self.safety = SafetyDistance(param('standstill', config.positive_float, 2.0),
                                         param('time_gap', config.positive_float, 1.5))
        except TjpConfigError as e:
            raise config.ConfigError(str(e))
        self.max_rate = param('max_rate', config.positive_float, 30.0)
        super(DistanceSecurityCalculatorNode, self).__init__(
            [PortSpec('laser', SUBSCRIBE, 'sensor_msgs/Range'), PortSpec('speed', SUBSCRIBE, 'aft_msgs/Measure'),
             PortSpec('gap', PUBLISH, 'aft_msgs/Measure'), PortSpec('safety_distance', PUBLISH, 'aft_msgs/Measure'),
             PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
            {'laser': self._on_laser, 'speed': self._on_speed})
        self.last = None   # (time, gap) of the last reading
        self.invalid = Episodes()

    def _on_laser(self, msg):
        gap = _range(msg)
        if gap is not None and gap != gap:
            # An invalid reading (NaN): not a free road (it was taken for max_range, and the car
            # accelerated). Nothing is passed on: the controller keeps its last gap; the alarm
            # manager's watch of the gap sees a lasting silence.
            with self.lock:
                first = self.invalid.bad()
            if first:
                self.ports.publish('alarms', Alarm(source=self.name, mechanism='plausibility', kind='invalid_gap',
                                                   detail='laser reading NaN refused (%d so far)' % self.invalid.count,
                                                   stamp=msg.header.stamp))
            return
        # Nothing within the laser's range: the road ahead is free up to its range.
        gap = msg.max_range if gap is None else gap
        now = msg.header.stamp.to_sec()
        with self.lock:
            self.invalid.good()
            last, self.last = self.last, (now, gap)
        if last is not None and now > last[0] and abs(gap - last[1]) / (now - last[0]) > self.max_rate:
            self.ports.publish('alarms', Alarm(source=self.name, mechanism='plausibility', kind='implausible_gap',
                                               detail='gap %.2f m -> %.2f m in %.3f s' % (last[1], gap, now - last[0]),
                                               stamp=msg.header.stamp))
        self.ports.publish('gap', Measure(stamp=msg.header.stamp, value=gap, source=self.name))

    def _on_speed(self, msg):
        self.ports.publish('safety_distance', Measure(stamp=msg.stamp, value=self.safety(msg.value), source=self.name))


class ControllerPidNode(PortedNode):
    """controllerPid: the acceleration command that keeps the safety distance, each cycle.

    A publish/subscribe node replicated with PBR: at the end of each cycle it calls the Terminate
    statement (aft_ftm.ros.cycle_nodes.Terminate), which gives its After the state to checkpoint.

    Parameters: ~period (float, 0.1 s of ROS time); ~kp, ~ki, ~kd (0.8, 0.01, 0.6);
        ~max_accel, ~max_decel (1.5, 3.0 m/s^2): the comfort limits
    Subscribes: gap, safety_distance (aft_msgs/Measure), ports ``gap``, ``safety_distance``
    Publishes: command (aft_msgs/CarCommand), port ``command``; cycle_end (aft_msgs/CycleEnd)
    Services: ~get_state, ~set_state (aft_msgs/GetState, SetState), ~rebind, ~suspend, ~resume
    """

    def __init__(self):
        self.period = param('period', config.positive_float, 0.1)
        try:
            self.pid = PidController(kp=param('kp', number, 0.8), ki=param('ki', number, 0.01),
                                     kd=param('kd', number, 0.6), max_accel=param('max_accel', config.positive_float, 1.5),
                                     max_decel=param('max_decel', config.positive_float, 3.0))
        except TjpConfigError as e:
            raise config.ConfigError('%s: %s' % (rospy.get_name(), e))
        super(ControllerPidNode, self).__init__(
            [PortSpec('gap', SUBSCRIBE, 'aft_msgs/Measure'), PortSpec('safety_distance', SUBSCRIBE, 'aft_msgs/Measure'),
             PortSpec('command', PUBLISH, 'aft_msgs/CarCommand')],
            {'gap': self._on_gap, 'safety_distance': self._on_safety})
        self.gap = self.safety = None
        self.cycle = 0

    def setup(self, timeout):
        self.terminate = Terminate(self._state_bytes)
        rospy.Service('~get_state', GetState, lambda _req: GetStateResponse(state=self._state_bytes()))
        rospy.Service('~set_state', SetState, self._on_set_state)
        self.bind_all()
        self.timer = rospy.Timer(rospy.Duration(self.period), self._cycle)
        return True

    def _on_gap(self, msg):
        with self.lock:
            self.gap, self.gap_time = msg.value, msg.stamp.to_sec()

    def _on_safety(self, msg):
        with self.lock:
            self.safety = msg.value

    def _state_bytes(self):
        with self.lock:
            return json.dumps(self.pid.state()).encode()

    def _on_set_state(self, req):
        try:
            state = json.loads(bytes(req.state).decode())
            with self.lock:
                self.pid.set_state(state)
        except (ValueError, TjpConfigError) as e:
            rospy.logerr('%s: state refused: %s', self.name, e)
            return SetStateResponse(success=False, message=str(e))
        return SetStateResponse(success=True, message='')

    def _cycle(self, event):
        with self.lock:
            if self.gap is None or self.safety is None:
                return    # no measurement yet: nothing to command
            command = self.pid.update(self.gap, self.safety, self.gap_time)
            self.cycle += 1
            cycle = self.cycle
        self.ports.publish('command', CarCommand(stamp=rospy.Time.now(), accel=command, mode=CarCommand.TJP,
                                                 cycle=cycle, source=self.name))
        self.terminate()


class EmergencyBrakingNode(PortedNode):
    """Emergency Braking, independent of the TJP: brakes for a close obstacle (ultrasonic sensor).

    Parameters: ~confirm (int, 1): readings of the last confirm + 1 that confirm an obstacle (time
        redundancy when > 1); ~period (float, 0.04 s): the ultrasonic's period; ~emergency_distance (1 m);
        ~release_delay (1 s); ~emergency_decel (6 m/s^2)
    Subscribes: ultrasonic (sensor_msgs/Range), port ``ultrasonic``; imu (geometry_msgs/TwistStamped),
        port ``imu``: its own reading of the speed, not the TJP's
    Publishes: emergency (std_msgs/Bool), port ``emergency``: its decision at each reading;
        alarms (aft_msgs/Alarm), port ``alarms``: a false detection masked (false_detection_masked), no
        valid speed (speed_stale, braking for the last one plus what the car may have gained, or for
        the TJP's top speed before any), an invalid reading (invalid_range), ultrasonic readings stamped
        0 (unstamped: refused) or not after the last one taken (late_reading: refused), or more than
        0.5 s after this node's clock (future_reading: refused), the clock gone back (clock_reset);
        each once per run of them
    Services: ~rebind, ~suspend, ~resume
    """

    def __init__(self):
        try:
            self.braking = EmergencyBraking(
                emergency_distance=param('emergency_distance', config.positive_float, 1.0),
                release_delay=param('release_delay', number, 1.0),
                emergency_decel=param('emergency_decel', config.positive_float, 6.0),
                confirm=param('confirm', config.non_negative_int, 1),
                period=param('period', config.positive_float, 0.04),
                speed_window=param('speed_window', config.positive_float, 0.2),
                max_accel=param('max_accel', config.positive_float, 3.0))
        except TjpConfigError as e:
            raise config.ConfigError('%s: %s' % (rospy.get_name(), e))
        super(EmergencyBrakingNode, self).__init__(
            [PortSpec('ultrasonic', SUBSCRIBE, 'sensor_msgs/Range'), PortSpec('imu', SUBSCRIBE, 'geometry_msgs/TwistStamped'),
             PortSpec('emergency', PUBLISH, 'std_msgs/Bool'), PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
            {'ultrasonic': self._on_ultrasonic, 'imu': self._on_imu})
        self.bad_speed, self.stale, self.bad_range = Episodes(), Episodes(), Episodes()
        self.unstamped, self.late, self.ahead = Episodes(), Episodes(), Episodes()

    def _alarm(self, kind, detail, stamp):
        self.ports.publish('alarms', Alarm(source=self.name, mechanism='emergency_braking', kind=kind, detail=detail,
                                           stamp=stamp))

    def _on_imu(self, msg):
        with self.lock:
            ok = self.braking.observe_speed(msg.twist.linear.x, msg.header.stamp.to_sec())
            first = False if ok else self.bad_speed.bad()
            if ok:
                self.bad_speed.good()
        if first:
            self._alarm('invalid_speed', 'IMU speed %r refused: braking for the last valid speed plus what the car '
                        'may have gained since' % msg.twist.linear.x, msg.header.stamp)

    def _on_ultrasonic(self, msg):
        now = msg.header.stamp.to_sec()
        distance = _range(msg)
        if not msg.header.stamp:   # names no instant: neither confirms nor clears anything
            with self.lock:
                first, active = self.unstamped.bad(), self.braking.active
            if first:
                self._alarm('unstamped', 'ultrasonic reading stamped 0 (unset) refused: it names no instant',
                            rospy.Time.now())
            self.ports.publish('emergency', Bool(data=active))
            return
        with self.lock:
            self.unstamped.good()
            masked, late, resets, ahead = (self.braking.masked, self.braking.late, self.braking.resets,
                                           self.braking.ahead)
            clock = rospy.get_time()
            active = self.braking.update(distance, now, clock=clock)
            masked = self.braking.masked > masked
            was_ahead = self.braking.ahead > ahead
            first_ahead = self.ahead.bad() if was_ahead else self.ahead.good()
            was_late = was_ahead or self.braking.late > late
            first_late = self.late.bad() if self.braking.late > late else self.late.good()
            reset = self.braking.resets > resets
        if first_ahead:
            self._alarm('future_reading', 'ultrasonic reading stamped %.3f s, more than %.1f s after this node\'s clock '
                        '(%.3f s): refused (a glitched or forged stamp)' % (now, self.braking.ahead_max, clock),
                        msg.header.stamp)
        if first_late:
            self._alarm('late_reading', 'ultrasonic reading stamped %.3f s, not after the last one taken (%.3f s): '
                        'refused (a duplicate, reordered or replayed reading)' % (now, self.braking.last_reading),
                        msg.header.stamp)
        if reset:
            self._alarm('clock_reset', 'ultrasonic reading stamped %.3f s and the clock went back: readings taken '
                        'afresh, the brake %s' % (now, 'held' if active else 'released'), msg.header.stamp)
        with self.lock:
            stale = self.braking.speed_stale(now)
            first_stale = self.stale.bad() if stale else self.stale.good()
            invalid = not was_late and distance is not None and distance != distance
            first_invalid = self.bad_range.bad() if invalid else self.bad_range.good()
            speed = self.braking.speed_at(now)
        if masked:
            self._alarm('false_detection_masked', 'an obstacle seen in fewer than %d of %d readings'
                        % (self.braking.confirm, self.braking.confirm + 1), msg.header.stamp)
        if first_stale:
            self._alarm('speed_stale', 'no valid IMU speed for %.2f s: braking for %.1f m/s (the last plus what the car '
                        'may have gained since, or the top speed before any)' % (self.braking.speed_window, speed),
                        msg.header.stamp)
        if first_invalid:
            self._alarm('invalid_range', 'ultrasonic reading NaN: neither confirms nor clears an obstacle (%d so far)'
                        % self.braking.invalid, msg.header.stamp)
        self.ports.publish('emergency', Bool(data=active))


class CommandManagerNode(PortedNode):
    """commandManager: the command the actuator gets, each cycle.

    Emergency Braking has priority over controllerPid; a safe stop (an alarm) over both. Without
    a new command from controllerPid (its board failing over), the last one is held ``~hold``.
    A command of controllerPid stamped more than ``~hold`` (0.15 s at least) before this node's
    clock (computed long ago: a board frozen and resumed behind the fence), more than 0.5 s after it,
    or at or before the last one taken (reordered, duplicated, replayed) is refused: as if
    controllerPid were silent. So is one sent by a node other than the primary board's (its
    connection's caller id, which TLS binds to the board's certificate), as the watchdog names it on
    ``primary``, and until it does, one of ``~sources`` (tjp_sim.control.PrimarySources): a deposed
    board nobody could power off, resumed, publishes fresh commands.

    Parameters: ~period (float, 0.05 s), ~hold (float, 0.3 s), ~emergency_decel (6), ~stop_decel (3 m/s^2),
        ~sources (list of node names, []: any node): whose commands are taken until the watchdog names the
        primary's; ~name_wait (float, 0.25 s): how long a command of another node is held, in case the
        watchdog is naming it the primary (its word and the new primary's first command come on separate
        connections), before it is refused (wall clock); ~watchdog (node name, '': any): the only node whose
        word on the primary is heard
    Subscribes: pid_command (aft_msgs/CarCommand), port ``pid_command``; primary (aft_msgs/PrimaryBoard),
        port ``primary``: the watchdog's word on the primary board (latched); emergency (std_msgs/Bool),
        port ``emergency``; safe_stop (std_msgs/String: the reason), port ``safe_stop``;
        service_safe_state (aft_msgs/SafeState), port ``service_safe_state``: the service manager's safe
        state, obeyed as a safe stop
    Publishes: command (aft_msgs/CarCommand), port ``command``: its ``source`` is the node whose command of
        controllerPid was last taken in modes TJP and HOLD, this node otherwise; alarms (aft_msgs/Alarm),
        port ``alarms``: a command of controllerPid refused, stale_command, future_command, reordered_command
        or foreign_command, each once per run of them (a command taken ends it; foreign_command once per
        sender and primary named); the watchdog's word refused (primary_ignored: of a term passed, of a run
        left, naming no node, or not from ~watchdog; primary_disputed: another watchdog run naming another
        board, aft_ftm.primary_word), once per sender and reason while the word followed stands; its word
        not come within 2 s of a start while the watchdog runs (primary_unknown: ~sources taken; every
        command is held until then)
    Services: ~rebind, ~suspend, ~resume
    """

    def __init__(self):
        self.period = param('period', config.positive_float, 0.05)
        try:
            self.arbiter = CommandArbiter(hold=param('hold', config.positive_float, 0.3),
                                          emergency_decel=param('emergency_decel', config.positive_float, 6.0),
                                          stop_decel=param('stop_decel', config.positive_float, 3.0),
                                          sources=[rospy.resolve_name(n)
                                                   for n in param('sources', config.name_list, [])],
                                          name_wait=param('name_wait', config.non_negative_float, 0.25))
            self.watchdog = param('watchdog', config.optional_name, '')
            self.watchdog = rospy.resolve_name(self.watchdog) if self.watchdog else ''
        except TjpConfigError as e:
            raise config.ConfigError('%s: %s' % (rospy.get_name(), e))
        super(CommandManagerNode, self).__init__(
            [PortSpec('pid_command', SUBSCRIBE, 'aft_msgs/CarCommand'), PortSpec('emergency', SUBSCRIBE, 'std_msgs/Bool'),
             PortSpec('safe_stop', SUBSCRIBE, 'std_msgs/String'), PortSpec('command', PUBLISH, 'aft_msgs/CarCommand'),
             PortSpec('service_safe_state', SUBSCRIBE, 'aft_msgs/SafeState'),
             PortSpec('primary', SUBSCRIBE, 'aft_msgs/PrimaryBoard'),
             PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
            {'pid_command': self._on_pid, 'emergency': self._on_emergency, 'safe_stop': self._on_safe_stop,
             'service_safe_state': self._on_service_safe_state, 'primary': self._on_primary})
        self.pending = None
        self.pending_sender = None
        self.driver = self.name   # the sender of the last command of controllerPid taken
        self.cycle = 0
        # The cycles' sends one at a time, in the order they were computed: a safe stop's immediate send
        # and the timer's cycle ran at once, and the cycle computed first (a driving command) could go
        # out after the stop (review of session 49). Not self.lock: a slow publish never holds up the
        # inputs.
        self.send_lock = threading.Lock()
        self.refused = {offer: Episodes() for offer in Offer if offer not in (Offer.TAKEN, Offer.FOREIGN)}
        # A deposed board's commands come between the primary's: their alarm is once per sender and
        # primary named, not ended by each command taken (it was raised every 0.1 s).
        self.foreign_alarmed = set()
        self.word_alarmed = set()   # (sender, reason, run, board) of words refused and alarmed (see _on_primary)
        self.words_refused = 0
        self.announced = threading.Event()   # the watchdog's word on the primary was followed
        self.waiter = None   # the timer that ends the wait for the watchdog's word (setup)

    def setup(self, timeout):
        # The watchdog's word is heard before any command of controllerPid: a commandManager started again
        # after a take-over must not take the deposed board's first. Every command is held from the
        # start (review of session 51: bound before the wait began, the deposed board's came through in
        # between), until the word comes, or at once if no watchdog runs (no word will come).
        if self.arbiter.sources.nodes:
            with self.lock:
                self.arbiter.wait_for_word()
        for name, spec in self.ports.specs.items():
            if spec.direction == PUBLISH:
                self.ports.bind(name)
        self.ports.bind('primary')
        for name, spec in self.ports.specs.items():
            if spec.direction == SUBSCRIBE and name != 'primary':
                self.ports.bind(name)
        self.ports.advertise_service()
        if self.arbiter.sources.nodes:
            # Unknown (the master slow or away) is waited as if it ran: taken for "no watchdog", the
            # configured board (deposed, after a take-over) was taken at once, unsaid (review of session 52).
            if self._watchdog_runs() is not False:
                self.waiter = threading.Timer(self.PRIMARY_WAIT, self._end_wait)
                self.waiter.daemon = True
                self.waiter.start()
            else:
                self._end_wait(said=False)
        self.timer = rospy.Timer(rospy.Duration(self.period), lambda _e: self._send())
        return True

    PRIMARY_WAIT = 2.0   # s: the longest a commandManager started while the watchdog runs waits for its word

    def _watchdog_runs(self):
        """Whether a node publishes the watchdog's word (asked of the master, 1 s at most): True, False, or
        None if the master did not say."""
        topic, found = rospy.resolve_name('primary'), []

        def ask():
            try:
                found.append(topic in {t for t, _ in rosgraph.Master(self.name).getPublishedTopics('')})
            except Exception as e:   # no master: unknown
                rospy.logwarn('%s: cannot ask the master whether a watchdog runs: %s', self.name, e)
        asker = threading.Thread(target=ask, daemon=True)
        asker.start()
        asker.join(1.0)
        return found[0] if found else None

    def _end_wait(self, said=True):
        """The wait for the watchdog's word ran out (``said``: it is said), or no watchdog runs: ~sources
        are taken."""
        with self.lock:
            if not self.arbiter.sources.waiting:
                return
            offered = self.arbiter.end_wait(rospy.get_time(), time.monotonic())
            refusal = self._offered(*offered) if offered is not None else None
        if refusal is not None:
            self._refusal_alarm(*refusal)
        if not said:
            return
        detail = ('the watchdog publishes on %s but its word on the primary board did not come within %.1f s of this '
                  'start: controllerPid\'s commands are taken from %s (configured) until it comes'
                  % (rospy.resolve_name('primary'), self.PRIMARY_WAIT, ', '.join(sorted(self.arbiter.sources.nodes))))
        rospy.logwarn('%s: %s', self.name, detail)
        self.ports.publish('alarms', Alarm(source=self.name, mechanism='plausibility', kind='primary_unknown',
                                           detail=detail, stamp=rospy.Time.now()))

    WORD_ALARMED_MAX = 64   # (sender, reason) pairs alarmed per word followed (a forger's names are many)

    def _on_primary(self, msg):
        sender = (getattr(msg, '_connection_header', None) or {}).get('callerid', '')
        what = 'board %s (%s) named the primary in term %d of watchdog run %s by %s' % (
            msg.board, ', '.join(msg.nodes) or 'no node', msg.term, msg.incarnation, sender or 'an unnamed node')
        with self.lock:
            sources = self.arbiter.sources
            if self.watchdog and sender != self.watchdog:
                word, refusal, why = None, None, 'not the watchdog (%s)' % self.watchdog
            else:
                word, offered = self.arbiter.announce(msg.board, [rospy.resolve_name(n) for n in msg.nodes], msg.term,
                                                      msg.incarnation, rospy.get_time(), time.monotonic())
                why = sources.word.why
                if not word.refused:
                    self.announced.set()
                if word in (Word.TAKEN, Word.ADOPTED):
                    self.foreign_alarmed.clear()
                    self.word_alarmed.clear()
                refusal = self._offered(*offered) if offered is not None else None
            refused = word is None or word.refused
            # A refused word is alarmed once per sender and reason while the word in force stands: a forger
            # repeating it (or naming itself many ways) must not flood the alarms; the count goes on.
            # (The run and board are in the key: another restart of the watchdog disputing is news. Other
            # senders fill half the room at most: a forger's many names never mute the watchdog; review of
            # session 52.)
            key = (sender, why, msg.incarnation, msg.board)
            alarm = refused and key not in self.word_alarmed and \
                len(self.word_alarmed) < self.WORD_ALARMED_MAX * (2 if sender == self.watchdog else 1)
            if alarm:
                self.word_alarmed.add(key)
            self.words_refused += int(refused)
            detail = '%s: refused (%s), %d words refused so far; in force: %s, commands taken from %s only' % (
                what, why, self.words_refused, sources.word.describe(), ', '.join(sorted(sources.nodes)) or 'any node')
        if refusal is not None:
            self._refusal_alarm(*refusal)
        if word in (Word.TAKEN, Word.ADOPTED):
            rospy.loginfo('%s: board %s is the primary (term %d of watchdog run %s%s): controllerPid\'s commands taken '
                          'from %s only', self.name, msg.board, msg.term, msg.incarnation,
                          ', a run adopted' if word is Word.ADOPTED else '', ', '.join(msg.nodes))
        if not alarm:
            return
        rospy.logwarn('%s: %s', self.name, detail)
        self.ports.publish('alarms', Alarm(source=self.name, mechanism='plausibility',
                                           kind=Word.DISPUTED.value if word is Word.DISPUTED else Word.PASSED.value,
                                           detail=detail, stamp=rospy.Time.now()))

    def _on_pid(self, msg):
        sender = (getattr(msg, '_connection_header', None) or {}).get('callerid', '')
        with self.lock:
            stamp = msg.stamp.to_sec()
            said = self._offered(self.arbiter.offer(stamp, rospy.get_time(), sender, msg, time.monotonic()), stamp,
                                 sender, msg)
        if said is not None:
            self._refusal_alarm(*said)

    def _offered(self, offer, stamp, sender, msg):
        """What becomes of a command of controllerPid offered to the arbiter (under the lock): taken, held
        (its sender may be the primary the watchdog is naming), or refused. Returns the refusal to alarm
        (the first of its run), else None."""
        if offer is Offer.TAKEN:
            self.pending, self.pending_sender = msg.accel, sender
            for run in self.refused.values():
                run.good()
            return None
        if offer is Offer.UNNAMED:
            return None
        if not self.refused[offer].bad():
            return None
        count = {Offer.STALE: self.arbiter.stale, Offer.FUTURE: self.arbiter.ahead,
                 Offer.REORDERED: self.arbiter.reordered}[offer]
        return offer, stamp, sender, msg.accel, msg.source, count, rospy.get_time(), self.arbiter.last_stamp

    FOREIGN_ALARMED_MAX = 64   # senders alarmed as foreign per primary named (a forger's names are many)

    def _foreign(self, wall):
        """The commands refused as foreign since the last look (under the lock): the alarms to raise (the
        first of each sender since the primary was last named; all of them, not the last one only)."""
        said = []
        for stamp, sender in self.arbiter.expire(wall):
            if sender not in self.foreign_alarmed and len(self.foreign_alarmed) < self.FOREIGN_ALARMED_MAX:
                self.foreign_alarmed.add(sender)
                sources = self.arbiter.sources
                said.append((Offer.FOREIGN, stamp, sender, None, None, self.arbiter.foreign, rospy.get_time(),
                             (sources.board, sources.term, sorted(sources.nodes))))
        return said

    def _refusal_alarm(self, offer, stamp, sender, accel, source, count, now, last):
        what = ('controllerPid command %sfrom %s stamped %.3f s'
                % ('' if accel is None else '%.2f m/s^2 ' % accel, source or sender or '?', stamp))
        if offer is Offer.FOREIGN:
            board, term, nodes = last
            detail = ('%s, sent by %s, not by the primary board\'s %s (%s) nor named so within %.2f s: refused (a '
                      'deposed board still running, or a forger), %d so far'
                      % (what, sender or 'an unnamed node', ', '.join(nodes),
                         'board %s, term %d' % (board, term) if board else 'as configured', self.arbiter.name_wait,
                         count))
        elif offer is Offer.STALE:
            detail = ('%s, %.2f s before this node\'s clock (%.3f s): computed longer ago than a command is used '
                      'for (%.2f s; a board frozen and resumed?): refused, %d so far; as if controllerPid were '
                      'silent' % (what, now - stamp, now, self.arbiter.stale_after(), count))
        elif offer is Offer.FUTURE:
            detail = ('%s, more than %.1f s after this node\'s clock (%.3f s): refused (a glitched or forged '
                      'stamp), %d so far' % (what, self.arbiter.ahead_max, now, count))
        else:
            detail = ('%s, not after the last one taken (%.3f s): refused (a reordered, duplicated or replayed '
                      'command), %d so far' % (what, last, count))
        self.ports.publish('alarms', Alarm(source=self.name, mechanism='plausibility', kind=offer.value,
                                           detail=detail, stamp=rospy.Time.now()))

    def _on_emergency(self, msg):
        with self.lock:
            self.arbiter.emergency(msg.data)

    def _on_safe_stop(self, msg):
        with self.lock:
            first = self.arbiter.mode != Mode.SAFE_STOP
            self.arbiter.safe_stop(msg.data)
        if first:
            rospy.logerr('%s: controlled stop: %s', self.name, msg.data)
            self._send()    # at once: the clock may have stopped with the simulator

    def _on_service_safe_state(self, msg):
        if msg.active:
            self._on_safe_stop(String(data='service manager: %s' % msg.reason))

    def _send(self):
        with self.send_lock:
            with self.lock:
                foreign = self._foreign(time.monotonic())
                accel = self.arbiter.command(self.pending, rospy.get_time())
                if self.pending is not None:
                    self.driver = self.pending_sender or self.name
                self.pending = self.pending_sender = None
                self.cycle += 1
                mode = self.arbiter.mode
                msg = CarCommand(stamp=rospy.Time.now(), accel=accel, mode=int(mode), cycle=self.cycle,
                                 source=self.driver if mode in (Mode.TJP, Mode.HOLD) else self.name)
            self.ports.publish('command', msg)
        for refusal in foreign:
            self._refusal_alarm(*refusal)
