"""The Traffic Jam Pilot's control logic (second paper, section III.B), without rospy.

- :class:`SafetyDistance`: the gap to keep grows with speed (a standstill gap plus a time gap).
- :class:`PidController`: controllerPid, an acceleration command that keeps the safety distance,
  within the comfort limits on acceleration and deceleration (a too severe braking may injure the
  passengers), with anti-windup.
- :class:`EmergencyBraking`: independent of the TJP, on the ultrasonic sensor; it brakes when an
  obstacle is inside the stopping distance and holds until the obstacle is gone for a delay.
- :class:`CommandArbiter`: commandManager, which passes controllerPid's command to the actuator
  unless Emergency Braking asks to stop (that has priority) or an alarm asked for a safe stop; a
  command stamped too long ago, ahead of the clock or out of order is refused (:class:`Offer`).

Units: metres, seconds, m/s, m/s^2. ``now`` is passed in; nothing here sleeps.
"""
import collections
import enum
import math

from aft_ftm.primary_word import PrimaryWord, Word

from .errors import TjpConfigError


def _positive(name, value):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise TjpConfigError('%s must be a number > 0, got %r' % (name, value))
    return float(value)


def _non_negative(name, value):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
        raise TjpConfigError('%s must be a number >= 0, got %r' % (name, value))
    return float(value)


MAX_CLOSING = 50.0   # m/s: no two cars below 35 km/h close in or draw apart faster
# The follower never reverses: an IMU speed below this is a faulty (a sign-inverted) IMU, not a car
# rolling back a little after a stop. Clamped to 0, one braked for 1 m instead of 10 at 10 m/s, and
# the safety distance was 2 m instead of 17, with nothing said (review of session 48).
MIN_SPEED = -0.5


def speed_refused(speed):
    """Why an IMU speed reading (m/s) cannot be used, or None: not a finite number, or below MIN_SPEED."""
    if isinstance(speed, bool) or not isinstance(speed, (int, float)) or not math.isfinite(speed):
        return 'not a number'
    if speed < MIN_SPEED:
        return 'below %.1f m/s: the car does not reverse (a sign-inverted IMU?)' % MIN_SPEED
    return None


class SafetyDistance(object):
    """d(v) = standstill + time_gap * v: the faster the follower, the larger the gap it keeps."""

    def __init__(self, standstill=2.0, time_gap=1.5):
        self.standstill = _positive('standstill', standstill)
        self.time_gap = _positive('time_gap', time_gap)

    def __call__(self, speed):
        return self.standstill + self.time_gap * max(0.0, speed)


class PidController(object):
    """controllerPid: an acceleration command from the gap error (gap - safety distance).

    The proportional and integral terms act on the gap error; the derivative term on the relative
    speed (the leader's speed minus ours), measured as the change of the gap between two cycles
    (the safety distance's own change with our speed would otherwise feed back the command). The
    command is clamped to [-max_decel, max_accel], the comfort limits; the integral stops growing
    while the command is clamped (anti-windup).
    """

    def __init__(self, kp=0.8, ki=0.01, kd=0.6, max_accel=1.5, max_decel=3.0, integral_limit=20.0):
        self.kp = _non_negative('kp', kp)
        self.ki = _non_negative('ki', ki)
        self.kd = _non_negative('kd', kd)
        self.max_accel = _positive('max_accel', max_accel)
        self.max_decel = _positive('max_decel', max_decel)
        self.integral_limit = _positive('integral_limit', integral_limit)
        self.integral = 0.0
        self.closing = 0.0
        self.last_gap = None
        self.last_time = None

    def reset(self):
        self.integral, self.closing, self.last_gap, self.last_time = 0.0, 0.0, None, None

    def update(self, gap, safety_distance, now):
        """The acceleration command (m/s^2) for the gap measured at time now (the measurement's
        time, not the cycle's: a derivative over the cycle's time would see the sensor's sampling
        as noise). A gap not measured again since the last call keeps the last closing speed."""
        error = gap - safety_distance
        dt = None if self.last_time is None else now - self.last_time
        if dt and dt > 0:
            # A jump of the gap (a wrong reading, the leader leaving the lasers' range) is not a
            # speed: the closing speed is bounded by what cars in a traffic jam can do.
            self.closing = min(MAX_CLOSING, max(-MAX_CLOSING, (gap - self.last_gap) / dt))
        raw = self.kp * error + self.ki * self.integral + self.kd * self.closing
        command = min(self.max_accel, max(-self.max_decel, raw))
        if dt and dt > 0 and command == raw:   # not saturated: integrate (anti-windup)
            self.integral = min(self.integral_limit, max(-self.integral_limit, self.integral + error * dt))
        if dt is None or dt > 0:
            self.last_gap, self.last_time = gap, now
        return command

    def state(self):
        """What a backup replica needs to take over smoothly (PBR's getState)."""
        return {'integral': self.integral, 'closing': self.closing, 'last_gap': self.last_gap,
                'last_time': self.last_time}

    def set_state(self, state):
        """Raise TjpConfigError on a malformed state: nothing changes then."""
        try:
            integral = float(state['integral'])
            closing = float(state.get('closing', 0.0))
            last_gap = None if state['last_gap'] is None else float(state['last_gap'])
            last_time = None if state['last_time'] is None else float(state['last_time'])
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise TjpConfigError('bad controller state %r: %s' % (state, e))
        if abs(integral) > self.integral_limit:
            raise TjpConfigError('bad controller state: integral %g outside +-%g' % (integral, self.integral_limit))
        if closing != closing or abs(closing) > MAX_CLOSING:
            raise TjpConfigError('bad controller state: closing speed %r is not a speed' % closing)
        # NaN passes every comparison above: an integral of NaN pinned the command at full braking for
        # good, a last_time of NaN or inf froze the integral and derivative terms (review, stop 39).
        for name, value in (('integral', integral), ('last_gap', last_gap), ('last_time', last_time)):
            if value is not None and not math.isfinite(value):
                raise TjpConfigError('bad controller state: %s %r is not a finite number' % (name, value))
        self.integral, self.closing, self.last_gap, self.last_time = integral, closing, last_gap, last_time


class Mode(enum.IntEnum):
    TJP = 0          # controllerPid drives
    EMERGENCY = 1    # Emergency Braking has priority: full braking
    SAFE_STOP = 2    # a non-recoverable failure (simulator, master, sensor): brake to a stop and stay
    HOLD = 3         # controllerPid is silent (its board failed over): its last command is held


class EmergencyBraking(object):
    """Emergency Braking, independent of the TJP, on the ultrasonic sensor.

    It brakes when an obstacle is closer than the stopping distance at full braking (plus a margin
    and the reaction time), and releases once nothing has been in range for ``release_delay``.
    With time redundancy (``confirm`` > 1) an obstacle must be seen in ``confirm`` of the last
    ``confirm + 1`` readings before it brakes: a single false detection (the FMECA's inconsistent
    ultrasonic data) is masked, at the price of (confirm - 1) readings of reaction time, which the
    braking distance includes (one reading more if one of them drops out). It was ``confirm`` in a
    row: an obstacle seen in 2 readings of every 3 (an echo lost now and then) was never braked for
    (review of session 48). A detection that leaves those readings unconfirmed counts in ``masked``.

    Its speed is its own reading of the IMU (:meth:`observe_speed`), not the TJP's filtered one: it
    stays independent of the TJP's nodes. A reading that drops out towards zero must not shrink the
    braking distance (the FMECA's IMU value faults: a quarter of the readings, and Emergency Braking
    ran into obstacles it would have braked for, review of stop 39), so the speed braked for is
    the second largest of the readings of the last ``speed_window`` seconds (one reading off in
    either direction changes nothing). A reading that is not a number is refused and counted. With
    no reading for ``speed_window``, it is the last speed plus what the car may have gained since at
    ``max_accel`` (``speed_stale`` says so; the node raises an alarm). With no reading at all for
    ``speed_window`` after its first ultrasonic reading (started again while the car moves, its IMU
    not connected), it brakes for ``max_speed``, the TJP's top speed, and ``speed_stale`` says so: it
    braked as for a standing car, 1 m instead of about 11 m at 10 m/s, and said nothing (review of
    session 36).

    Ultrasonic readings are taken in the order of their stamps: one stamped at or before the last
    one taken (a duplicate, a reordered or replayed one) tells nothing and is counted in ``late``: a
    replayed "nothing in range" released the brake before ``release_delay``, and one false detection
    repeated confirmed itself. If the caller's own clock went back too (``clock``, a /clock reset),
    it is a new start: ``resets`` counts it, and the readings are taken afresh (the brake held).

    A reading stamped more than ``ahead_max`` seconds after the caller's own clock (a glitched or
    forged stamp) is refused and counted in ``ahead``, and the order above ignores it: taken, one
    reading stamped 1000 s ahead made every later one "late", and Emergency Braking never braked
    again (review of session 48).
    """

    def __init__(self, emergency_distance=1.0, release_delay=1.0, emergency_decel=6.0, confirm=1, period=0.04,
                 speed_window=0.2, max_accel=3.0, max_speed=35 / 3.6, ahead_max=0.5):
        self.emergency_distance = _positive('emergency_distance', emergency_distance)
        self.release_delay = _non_negative('release_delay', release_delay)
        self.emergency_decel = _positive('emergency_decel', emergency_decel)
        if isinstance(confirm, bool) or not isinstance(confirm, int) or confirm < 1:
            raise TjpConfigError('confirm must be an integer >= 1, got %r' % (confirm,))
        self.confirm = confirm
        self.period = _positive('period', period)
        self.active = False
        self.recent = collections.deque(maxlen=confirm + 1 if confirm > 1 else 1)   # detected, per reading
        self.seen = 0            # readings of those with an obstacle inside the braking distance
        self.clear_since = None
        self.masked = 0          # detections not confirmed (masked by time redundancy)
        self.activations = 0
        self.reason = ''
        self.speed_window = _positive('speed_window', speed_window)
        self.max_accel = _positive('max_accel', max_accel)
        self.max_speed = _positive('max_speed', max_speed)
        self.speeds = collections.deque(maxlen=16)   # (time, speed) of the IMU's recent valid readings
        self.first_reading = None   # the stamp of the first ultrasonic reading taken (since a reset)
        self.last_reading = None    # the stamp of the last one taken
        self.last_clock = None      # the caller's clock when it was taken
        self.late = 0               # ultrasonic readings refused: stamped at or before the last one taken
        self.resets = 0             # the clock gone back
        self.speed_refused = 0   # IMU readings refused (speed_refused)
        self.invalid = 0         # ultrasonic readings that are not numbers (REP 117: NaN)
        self.ahead_max = _positive('ahead_max', ahead_max)
        self.ahead = 0           # ultrasonic readings refused: stamped more than ahead_max after the clock

    def braking_distance(self, speed):
        """How close an obstacle may come before braking must start at this speed: the stopping
        distance at full braking, a reaction time of one 0.1 s cycle plus the confirmation
        readings, and the margin."""
        reaction = 0.1 + (self.confirm - 1) * self.period
        return self.emergency_distance + reaction * speed + speed * speed / (2 * self.emergency_decel)

    def observe_speed(self, speed, now):
        """An IMU reading (m/s) at ``now``; False if refused (speed_refused: not a finite number, or the car
        reversing)."""
        if speed_refused(speed):
            self.speed_refused += 1
            return False
        self.speeds.append((now, max(0.0, float(speed))))
        return True

    def speed_at(self, now):
        """The speed braked for at ``now`` (m/s): the second largest reading of the last speed_window
        seconds; with none, the last one plus what the car may have gained since (0 before any)."""
        recent = sorted((v for t, v in self.speeds if now - self.speed_window <= t <= now), reverse=True)
        if recent:
            return recent[1] if len(recent) > 1 else recent[0]
        if not self.speeds:
            return self.max_speed if self._no_speed_yet(now) else 0.0
        when, last = self.speeds[-1]
        return last + self.max_accel * max(0.0, now - when)

    def speed_stale(self, now):
        """Whether no IMU reading came in the last speed_window seconds (after a first one, or after the
        first ultrasonic reading)."""
        if not self.speeds:
            return self._no_speed_yet(now)
        return now - self.speeds[-1][0] > self.speed_window

    def _no_speed_yet(self, now):
        return self.first_reading is not None and now - self.first_reading > self.speed_window

    def update(self, distance, now, speed=None, clock=None):
        """An ultrasonic reading (m; None: nothing in range; NaN: an invalid reading, REP 117) stamped
        ``now`` while driving at ``speed`` (m/s; None: :meth:`speed_at`); ``clock``: the caller's own
        time then, if it has one. Returns whether Emergency Braking is active. An invalid reading, or
        one out of order or stamped ahead of ``clock`` (see the class), tells nothing: it neither confirms
        an obstacle nor clears one."""
        if clock and now > clock + self.ahead_max:
            self.ahead += 1
            return self.active
        if self.last_reading is not None and now <= self.last_reading:
            # A reset only if the caller's own clock went back since the last reading taken (its clock
            # and the readings come on separate connections: compared with the reading's stamp, a
            # replayed reading in the moment the clock lagged passed for a reset; review of session 36).
            if not clock or self.last_clock is None or clock >= self.last_clock:
                self.late += 1
                return self.active
            self.resets += 1   # the clock went back: afresh, the brake as it was
            self.speeds.clear()
            self.first_reading = self.clear_since = None
            self.recent.clear()
            self.seen = 0
        self.last_reading = now
        if clock:
            self.last_clock = clock
        if self.first_reading is None:
            self.first_reading = now
        if distance is not None and not (isinstance(distance, (int, float)) and distance == distance):
            self.invalid += 1
            return self.active
        if speed is None:
            speed = self.speed_at(now)
        if distance is not None and distance < self.braking_distance(speed):
            self._note(True)
            self.clear_since = None
            if not self.active and self.seen >= self.confirm:
                self.active, self.reason = True, 'obstacle at %.2f m' % distance
                self.activations += 1
                self.recent.clear()
                self.seen = 0
            return self.active
        self._note(False)
        if distance is not None and self.active:
            self.clear_since = None   # stopped short of it: wait until the obstacle has gone
        elif self.active:
            if self.clear_since is None:
                self.clear_since = now
            if now - self.clear_since >= self.release_delay:
                self.active, self.reason = False, 'obstacle gone for %.1f s' % self.release_delay
                self.recent.clear()   # the detections before the release confirm nothing after it
                self.seen = 0
        return self.active


    def _note(self, detected):
        """One valid reading: whether it saw an obstacle inside the braking distance. A detection that
        leaves the last readings unconfirmed is masked (a false detection)."""
        if len(self.recent) == self.recent.maxlen and self.recent[0] and not self.active:
            self.masked += 1
        self.recent.append(detected)
        self.seen = sum(self.recent)


class Offer(enum.Enum):
    """What commandManager makes of a command of controllerPid (:meth:`CommandArbiter.offer`). A
    refusal's value is the kind of the alarm that says so."""
    TAKEN = 'taken'
    STALE = 'stale_command'           # computed longer ago than a command is used for
    FUTURE = 'future_command'         # stamped more than ahead_max after the caller's clock
    REORDERED = 'reordered_command'   # stamped at or before the last one taken
    FOREIGN = 'foreign_command'       # sent by a node that is not the primary board's (a deposed board)
    UNNAMED = 'unnamed'               # held: the watchdog may be naming its sender the primary this moment


class PrimarySources(object):
    """Whose commands of controllerPid commandManager takes: those of the nodes of the primary board,
    as the watchdog of the replicated controllerPid names them (:meth:`announce`, from
    aft_msgs/PrimaryBoard, followed by :class:`aft_ftm.primary_word.PrimaryWord`'s rule), and until it
    first does, the nodes given at the start. None given and none named: any node's (controllerPid not
    replicated). While ``waiting`` (a commandManager started again while the watchdog runs, until its
    word comes) nobody's.

    This is the take-over's fencing at the actuator's side. The watchdog powers a failed board off
    before it promotes the backup, but where it cannot (a board on a machine of its own with no power
    switch wired in), a board that only froze resumes taking itself for the primary and publishes fresh
    commands: both boards drove the car, one command in two, for the rest of the run (before session 51).
    """

    def __init__(self, nodes=()):
        self.nodes = frozenset(nodes)
        self.word = PrimaryWord()
        self.waiting = False

    @property
    def board(self):
        return self.word.board

    @property
    def term(self):
        return self.word.term

    @property
    def ignored(self):
        return self.word.refused

    def allows(self, node):
        return not self.waiting and (not self.nodes or node in self.nodes)

    def announce(self, board, nodes, term, incarnation):
        """The watchdog names ``board`` (its ``nodes``) the primary in ``term`` of its run
        ``incarnation``. Returns the :class:`aft_ftm.primary_word.Word`; the nodes named are taken with
        a word followed from now on (TAKEN, ADOPTED), and the wait ends with any word followed (TAKEN,
        ADOPTED, DUPLICATE)."""
        verdict = self.word.hear(board, term, incarnation, bool(nodes))
        if verdict in (Word.TAKEN, Word.ADOPTED):   # (adopted: the run followed from now on names them)
            self.nodes = frozenset(nodes)
        if not verdict.refused:
            self.waiting = False
        return verdict


# Allowed mode changes and what causes each.
MODE_EDGES = {
    (Mode.TJP, Mode.EMERGENCY): 'Emergency Braking is active',
    (Mode.HOLD, Mode.EMERGENCY): 'Emergency Braking is active',
    (Mode.EMERGENCY, Mode.TJP): 'Emergency Braking released',
    (Mode.TJP, Mode.HOLD): 'controllerPid is late',
    (Mode.HOLD, Mode.TJP): 'controllerPid speaks again',
    (Mode.TJP, Mode.SAFE_STOP): 'an alarm asked for a controlled stop',
    (Mode.HOLD, Mode.SAFE_STOP): 'an alarm asked for a controlled stop',
    (Mode.EMERGENCY, Mode.SAFE_STOP): 'an alarm asked for a controlled stop',
}


class CommandArbiter(object):
    """commandManager: which command reaches the actuator.

    Emergency Braking has priority over controllerPid; a safe stop (an alarm) over both, for good.
    controllerPid's latest command is used while it is at most ``late`` old (its period and a
    margin); past that controllerPid is late (HOLD): its last command is held until it is ``hold``
    old (the time a failover to the backup board takes), then the car brakes at ``stop_decel``
    until controllerPid speaks again.

    controllerPid stamps each command with when it computed it. :meth:`offer` checks the stamp
    before the caller passes the command on; a refused one is as if controllerPid had said nothing
    (its last good command held, then braking, as above). Refused, each counted:
    - stamped more than ``max(late, hold)`` before the caller's clock (``stale``): older than any
      command is used for when it comes on time. A board frozen (SIGSTOP) and resumed after the
      backup took over published the commands it computed before it froze, and they were applied;
    - stamped more than ``ahead_max`` after the caller's clock (``ahead``; a glitched or forged stamp,
      the bound of the sensors' readings), unless the caller has no clock yet (0);
    - stamped at or before the last one taken (``reordered``: a reordered, duplicated or replayed
      one), unless the caller's own clock went back since (a /clock reset: taken afresh, ``resets``).
    Before the stamp is looked at, a command sent by a node that ``sources`` (:class:`PrimarySources`)
    does not allow is held (``UNNAMED``): the watchdog names the new primary once it promoted it, on
    another connection than the new primary's commands, so its first command can come first. The last
    one of each sender is held (an earlier one it replaces is ``superseded``), of at most
    ``HELD_SENDERS`` senders (the oldest refused first). If :meth:`announce` names its sender within
    ``name_wait`` of the first one held (on the caller's ``wall`` clock: the race is in real time,
    whatever rate the simulation runs at), the last one is offered then; otherwise it is refused
    (``foreign``, :meth:`expire`), and the sender's next one starts a new hold: a deposed board's
    fresh commands neither drive nor move the order the primary's are checked against. While the
    sources wait for the watchdog's word (:meth:`wait_for_word`), every command is held and none
    expires; :meth:`end_wait` (the word did not come) takes the configured sources' and expires the
    rest.
    """

    def __init__(self, hold=0.3, emergency_decel=6.0, stop_decel=3.0, late=0.15, ahead_max=0.5, sources=(),
                 name_wait=0.1):
        self.hold = _non_negative('hold', hold)
        self.late = _positive('late', late)   # controllerPid silent this long is late (its period + margin)
        self.emergency_decel = _positive('emergency_decel', emergency_decel)
        self.stop_decel = _positive('stop_decel', stop_decel)
        self.last = None    # (command, when) of the last command controllerPid sent
        self.mode = Mode.TJP
        self.emergency_active = False
        self.reason = ''
        self.holds = 0      # cycles in which controllerPid's last command was held
        self.ahead_max = _positive('ahead_max', ahead_max)
        self.last_stamp = None   # the stamp of the last command taken by offer()
        self.last_clock = None   # the caller's clock then
        self.stale = 0           # commands refused: computed too long ago
        self.ahead = 0           # commands refused: stamped ahead of the clock
        self.reordered = 0       # commands refused: stamped at or before the last one taken
        self.resets = 0          # the clock gone back: commands taken afresh
        self.sources = PrimarySources(sources)
        self.foreign = 0         # commands refused: sent by a node other than the primary board's
        self.name_wait = _non_negative('name_wait', name_wait)
        # sender -> (stamp, sender, payload, first held, last held) of the command held by offer()
        self.unnamed = collections.OrderedDict()
        self.refused_foreign = []   # (stamp, sender) refused as foreign, until expire() hands them over
        self.superseded = 0      # commands held, replaced by a later one (of the same sender, or of the board named)
        self.named_late = 0      # commands held, their sender named after name_wait: dropped (not used, not foreign)

    def _change(self, mode, reason):
        if self.mode == mode:
            return
        if (self.mode, mode) not in MODE_EDGES:
            raise TjpConfigError('mode change %s -> %s is not allowed' % (self.mode.name, mode.name))
        self.mode, self.reason = mode, reason

    def emergency(self, active):
        """Emergency Braking's latest decision."""
        self.emergency_active = bool(active)

    def safe_stop(self, reason):
        """A failure the TJP cannot survive: brake to a stop and stay stopped."""
        self._change(Mode.SAFE_STOP, reason)

    def stale_after(self):
        """How old a command may be when it comes (s): the longest a command that came on time is used."""
        return max(self.late, self.hold)

    def offer(self, stamp, now, sender=None, payload=None, wall=None):
        """Whether a command of controllerPid stamped ``stamp``, sent by node ``sender``, may be passed
        on to :meth:`command` at ``now`` (the caller's clock, in the stamps' units; 0: none yet). See the
        class. ``payload`` (the command) is kept with a command held (UNNAMED), for :meth:`announce`;
        ``wall`` (default ``now``) times the hold."""
        if not self.sources.allows(sender):
            wall = now if wall is None else wall
            first = wall
            earlier = self.unnamed.pop(sender, None)
            if earlier is not None:   # superseded: the hold still counts from the sender's first one
                self.superseded += 1
                first = earlier[3]
            while len(self.unnamed) >= self.HELD_SENDERS:
                self._drop_unnamed(next(iter(self.unnamed)))
            self.unnamed[sender] = (stamp, sender, payload, first, wall)
            return Offer.UNNAMED
        if now and stamp > now + self.ahead_max:
            self.ahead += 1
            return Offer.FUTURE
        if now - stamp > self.stale_after():
            self.stale += 1
            return Offer.STALE
        if self.last_stamp is not None and stamp <= self.last_stamp:
            # A reset only if the caller's own clock went back since the last command taken (compared
            # with the stamp, a replayed command in a moment the clock lagged would pass for one).
            if self.last_clock is None or now >= self.last_clock:
                self.reordered += 1
                return Offer.REORDERED
            self.resets += 1
        self.last_stamp, self.last_clock = stamp, now
        return Offer.TAKEN

    HELD_SENDERS = 4
    REFUSED_KEPT = 64   # refusals kept for expire() to hand over (the count goes on)

    def _drop_unnamed(self, sender):
        dropped = self.unnamed.pop(sender, None)
        if dropped is not None:
            self.foreign += 1
            if len(self.refused_foreign) < self.REFUSED_KEPT:
                self.refused_foreign.append(dropped[:2])

    def _release(self, now, wall):
        """The freshest command held of a sender the sources allow now, if it came within name_wait (a
        hold not yet expired: see :meth:`expire`), offered again (its stamp checked then): None or
        (offer, stamp, sender, payload). The other held commands of allowed senders are dropped, not
        refused as foreign (their sender is named: alarmed so, the alarm contradicted itself; review of
        session 51): ``superseded`` if another was fresher, ``named_late`` if held too long for the word."""
        named = [held for held in self.unnamed.values() if self.sources.allows(held[1])]
        fresh = [held for held in named if wall - held[4] <= self.name_wait]
        best = max(fresh, key=lambda held: held[0]) if fresh else None
        for held in named:
            if held is not best:
                del self.unnamed[held[1]]
                if held in fresh:
                    self.superseded += 1
                else:
                    self.named_late += 1
        if best is None:
            return None
        stamp, sender, payload = self.unnamed.pop(best[1])[:3]
        return self.offer(stamp, now, sender), stamp, sender, payload

    def announce(self, board, nodes, term, incarnation, now, wall=None):
        """The watchdog's word (:meth:`PrimarySources.announce`). Returns (word, offered): the
        :class:`aft_ftm.primary_word.Word`, and None or (offer, stamp, sender, payload) of the command
        held if the primary named sent it within ``name_wait``, offered again now (:meth:`offer`'s
        answer: TAKEN, or why not)."""
        word = self.sources.announce(board, nodes, term, incarnation)
        if word.refused:
            return word, None
        return word, self._release(now, now if wall is None else wall)

    def wait_for_word(self):
        """Take nobody's commands (hold them) until the watchdog's word comes, or :meth:`end_wait`."""
        self.sources.waiting = True

    def end_wait(self, now, wall=None):
        """The watchdog's word did not come: the configured sources again. Returns as :meth:`_release`."""
        if not self.sources.waiting:
            return None
        self.sources.waiting = False
        return self._release(now, now if wall is None else wall)

    def expire(self, wall):
        """The commands refused as foreign since the last call, [(stamp, sender), ...] (the first
        ``REFUSED_KEPT``): held longer than ``name_wait`` (on the ``wall`` clock the hold was timed on)
        with their sender not named. Nothing expires while the sources wait for the word."""
        if not self.sources.waiting:
            for held in list(self.unnamed.values()):
                if wall - held[3] > self.name_wait or wall < held[3]:
                    self._drop_unnamed(held[1])
        refused, self.refused_foreign = self.refused_foreign, []
        return refused

    def command(self, tjp_command, now):
        """The acceleration sent to the actuator this cycle, given controllerPid's latest command
        (None: none came since the last cycle). The mode after the call says whose it is."""
        if tjp_command is not None:
            self.last = (tjp_command, now)
        if self.mode == Mode.SAFE_STOP:
            # Emergency Braking still has priority over the gentler controlled stop.
            return -self.emergency_decel if self.emergency_active else -self.stop_decel
        if self.emergency_active:
            self._change(Mode.EMERGENCY, 'Emergency Braking is active')
            return -self.emergency_decel
        if self.mode == Mode.EMERGENCY:
            self._change(Mode.TJP, 'Emergency Braking released')
        if self.last is None:
            return -self.stop_decel      # controllerPid never spoke: stand still
        silent = now - self.last[1]
        if silent <= self.late:
            self._change(Mode.TJP, 'controllerPid speaks')
            return self.last[0]
        self._change(Mode.HOLD, 'controllerPid silent for %.2f s' % silent)
        if silent <= self.hold:
            self.holds += 1
            return self.last[0]
        return -self.stop_decel
