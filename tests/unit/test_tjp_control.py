"""The TJP's control logic without a master: safety distance, controllerPid, commandManager."""
import random
import pytest

from aft_ftm.primary_word import Word
from tjp_sim.control import CommandArbiter, EmergencyBraking, Mode, Offer, PidController, PrimarySources, SafetyDistance
from tjp_sim.errors import TjpConfigError


@pytest.mark.parametrize('speed,expected', [(0.0, 2.0), (5.0, 9.5), (9.7, 16.55), (-1.0, 2.0)])
def test_the_safety_distance_grows_with_speed(speed, expected):
    assert SafetyDistance(standstill=2.0, time_gap=1.5)(speed) == pytest.approx(expected)


def simulate(leader_speed, seconds, dt=0.05, gap=20.0, speed=5.0, pid=None):
    """A follower driven by the controller behind a leader at leader_speed(t).
    Returns (smallest gap / safety distance, largest |acceleration|, final gap, final speed)."""
    pid = pid or PidController()
    safety = SafetyDistance()
    worst, peak, t = float('inf'), 0.0, 0.0
    while t < seconds:
        accel = pid.update(gap, safety(speed), t)
        peak = max(peak, abs(accel))
        speed = max(0.0, speed + accel * dt)
        gap += (leader_speed(t) - speed) * dt
        worst = min(worst, gap / safety(speed))
        t += dt
    return worst, peak, gap, speed


def test_the_controller_settles_at_the_safety_distance_behind_a_steady_leader():
    _, peak, gap, speed = simulate(lambda t: 8.0, 120.0)
    assert speed == pytest.approx(8.0, abs=0.05)
    assert gap == pytest.approx(SafetyDistance()(8.0), abs=0.3)
    assert peak <= 3.0


def test_behind_a_braking_leader_the_gap_never_collapses_and_comfort_limits_hold():
    def leader(t):   # stop-and-go: 9 m/s, braking at 2 m/s^2 to a stop, then going again
        if t < 10:
            return 9.0
        if t < 14.5:
            return max(0.0, 9.0 - 2.0 * (t - 10))
        if t < 25:
            return 0.0
        return min(9.0, 1.0 * (t - 25))
    worst, peak, _, _ = simulate(leader, 60.0, gap=SafetyDistance()(9.0), speed=9.0)
    assert worst > 0.9      # never closer than 90 % of the safety distance (and so never a collision)
    assert peak <= 3.0 + 1e-9


def test_the_command_is_clamped_to_the_comfort_limits_and_the_integral_does_not_wind_up():
    pid = PidController(max_accel=1.5, max_decel=3.0)
    assert pid.update(200.0, 10.0, 0.0) == 1.5
    for i in range(1, 200):
        assert pid.update(200.0, 10.0, i * 0.05) == 1.5
    assert pid.integral == 0.0        # saturated all along: nothing integrated
    assert pid.update(0.5, 10.0, 10.0) == -3.0


def test_the_controller_state_moves_to_a_backup_and_a_corrupt_one_is_refused():
    primary, backup = PidController(), PidController()
    for i in range(20):
        primary.update(15.0 - i * 0.1, 10.0, i * 0.05)
    backup.set_state(primary.state())
    assert backup.update(12.0, 10.0, 1.0) == primary.update(12.0, 10.0, 1.0)
    for bad in ({'integral': 'x', 'last_gap': None, 'last_time': None},
                {'integral': 1e9, 'last_gap': 0, 'last_time': 0}, {}):
        before = backup.state()
        with pytest.raises(TjpConfigError, match='bad controller state'):
            backup.set_state(bad)
        assert backup.state() == before


def test_emergency_braking_has_priority_and_releases_only_after_the_delay():
    braking = EmergencyBraking(emergency_distance=1.5, release_delay=1.0, emergency_decel=6.0)
    arbiter = CommandArbiter(emergency_decel=6.0)
    assert braking.braking_distance(6.0) == pytest.approx(1.5 + 0.6 + 3.0)
    assert arbiter.command(1.0, 0.0) == 1.0
    arbiter.emergency(braking.update(1.2, 0.1))
    assert arbiter.command(1.0, 0.1) == -6.0 and arbiter.mode == Mode.EMERGENCY
    arbiter.emergency(braking.update(None, 0.2))
    assert arbiter.command(1.0, 0.5) == -6.0      # clear for 0.3 s only
    arbiter.emergency(braking.update(None, 1.3))
    assert arbiter.command(0.5, 1.3) == 0.5 and arbiter.mode == Mode.TJP
    assert braking.activations == 1


def test_an_obstacle_still_there_keeps_the_car_braked_however_long():
    braking = EmergencyBraking(release_delay=0.5)
    assert braking.update(0.8, 0.0)
    assert all(braking.update(0.8, t) for t in (1.0, 5.0, 30.0))


def test_time_redundancy_masks_a_single_false_detection_but_confirms_a_real_obstacle():
    braking = EmergencyBraking(confirm=3, period=0.04)
    # A false detection: one reading, then nothing again; masked once it leaves the last 4 readings.
    assert not braking.update(0.9, 0.00, speed=5.0)
    assert [braking.update(None, t, speed=5.0) for t in (0.04, 0.08, 0.12, 0.16)] == [False] * 4
    assert braking.masked == 1 and braking.activations == 0
    # A real obstacle stays: braking starts at the third reading.
    assert [braking.update(0.9, t, speed=5.0) for t in (0.20, 0.24, 0.28)] == [False, False, True]
    # The confirmation readings are paid for in the braking distance.
    assert braking.braking_distance(5.0) == pytest.approx(EmergencyBraking(confirm=1).braking_distance(5.0)
                                                          + 2 * 0.04 * 5.0)


def test_a_failover_of_the_controller_holds_the_last_command_briefly_then_brakes():
    arbiter = CommandArbiter(hold=0.3, stop_decel=3.0)
    assert arbiter.command(0.8, 0.0) == 0.8
    assert arbiter.command(None, 0.2) == 0.8 and arbiter.mode == Mode.HOLD   # the backup has not spoken yet
    assert arbiter.command(None, 0.5) == -3.0     # nothing for too long: stop
    assert arbiter.command(0.4, 0.6) == 0.4 and arbiter.mode == Mode.TJP
    assert arbiter.holds == 1


def test_a_safe_stop_stays_whatever_comes_but_emergency_braking_still_brakes_harder():
    arbiter = CommandArbiter(emergency_decel=6.0, stop_decel=3.0)
    arbiter.safe_stop('the simulator stopped publishing')
    arbiter.emergency(True)
    assert arbiter.command(1.0, 9.0) == -6.0 and arbiter.mode == Mode.SAFE_STOP
    arbiter.emergency(False)
    assert arbiter.command(1.0, 10.0) == -3.0 and arbiter.mode == Mode.SAFE_STOP


def test_any_state_the_controller_reaches_can_be_set_into_a_backup():
    # A laser jumping from 10 m to 40 m (or the leader leaving the lasers' range) must not give
    # a state the backup refuses: that would invalidate the backup for good.
    primary, backup = PidController(), PidController()
    for now, gap in ((0.0, 10.0), (0.04, 10.0), (0.08, 40.0), (0.12, 100.0), (0.16, 2.0)):
        primary.update(gap, 12.0, now)
        backup.set_state(primary.state())
        assert backup.state() == primary.state()


@pytest.mark.parametrize('kwargs,message', [
    ({'standstill': 0}, 'standstill must be a number > 0'),
    ({'time_gap': -1}, 'time_gap must be a number > 0'),
])
def test_bad_parameters_are_named(kwargs, message):
    with pytest.raises(TjpConfigError, match=message):
        SafetyDistance(**kwargs)


@pytest.mark.parametrize('kwargs,message', [
    ({'confirm': 0}, 'confirm must be an integer >= 1'),
    ({'release_delay': -1}, 'release_delay must be a number >= 0'),
])
def test_bad_emergency_braking_parameters_are_named(kwargs, message):
    with pytest.raises(TjpConfigError, match=message):
        EmergencyBraking(**kwargs)


# -- review of stop 39: Emergency Braking's own speed, and readings that are not numbers -------------
def test_imu_dropouts_towards_zero_do_not_shrink_the_braking_distance():
    """The FMECA's IMU value faults (a quarter of the readings drop towards zero): with the raw
    reading, a dropout made the braking distance that of a standing car and broke the confirmation
    chain; the car ran into obstacles it brakes for without the faults."""
    import random
    rng = random.Random(39)
    braking = EmergencyBraking(confirm=3, period=0.04)
    t, active = 0.0, False
    for step in range(200):                        # 4 s at 6 m/s, IMU every 20 ms, ultrasonic every 40 ms
        t = step * 0.02
        braking.observe_speed(0.0 if rng.random() < 0.25 else 6.0, t)
        if step >= 10:                             # a full window: never the speed of a dropout
            assert braking.speed_at(t) == 6.0, (step, t)
        if step % 2 == 0 and step >= 100:           # an obstacle 5 m ahead from 2 s on
            active = braking.update(5.0, t)
            if active:
                break
    assert active and braking.activations == 1 and t <= 2.0 + 3 * 0.04


def test_one_upward_imu_spike_does_not_make_it_brake_for_the_car_ahead():
    braking = EmergencyBraking(confirm=3, period=0.04)
    for step in range(50):                         # standing 2 m behind the leader, one spike of 10 m/s
        t = step * 0.02
        braking.observe_speed(10.0 if step == 20 else 0.0, t)
        if step % 2 == 0:
            assert not braking.update(2.0, t), step


def test_without_imu_readings_it_brakes_for_the_speed_the_car_may_have_reached():
    braking = EmergencyBraking(max_accel=3.0, speed_window=0.2)
    assert braking.speed_at(0.0) == 0.0 and not braking.speed_stale(0.0)
    braking.observe_speed(5.0, 1.0)
    assert braking.speed_at(1.1) == 5.0 and not braking.speed_stale(1.1)
    assert braking.speed_stale(2.0) and braking.speed_at(2.0) == pytest.approx(8.0)
    for bad in (float('nan'), float('inf'), None, True):
        assert not braking.observe_speed(bad, 2.0)
    assert braking.speed_refused == 4 and braking.speed_stale(2.0)


def test_an_invalid_ultrasonic_reading_neither_confirms_nor_clears_an_obstacle():
    braking = EmergencyBraking(confirm=1, release_delay=0.5)
    nan = float('nan')
    assert not braking.update(nan, 0.0, speed=3.0)
    assert braking.update(0.8, 0.1, speed=3.0)
    assert all(braking.update(nan, t, speed=0.0) for t in (0.2, 1.0, 2.0))   # NaN compared false: "gone"
    assert braking.invalid == 4 and braking.activations == 1


def test_a_controller_state_with_a_number_that_is_not_finite_is_refused():
    pid = PidController()
    pid.update(15.0, 10.0, 0.0)
    before = pid.state()
    nan, inf = float('nan'), float('inf')
    for bad in ({'integral': nan, 'last_gap': 1.0, 'last_time': 1.0},
                {'integral': 0.0, 'last_gap': nan, 'last_time': 1.0},
                {'integral': 0.0, 'last_gap': 1.0, 'last_time': inf}):
        with pytest.raises(TjpConfigError, match='not a finite number'):
            pid.set_state(bad)
        assert pid.state() == before


def test_with_no_imu_reading_since_it_started_it_brakes_for_the_top_speed_and_says_so():
    """Emergency Braking started again while the car moves (the service manager restarts it), its IMU
    not connected: it braked as for a standing car, 1 m, and said nothing (review of session 36)."""
    braking = EmergencyBraking(confirm=1, speed_window=0.2)
    assert not braking.update(None, 10.0)                 # first reading: no speed yet, not stale yet
    assert braking.speed_at(10.1) == 0.0 and not braking.speed_stale(10.1)
    assert braking.speed_stale(10.3) and braking.speed_at(10.3) == pytest.approx(35 / 3.6)
    # An obstacle 5 m ahead: inside the stopping distance at 35 km/h, far outside a standing car's 1 m.
    assert braking.update(5.0, 10.3) and braking.activations == 1
    braking.observe_speed(2.0, 10.35)                    # the IMU speaks: its reading counts again
    assert braking.speed_at(10.4) == 2.0 and not braking.speed_stale(10.4)


def test_a_late_duplicated_or_replayed_ultrasonic_reading_tells_nothing():
    import random
    seed = random.randrange(1 << 16)
    rng = random.Random(seed)
    braking = EmergencyBraking(confirm=3, period=0.04, release_delay=1.0)
    # One false detection, replayed twice: time redundancy must still mask it.
    assert not braking.update(0.9, 1.00, speed=5.0)
    assert not braking.update(0.9, 1.00, speed=5.0) and not braking.update(0.9, 0.96, speed=5.0)
    assert not braking.update(None, 1.04, speed=5.0)
    assert braking.activations == 0 and braking.late == 2, seed
    # A real obstacle, braked for; then "nothing in range" readings from the past (replayed or
    # reordered, drawn) must not count as clear time: the brake holds until 1 s of fresh clear readings.
    for t in (1.08, 1.12, 1.16):
        braking.update(0.9, t, speed=5.0)
    assert braking.active, seed
    t = 1.20
    braking.update(None, t, speed=0.0)                   # clear from 1.20 on
    for _ in range(20):
        old = rng.uniform(0.0, t)
        assert braking.update(None, old, speed=0.0, clock=t + 0.01), (seed, old)   # the clock goes on: late
    assert braking.update(None, 2.0, speed=0.0), seed      # 0.8 s clear: still braking
    assert not braking.update(None, 2.21, speed=0.0), seed  # 1 s clear: released
    assert braking.late == 22, seed


def test_a_clock_gone_back_starts_the_readings_afresh_with_the_brake_held():
    braking = EmergencyBraking(confirm=1, release_delay=0.5)
    braking.observe_speed(3.0, 50.0)
    assert braking.update(0.8, 50.0, clock=49.9)         # (its clock a little behind the readings' stamps)
    assert braking.update(None, 10.0, clock=49.95) and braking.resets == 0 and braking.late == 1   # lagging: late
    assert braking.update(None, 0.5, clock=0.5)          # the simulation started again: its clock went back
    assert braking.resets == 1 and braking.late == 1 and braking.active
    assert braking.update(None, 0.9) and not braking.update(None, 1.05)   # then 0.5 s clear, as ever


def test_an_obstacle_seen_in_two_readings_of_three_is_braked_for():
    """Review of session 48: confirm readings had to be in a row; an obstacle whose echo was lost one
    reading in three was never braked for (0 activations in 3 s at 3 m and 5 m/s, 25 detections
    masked). Now confirm of the last confirm + 1 readings: braked for at its fourth reading."""
    braking = EmergencyBraking(confirm=3, period=0.04)
    seen = [0.9 if i % 3 != 2 else None for i in range(12)]
    active = [braking.update(d, i * 0.04, speed=5.0) for i, d in enumerate(seen)]
    assert active.index(True) == 3 and braking.activations == 1 and braking.masked == 0
    # A detection one reading in two never confirms itself, and is said each time (masked).
    sparse = EmergencyBraking(confirm=3, period=0.04)
    assert not any(sparse.update(0.9 if i % 2 == 0 else None, i * 0.04, speed=5.0) for i in range(20))
    assert sparse.activations == 0 and sparse.masked >= 8



def test_one_reading_stamped_ahead_of_the_clock_is_refused_and_does_not_blind_emergency_braking():
    """Review of session 48: a reading stamped 1000 s ahead was taken, and every later one was "late":
    a pedestrian at 0.5 m for 5 s was never braked for. Refused now (``ahead``); the next ones count."""
    braking = EmergencyBraking(confirm=3, period=0.04)
    t = 10.0
    for _ in range(10):
        braking.observe_speed(8.0, t)
        assert braking.update(None, t, clock=t) is False
        t += 0.04
    braking.update(None, t + 1000.0, clock=t)
    assert braking.ahead == 1 and braking.last_reading < t
    t += 0.04
    active = []
    for _ in range(5):
        braking.observe_speed(8.0, t)
        active.append(braking.update(0.5, t, clock=t))
        t += 0.04
    assert active == [False, False, True, True, True] and braking.late == 0
    # Within ahead_max of the clock (a stamp a little ahead of a lagging /clock): taken.
    assert EmergencyBraking().update(None, 10.3, clock=10.0) is False
    near = EmergencyBraking()
    near.update(None, 10.3, clock=10.0)
    assert near.ahead == 0 and near.last_reading == 10.3


def test_an_imu_speed_below_the_reverse_limit_is_refused_not_taken_for_a_standing_car():
    """Review of session 48: a sign-inverted IMU (-10 m/s at 10) was clamped to 0: braking for 1 m
    instead of about 10, and a safety distance of 2 m instead of 17, with no alarm."""
    from tjp_sim.control import MIN_SPEED, speed_refused
    braking = EmergencyBraking()
    assert braking.observe_speed(10.0, 0.0)
    assert not braking.observe_speed(-10.0, 0.01) and braking.speed_refused == 1
    assert braking.speed_at(0.01) == 10.0
    assert braking.observe_speed(-0.2, 0.02)                     # rolling back a little after a stop
    assert speed_refused(-10.0).startswith('below') and speed_refused(float('nan')) == 'not a number'
    assert speed_refused(MIN_SPEED) is None and speed_refused(True) == 'not a number'


def test_detections_before_a_release_confirm_nothing_after_it():
    """Review of session 48 (of its own change): with release_delay 0 the detections taken while braking
    stayed in the last readings; one false detection after the release made 3 of 4 and braked again."""
    braking = EmergencyBraking(confirm=3, period=0.04, release_delay=0.0)
    assert [braking.update(0.9, t, speed=5.0) for t in (0.0, 0.04, 0.08)] == [False, False, True]
    assert braking.update(None, 0.12, speed=5.0) is False          # released at once
    assert braking.update(0.9, 0.16, speed=5.0) is False            # one false detection: not confirmed


# -- controllerPid's command checked by its stamp (commandManager; the nodes' side: test_tjp_nodes.py) --
@pytest.mark.parametrize('hold,stamp,now,offer', [
    (0.3, 10.0, 10.0, Offer.TAKEN),
    (0.3, 9.75, 10.0, Offer.TAKEN),       # 0.25 s old: a command that came on time is held that long
    (0.3, 9.6, 10.0, Offer.STALE),        # 0.4 s old: not used even had it come on time
    (0.1, 9.88, 10.0, Offer.TAKEN),       # a hold shorter than late: a command is used for late (0.15 s)
    (0.1, 9.8, 10.0, Offer.STALE),
    (0.3, 10.45, 10.0, Offer.TAKEN),      # a clock lagging the controller's by less than ahead_max
    (0.3, 10.6, 10.0, Offer.FUTURE),      # a glitched or forged stamp
    (0.3, 5.0, 0.0, Offer.TAKEN),         # no clock yet (0): no bound ahead
], ids=['now', 'within hold', 'older than hold', 'within late', 'older than late', 'a little ahead',
        'too far ahead', 'no clock yet'])
def test_a_command_of_controllerpid_is_checked_by_its_stamp(hold, stamp, now, offer):
    arbiter = CommandArbiter(hold=hold, late=0.15, ahead_max=0.5)
    assert arbiter.offer(stamp, now) is offer
    assert (arbiter.stale, arbiter.ahead) == (offer is Offer.STALE, offer is Offer.FUTURE)
    assert arbiter.last_stamp == (stamp if offer is Offer.TAKEN else None)


def test_a_command_not_after_the_last_one_taken_is_refused_unless_the_clock_went_back():
    arbiter = CommandArbiter()
    assert arbiter.offer(10.0, 10.0) is Offer.TAKEN
    assert arbiter.offer(10.0, 10.05) is Offer.REORDERED       # a duplicate
    assert arbiter.offer(9.9, 10.05) is Offer.REORDERED        # reordered, or replayed
    assert arbiter.offer(10.1, 10.1) is Offer.TAKEN
    assert arbiter.offer(9.0, 10.15) is Offer.STALE            # older than any command is used for
    assert (arbiter.reordered, arbiter.stale, arbiter.resets) == (2, 1, 0)
    # The simulation started again (/clock went back): its commands are taken afresh, not refused for good.
    assert arbiter.offer(0.2, 0.2) is Offer.TAKEN and arbiter.resets == 1
    assert arbiter.offer(0.3, 0.3) is Offer.TAKEN and arbiter.offer(0.25, 0.3) is Offer.REORDERED


A, B = '/board_a/cycle_after', '/board_b/cycle_after'
TAKEN, ADOPTED, DUPLICATE, PASSED, DISPUTED = Word.TAKEN, Word.ADOPTED, Word.DUPLICATE, Word.PASSED, Word.DISPUTED


def test_commands_are_taken_from_the_configured_board_until_the_watchdog_names_another():
    arbiter = CommandArbiter(sources=[A])
    assert arbiter.offer(10.0, 10.0, A) is Offer.TAKEN
    assert arbiter.offer(10.1, 10.1, B) is Offer.UNNAMED          # the backup, or anyone else: held
    assert arbiter.expire(10.15) == []                             # within name_wait (0.1 s)
    assert arbiter.expire(10.25) == [(10.1, B)] and arbiter.foreign == 1
    assert arbiter.offer(10.3, 10.3, '') is Offer.UNNAMED         # a sender that gave no name
    assert arbiter.announce('board_b', [B], 2, 'w1', 10.3) == (TAKEN, None)   # (the held one is not B's)
    assert arbiter.expire(10.35) == [] and arbiter.expire(10.45) == [(10.3, '')] and arbiter.foreign == 2
    assert arbiter.offer(10.4, 10.4, A) is Offer.UNNAMED          # the deposed board, resumed
    assert arbiter.offer(10.4, 10.4, B) is Offer.TAKEN
    assert arbiter.offer(10.45, 10.45, A) is Offer.UNNAMED        # replaces its own: superseded
    assert arbiter.expire(10.48) == [] and arbiter.superseded == 1
    # The hold counts from the first: a board sending faster than name_wait is refused all the same.
    assert arbiter.expire(10.55) == [(10.45, A)] and arbiter.foreign == 3


def test_the_new_primarys_command_that_comes_before_the_watchdogs_word_is_taken_with_it():
    """The watchdog names board_b once it promoted it, on another connection than board_b's commands:
    board_b's first command can come first (seen in the car scenario board_freeze)."""
    arbiter = CommandArbiter(sources=[A])
    assert arbiter.offer(10.0, 10.0, A) is Offer.TAKEN
    assert arbiter.offer(10.1, 10.1, B, payload='b1') is Offer.UNNAMED
    assert arbiter.offer(10.15, 10.15, B, payload='b2') is Offer.UNNAMED   # the word is slow: b1 superseded
    word, offered = arbiter.announce('board_b', [B], 2, 'w1', 10.18)
    assert word is TAKEN and offered == (Offer.TAKEN, 10.15, B, 'b2')
    assert arbiter.expire(10.5) == [] and arbiter.foreign == 0 and arbiter.last_stamp == 10.15
    # Named too late (past name_wait), it is not used, and not refused as foreign either: its sender is
    # the primary named (alarmed as foreign, the alarm named it the primary; review of session 51).
    arbiter = CommandArbiter(sources=[A])
    assert arbiter.offer(10.1, 10.1, B, payload='b1') is Offer.UNNAMED
    assert arbiter.announce('board_b', [B], 2, 'w1', 10.25) == (TAKEN, None)
    assert arbiter.expire(10.25) == [] and arbiter.last_stamp is None
    assert (arbiter.named_late, arbiter.foreign, arbiter.unnamed) == (1, 0, {})
    assert arbiter.offer(10.3, 10.3, B) is Offer.TAKEN
    # Taken late, its stamp is checked as any command's: too old by then, it is refused as stale.
    arbiter = CommandArbiter(sources=[A], name_wait=1.0)
    assert arbiter.offer(10.0, 10.0, B, payload='b1') is Offer.UNNAMED
    assert arbiter.announce('board_b', [B], 2, 'w1', 10.5) == (TAKEN, (Offer.STALE, 10.0, B, 'b1'))


def test_the_hold_is_timed_on_the_wall_clock_not_on_the_simulations():
    """At 20 times real time, 0.1 s of road time is 5 ms: the race the hold covers is in real time. A
    wall clock before the hold (a held command's time gone wrong) does not keep it for ever."""
    arbiter = CommandArbiter(sources=[A])
    assert arbiter.offer(10.0, 10.0, B, payload='b1', wall=500.0) is Offer.UNNAMED
    word, offered = arbiter.announce('board_b', [B], 2, 'w1', 11.5, wall=500.05)   # 1.5 s of road time later
    assert offered == (Offer.STALE, 10.0, B, 'b1')   # offered (its stamp then too old: refused as stale)
    arbiter = CommandArbiter(sources=[A])
    assert arbiter.offer(10.0, 10.0, B, wall=500.0) is Offer.UNNAMED
    assert arbiter.expire(499.0) == [(10.0, B)]


def test_a_deposed_boards_fresh_commands_do_not_move_the_order_the_primarys_are_checked_against():
    """Set aside before its stamp is looked at: a deposed board's command stamped a moment later than the
    primary's would otherwise make the primary's next one 'reordered'."""
    arbiter = CommandArbiter(sources=[B])
    assert arbiter.offer(10.0, 10.0, B) is Offer.TAKEN
    assert arbiter.offer(10.09, 10.09, A) is Offer.UNNAMED
    assert arbiter.offer(10.05, 10.1, B) is Offer.TAKEN
    assert (arbiter.last_stamp, arbiter.reordered) == (10.05, 0)


def test_without_sources_every_sender_is_taken_until_a_watchdog_names_one():
    arbiter = CommandArbiter()
    assert arbiter.offer(10.0, 10.0, A) is Offer.TAKEN and arbiter.offer(10.1, 10.1, B) is Offer.TAKEN
    assert arbiter.announce('board_a', [A], 1, 'w1', 10.1) == (TAKEN, None)
    assert arbiter.offer(10.2, 10.2, B) is Offer.UNNAMED


def test_started_again_it_takes_nobodys_commands_until_the_word_comes_or_the_wait_ends():
    """A commandManager started again after board_b took over: its configuration names board_a, the
    deposed board may still publish. Nothing is taken, nothing expires, until the latched word."""
    arbiter = CommandArbiter(sources=[A])
    arbiter.wait_for_word()
    assert arbiter.offer(10.0, 10.0, A) is Offer.UNNAMED and arbiter.offer(10.0, 10.0, B, payload='b') is Offer.UNNAMED
    assert arbiter.expire(10.5) == []
    assert arbiter.offer(10.55, 10.55, B, payload='b2') is Offer.UNNAMED
    word, offered = arbiter.announce('board_b', [B], 2, 'w1', 10.6)
    assert word is TAKEN and offered == (Offer.TAKEN, 10.55, B, 'b2')
    assert arbiter.expire(10.6) == [(10.0, A)]     # the deposed board's, now it is known not to be named
    # The word never came: the configured board is taken again, its last command if it came within name_wait.
    arbiter = CommandArbiter(sources=[A])
    arbiter.wait_for_word()
    assert arbiter.offer(12.0, 12.0, A, payload='a') is Offer.UNNAMED
    assert arbiter.end_wait(12.05) == (Offer.TAKEN, 12.0, A, 'a')
    assert arbiter.end_wait(12.1) is None and arbiter.offer(12.1, 12.1, A) is Offer.TAKEN


@pytest.mark.parametrize('seed', range(30))
def test_no_command_of_a_board_not_named_the_primary_is_ever_taken(seed):
    """Two boards send every 0.1 s, the watchdog's take-overs come at random, its word delayed at random
    (before or after the new primary's first command, up to 0.15 s), words repeated and reordered at
    random. Whatever the order: a command taken was sent by the board of the highest term heard when
    it was taken; each command is taken, refused, superseded or still held, once; the command the
    named board sent within name_wait before its word came is offered when the word comes, and taken
    unless its stamp is not after the last one taken; a fresh command of the board in force, stamped
    after the last one taken, is taken at once (liveness: nothing refuses the primary)."""
    rng = random.Random(seed)
    arbiter = CommandArbiter(sources=[A], name_wait=0.1)
    primary, term, events = A, 1, []
    t = 10.0
    for step in range(200):
        t = round(t + 0.01, 2)
        if rng.random() < 0.02:   # a take-over; the word comes with a delay drawn at random
            primary, term = (B if primary == A else A), term + 1
            events.append((round(t + rng.uniform(-0.05, 0.15), 2), 'announce', primary, term))
        if step % 10 == 0:
            for board in rng.sample((A, B), 2):
                events.append((round(t + rng.uniform(0, 0.005), 3), 'command', board, (t, board)))
        if rng.random() < 0.05 and term > 1:   # an old word again
            old = rng.randint(1, term)
            events.append((t, 'announce', A if old % 2 else B, old))
    events.sort(key=lambda e: e[0])
    taken, sent, last, best = [], [], {}, 1   # term 1: board_a, as configured
    for now, kind, board, arg in events:
        if kind == 'announce':
            before, holding = arbiter.sources.nodes, board in arbiter.unnamed
            word, offered = arbiter.announce(board, [board], arg, 'w1', now)
            if word is TAKEN:
                best = arg
                # The board named, if it was not allowed already, gets its last command offered if it came
                # within name_wait (the one its After published before the word came) and its hold did not
                # expire (name_wait after the first one held).
                waited, held = last.get(board, (None, False))
                if board not in before and held and holding and now - waited[0] < 0.1 - 1e-6:
                    assert offered is not None and offered[3] == waited, 'seed %d' % seed
                    assert offered[0] is Offer.TAKEN or (offered[0] is Offer.REORDERED and
                                                          waited[0] <= arbiter.last_stamp), 'seed %d' % seed
            else:
                assert word in (DUPLICATE, PASSED) and offered is None, 'seed %d' % seed
            if offered is not None and offered[0] is Offer.TAKEN:
                taken.append((offered[3], board, best))
        else:
            sent.append(arg)
            # Liveness: a fresh command of the board in force, after the last one taken, is taken at once.
            due = board in arbiter.sources.nodes and (arbiter.last_stamp is None or arg[0] > arbiter.last_stamp) \
                and now - arg[0] <= arbiter.stale_after()
            offer = arbiter.offer(arg[0], now, board, payload=arg)
            assert offer is Offer.TAKEN or not due, 'seed %d: %s of the board in force: %s' % (seed, arg, offer)
            last[board] = (arg, offer is Offer.UNNAMED)
            if offer is Offer.TAKEN:
                taken.append((arg, board, best))
        arbiter.expire(now)
    why = 'seed %d' % seed
    for command, board, at_term in taken:
        assert command[1] == board and (A if at_term % 2 else B) == board, why
    held = len(arbiter.unnamed)
    assert len({c for c, _, _ in taken}) == len(taken), why
    assert len(taken) + arbiter.foreign + arbiter.superseded + arbiter.named_late + held + arbiter.stale + \
        arbiter.ahead + arbiter.reordered == len(sent), why


@pytest.mark.parametrize('seed', range(20))
def test_a_word_of_a_passed_term_changes_nothing_whatever_order_they_come_in(seed):
    """Words duplicated, reordered and replayed at random: the primary is always the one of the highest
    term heard of the watchdog's run; the word in force heard again is a silent duplicate, an older
    term refused aloud."""
    rng = random.Random(seed)
    terms = [(t, 'board_a' if t % 2 else 'board_b') for t in range(1, 8)]
    heard = [rng.choice(terms[:i + 1]) for i in range(len(terms)) for _ in range(rng.randint(1, 3))]
    sources = PrimarySources([A])
    best = 0
    for term, board in heard:
        nodes = ['/%s/cycle_after' % board]
        word = sources.announce(board, nodes, term, 'w1')
        assert word is (TAKEN if term > best else DUPLICATE if term == best else PASSED), 'seed %d' % seed
        best = max(best, term)
        expected = dict(terms)[best]
        assert (sources.board, sources.term, sources.nodes) == (expected, best, {'/%s/cycle_after' % expected})


def test_another_watchdog_run_is_followed_only_if_it_names_the_board_in_force():
    """A watchdog started again starts from its configured primary (board_a) whatever board drives: its
    word must not take the car from board_b. Naming board_b, its run is adopted."""
    sources = PrimarySources([A])
    assert sources.announce('board_a', [A], 1, 'w1') is TAKEN
    assert sources.announce('board_b', [B], 2, 'w1') is TAKEN
    assert sources.announce('board_a', [A], 1, 'w2') is DISPUTED and sources.nodes == {B}
    assert sources.announce('board_a', [A], 3, 'w0') is DISPUTED and sources.nodes == {B}   # an old run, late
    assert sources.announce('board_b', [B], 1, 'w2') is ADOPTED and sources.word.run == 'w2'
    assert sources.announce('board_a', [A], 2, 'w2') is TAKEN and sources.nodes == {A}
    # w1 was left for w2: never followed again, even naming the board in force (re-adopted, it disputed
    # every later term of w2; review of session 51).
    assert sources.announce('board_a', [A], 2, 'w1') is PASSED and sources.ignored == 3
    assert sources.announce('board_b', [B], 3, 'w2') is TAKEN and sources.word.run == 'w2'


def test_a_run_adopted_brings_its_nodes():
    sources = PrimarySources([A])
    assert sources.announce('board_a', [A], 1, 'w1') is TAKEN
    assert sources.announce('board_a', [A, '/board_a/other'], 1, 'w2') is ADOPTED
    assert sources.nodes == {A, '/board_a/other'}


def test_the_first_word_is_taken_whatever_its_run_and_a_word_naming_no_node_never():
    sources = PrimarySources([A])
    assert sources.announce('board_b', [], 5, 'w1') is PASSED and sources.nodes == {A}
    assert sources.announce('board_b', [B], 7, 'w9') is TAKEN and sources.nodes == {B}


def test_a_late_word_of_an_earlier_watchdog_run_never_locks_out_the_live_one():
    """w1 (started at 200) names board_a; a late word of w0 (started at 100) naming board_a too was
    adopted and w1 left: its take-over naming board_b was refused for good (review of session 52)."""
    w0, w1, w2 = '100.0:7:aaa', '200.0:8:bbb', '300.0:9:ccc'
    sources = PrimarySources([A])
    assert sources.announce('board_a', [A], 1, w1) is TAKEN
    assert sources.announce('board_a', [A], 7, w0) is PASSED and sources.word.run == w1
    assert 'earlier' in sources.word.why
    assert sources.announce('board_b', [B], 2, w1) is TAKEN and sources.nodes == {B}
    assert sources.announce('board_a', [A], 9, w0) is PASSED          # an earlier run naming another board
    assert sources.announce('board_b', [B], 1, w2) is ADOPTED         # a later one naming the board in force
    assert sources.announce('board_b', [B], 3, w1) is PASSED and sources.word.run == w2


def test_a_watchdog_run_says_when_it_started():
    from aft_ftm.primary_word import run_started
    assert run_started('1796278101.141202:4242:0123456789ab') == 1796278101.141202
    assert run_started('w1') is None and run_started('x:1:y') is None and run_started('') is None
