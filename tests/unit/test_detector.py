"""Failure detection from heartbeat timing, with a fake clock. No ROS."""
import random

import pytest

from aft_ftm.detector import HeartbeatMonitor, PeerState, PhiAccrualMonitor, phi, phi_z, why_heard_again
from fakes import FakeClock


def beat_every(monitor, clock, period, count):
    verdicts = []
    for _ in range(count):
        clock.advance(period)
        monitor.beat(clock.now)
        verdicts.append(monitor.check(clock.now))
    return verdicts


def test_regular_heartbeats_never_raise_a_verdict():
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03)
    assert beat_every(monitor, clock, 0.01, 1000) == [None] * 1000
    assert monitor.state == PeerState.ALIVE


@pytest.mark.parametrize('silence,failed', [(0.02, False), (0.03, False), (0.0301, True), (1.0, True)])
def test_silence_longer_than_timeout_is_a_failure(silence, failed):
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03)
    monitor.beat(clock.now, info='site info')
    verdict = monitor.check(clock.advance(silence))
    assert (verdict is not None) == failed
    if failed:
        assert verdict.last_info == 'site info' and verdict.silence == pytest.approx(silence)
        assert monitor.state == PeerState.FAILED


def test_failure_is_declared_once():
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03)
    monitor.beat(clock.now)
    assert monitor.check(clock.advance(0.1)) is not None
    assert monitor.check(clock.advance(0.1)) is None


def test_a_peer_never_heard_is_not_a_crash_without_a_grace_period():
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03)
    assert monitor.check(clock.advance(100)) is None
    assert monitor.state == PeerState.UNKNOWN


def test_start_up_grace_declares_a_peer_that_never_came():
    clock = FakeClock(10.0)
    monitor = HeartbeatMonitor(timeout=0.03, startup_grace=5.0, started_at=clock.now)
    assert monitor.check(clock.advance(4.9)) is None
    assert 'never heard' in monitor.check(clock.advance(0.2)).reason


def test_heartbeat_after_failure_is_flagged_and_does_not_revive_the_peer():
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03)
    monitor.beat(clock.now)
    monitor.check(clock.advance(0.05))
    assert monitor.beat(clock.advance(0.01)) is True
    assert monitor.state == PeerState.FAILED and monitor.beats_after_failure == 1


@pytest.mark.parametrize('make', [lambda: HeartbeatMonitor(timeout=0.03),
                                  lambda: PhiAccrualMonitor(threshold=8, bootstrap_timeout=0.03)])
def test_a_peer_that_announces_its_fail_stop_is_declared_at_the_next_check_once(make):
    clock = FakeClock()
    monitor = make()
    beat_every(monitor, clock, 0.01, 50)
    assert monitor.announced(clock.advance(0.004), 'the required node /m/before died', info='last words') is True
    verdict = monitor.check(clock.advance(0.002))   # the next check, not one timeout later
    assert verdict is not None and 'announced its fail-stop: the required node /m/before died' in verdict.reason
    assert verdict.last_info == 'last words' and verdict.silence == pytest.approx(0.004)
    assert monitor.state == PeerState.FAILED
    # Declared once: neither a second announcement nor the silence that follows declares it again.
    assert monitor.announced(clock.advance(0.001), 'again') is False
    assert [monitor.check(clock.advance(0.01)) for _ in range(10)] == [None] * 10


def test_an_announcement_from_a_peer_already_declared_failed_changes_nothing():
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03)
    monitor.beat(clock.now)
    assert 'no heartbeat' in monitor.check(clock.advance(0.05)).reason
    assert monitor.announced(clock.advance(0.01), 'late words') is False
    assert monitor.check(clock.advance(0.01)) is None


def test_a_first_word_that_is_a_fail_stop_declares_a_peer_never_heard():
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03)
    assert monitor.announced(clock.now, 'deposed') is True
    assert 'deposed' in monitor.check(clock.advance(0.001)).reason


def test_invalid_timeout_is_refused():
    with pytest.raises(ValueError):
        HeartbeatMonitor(timeout=0)


def checked_every(monitor, clock, tick, duration):
    """Check every tick for duration seconds with no beat; returns the first verdict (or None)."""
    for _ in range(int(round(duration / tick))):
        verdict = monitor.check(clock.advance(tick))
        if verdict is not None:
            return verdict
    return None


def test_a_stall_of_the_detector_itself_is_not_held_against_the_peer():
    # Beats every 10 ms, checks every 2 ms; then this detector is not scheduled for 40 ms (the
    # machine stalled): the peer's beats of that time wait unread. Without stall_after that is a
    # 42 ms silence and a false failure; with it, only the 2 ms the detector ran count.
    for stall_after, failed in ((None, True), (0.01, False)):
        clock = FakeClock()
        monitor = HeartbeatMonitor(timeout=0.03, stall_after=stall_after)
        monitor.beat(clock.now)
        monitor.check(clock.advance(0.002))
        verdict = monitor.check(clock.advance(0.040))
        assert (verdict is not None) == failed
        if not failed:
            assert monitor.stalled == pytest.approx(0.040 - 0.010) and monitor.stalls == 1
            monitor.beat(clock.advance(0.001))   # the beats read at last: the peer is alive
            assert checked_every(monitor, clock, 0.002, 0.028) is None


def test_a_crashed_peer_is_declared_as_fast_while_the_detector_runs_on_time():
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03, stall_after=0.01)
    assert beat_every(monitor, clock, 0.01, 50) == [None] * 50
    crash = clock.now
    verdict = checked_every(monitor, clock, 0.002, 1.0)
    assert verdict is not None and clock.now - crash == pytest.approx(0.031, abs=0.0015)   # within a tick
    assert 'stalled' not in verdict.reason and monitor.stalls == 0


def test_a_stall_delays_the_verdict_on_a_crashed_peer_by_the_stall_only():
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03, stall_after=0.01)
    monitor.beat(clock.now)
    monitor.check(clock.advance(0.002))
    monitor.check(clock.advance(0.050))          # stalled 40 ms beyond stall_after
    verdict = checked_every(monitor, clock, 0.002, 1.0)
    assert verdict is not None
    assert verdict.silence == pytest.approx(0.030 + 0.040 + 0.001, abs=0.0015)
    assert 'of which 40.0 ms this detector was stalled' in verdict.reason


def test_the_check_that_ends_a_stall_waits_a_tick_for_the_beats_unread_meanwhile():
    """A campaign's false suspicion: the peer's beats were already 24 ms late, then this detector stalled
    81 ms; its first check after the stall found 34.2 ms not excused and declared the peer failed, while
    the peer's beats of that time still waited unread. That check now leaves the judgement to the next."""
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03, stall_after=0.01)
    monitor.beat(clock.now)
    assert checked_every(monitor, clock, 0.002, 0.024) is None
    assert monitor.check(clock.advance(0.081)) is None          # 34.2 ms not excused: it would have declared
    assert monitor.stalls == 1 and monitor.deferred
    monitor.beat(clock.advance(0.001))                           # the beats unread meanwhile, read at last
    assert checked_every(monitor, clock, 0.002, 0.028) is None
    assert monitor.state == PeerState.ALIVE


def test_a_dead_peer_is_declared_one_check_after_the_stall_and_at_every_other_late_check():
    """The deferral holds one check: a peer that stays silent is declared at the next, and a detector
    late at every check (starved, without real-time priority) still declares a dead peer."""
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03, stall_after=0.01)
    monitor.beat(clock.now)
    checked_every(monitor, clock, 0.002, 0.024)
    assert monitor.check(clock.advance(0.081)) is None
    verdict = monitor.check(clock.advance(0.002))
    assert verdict is not None and 'this detector was stalled' in verdict.reason
    starved = HeartbeatMonitor(timeout=0.03, stall_after=0.01)
    starved.beat(clock.now)
    verdicts = [starved.check(clock.advance(0.015)) for _ in range(40)]
    assert any(v is not None for v in verdicts), 'a detector late at every check never declared the dead peer'


def test_a_stall_before_the_last_beat_is_no_excuse_for_the_silence_after_it():
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03, stall_after=0.01)
    monitor.beat(clock.now)
    monitor.check(clock.advance(0.002))
    monitor.beat(clock.advance(0.045))            # read during the stall, before the late check
    monitor.check(clock.advance(0.001))
    assert monitor.stalled == pytest.approx(0.001)
    verdict = checked_every(monitor, clock, 0.002, 1.0)
    assert verdict is not None and verdict.silence == pytest.approx(0.031, abs=0.0015)


def test_invalid_stall_after_is_refused():
    with pytest.raises(ValueError, match='stall_after'):
        HeartbeatMonitor(timeout=0.03, stall_after=0)


# -- phi accrual ------------------------------------------------------------------------------------

PERIOD, TICK = 0.01, 0.002


def phi_monitor(**kw):
    settings = dict(threshold=8.0, bootstrap_timeout=0.03, window=100, min_std=0.005, min_samples=10,
                    stall_after=PERIOD)
    settings.update(kw)
    return PhiAccrualMonitor(**settings)


def jittered(monitor, clock, rng, count, jitter):
    """count beats, period +- jitter apart, checked every tick in between; the verdicts seen."""
    verdicts = []
    for _ in range(count):
        gap = PERIOD + rng.uniform(-jitter, jitter)
        due = clock.now + gap
        while clock.now + TICK < due:
            verdicts.append(monitor.check(clock.advance(TICK)))
        monitor.beat(clock.advance(due - clock.now))
        verdicts.append(monitor.check(clock.now))
    return [v for v in verdicts if v is not None]


def test_phi_is_the_normal_tail_in_log10_and_its_inverse_holds():
    assert phi(0.010, 0.010, 0.002) == pytest.approx(0.30, abs=0.01)        # at the mean: P(later) = 1/2
    values = [phi(0.010 + k * 0.001, 0.010, 0.002) for k in range(-20, 60)]
    assert values == sorted(values) and values[0] >= 0.0
    for threshold in (1.0, 3.0, 8.0, 12.0, 16.0):
        assert phi(phi_z(threshold), 0.0, 1.0) == pytest.approx(threshold, rel=1e-6)
    assert phi(-1e6, 0.0, 1e-3) == 0.0 and phi(1e6, 0.0, 1e-3) > 1e6       # far tails: no overflow


@pytest.mark.parametrize('seed', range(20))
def test_steady_heartbeats_with_bounded_jitter_are_never_suspected(seed):
    rng = random.Random(seed)
    jitter = rng.uniform(0.0, 0.004)
    clock = FakeClock(rng.uniform(0, 100))
    monitor = phi_monitor(threshold=rng.choice([3.0, 8.0, 12.0]))
    verdicts = jittered(monitor, clock, rng, 500, jitter)
    assert verdicts == [], 'seed %d (jitter %.1f ms): %s' % (seed, jitter * 1e3, verdicts)
    assert monitor.state == PeerState.ALIVE and not monitor.learning()


@pytest.mark.parametrize('seed', range(20))
def test_a_stop_is_suspected_within_the_bound_the_window_gives(seed):
    # Whatever the window holds, std <= (max - min) / 2, so the verdict comes at most
    # max + z(threshold) * max(min_std, (max - min) / 2) after the last beat (plus a check tick),
    # and not before the model's own suspicion time.
    rng = random.Random(seed)
    clock = FakeClock()
    threshold = rng.choice([3.0, 8.0, 12.0])
    monitor = phi_monitor(threshold=threshold, window=rng.choice([20, 100]))
    jittered(monitor, clock, rng, rng.randint(30, 300), rng.uniform(0.0, 0.005))
    intervals = list(monitor.intervals)
    bound = max(intervals) + phi_z(threshold) * max(0.005, (max(intervals) - min(intervals)) / 2.0)
    expected = monitor.suspicion_after()
    stop = clock.now
    verdict = checked_every(monitor, clock, TICK, 2.0)
    assert verdict is not None, 'seed %d' % seed
    assert expected - 1e-9 <= clock.now - stop <= min(bound, expected) + TICK + 1e-9, \
        'seed %d: verdict %.1f ms after the stop, model %.1f ms, bound %.1f ms' % (
            seed, (clock.now - stop) * 1e3, expected * 1e3, bound * 1e3)
    assert 'phi' in verdict.reason and monitor.state == PeerState.FAILED


@pytest.mark.parametrize('seed', range(20))
def test_a_one_off_pause_shorter_than_the_acceptable_pause_is_tolerated(seed):
    # Regular beats: mean 10 ms, std at its floor. With an acceptable pause P, any single silence
    # shorter than P + mean + z * min_std passes; the peer is alive after it, and a stop is then
    # still declared.
    rng = random.Random(seed)
    pause = rng.choice([0.0, 0.02, 0.05, 0.2])
    clock = FakeClock()
    monitor = phi_monitor(acceptable_pause=pause)
    jittered(monitor, clock, rng, 150, 0.0)
    tolerated = PERIOD + pause + phi_z(8.0) * 0.005
    silence = rng.uniform(PERIOD, tolerated - 2 * TICK)
    assert checked_every(monitor, clock, TICK, silence) is None, 'seed %d: pause %.1f ms' % (seed, silence * 1e3)
    monitor.beat(clock.now)
    assert jittered(monitor, clock, rng, 20, 0.0) == [] and monitor.state == PeerState.ALIVE
    stop = clock.now
    assert checked_every(monitor, clock, TICK, 2.0) is not None
    assert clock.now - stop <= monitor.suspicion_after() + TICK + 1e-9   # the pause, now learnt, widened it


def test_irregular_beats_widen_the_suspicion_time_and_regular_ones_narrow_it_again():
    rng = random.Random(5)
    clock = FakeClock()
    monitor = phi_monitor(window=50)
    jittered(monitor, clock, rng, 60, 0.0)
    quiet = monitor.suspicion_after()
    assert quiet < 0.04                                       # 10 ms + 5.2 x 5 ms
    for k in range(50):                                       # a loaded spell: gaps of 6 and 24 ms
        gap = 0.024 if k % 2 else 0.006
        assert checked_every(monitor, clock, TICK, gap - TICK) is None
        monitor.beat(clock.advance(TICK))
    loaded = monitor.suspicion_after()
    assert loaded > 0.06, 'after a spell of irregular beats, 60 ms of silence is no failure (%.1f ms)' % (loaded * 1e3)
    assert checked_every(monitor, clock, TICK, 0.06) is None
    monitor.beat(clock.now)
    jittered(monitor, clock, rng, 50, 0.0)                    # the window forgets the spell
    assert monitor.suspicion_after() == pytest.approx(quiet, abs=1e-6)


def test_while_learning_the_bootstrap_timeout_decides():
    clock = FakeClock()
    monitor = phi_monitor(bootstrap_timeout=0.05, min_samples=10)
    monitor.beat(clock.now)
    for _ in range(5):
        monitor.beat(clock.advance(PERIOD))
    assert monitor.learning() and monitor.phi(1.0) is None
    assert checked_every(monitor, clock, TICK, 0.048) is None
    verdict = checked_every(monitor, clock, TICK, 0.01)
    assert verdict is not None and 'while learning (5 of 10 intervals)' in verdict.reason


def test_phi_does_not_hold_the_detectors_own_stall_against_the_peer():
    clock = FakeClock()
    monitor = phi_monitor()
    jittered(monitor, clock, random.Random(1), 50, 0.0)
    monitor.check(clock.advance(0.002))
    assert monitor.check(clock.advance(0.080)) is None        # 72 ms of it this detector's own stall
    monitor.beat(clock.advance(0.001))
    assert max(monitor.intervals) < 0.02                      # nor is it learnt as the peer's lateness


def test_phi_shares_the_life_cycle_a_failed_peer_stays_failed():
    clock = FakeClock()
    monitor = phi_monitor(startup_grace=1.0, started_at=clock.now)
    assert monitor.state == PeerState.UNKNOWN
    jittered(monitor, clock, random.Random(2), 20, 0.0)
    assert checked_every(monitor, clock, TICK, 1.0) is not None
    assert monitor.beat(clock.advance(PERIOD)) is True and monitor.state == PeerState.FAILED
    with pytest.raises(AssertionError, match='no edge FAILED -> ALIVE'):
        monitor._change(PeerState.ALIVE)
    never = phi_monitor(startup_grace=1.0, started_at=clock.now)
    assert 'never heard' in checked_every(never, clock, 0.1, 2.0).reason


@pytest.mark.parametrize('kw,message', [
    (dict(threshold=0), 'threshold'), (dict(window=1), 'window'), (dict(window=2.5), 'window'),
    (dict(min_samples=1), 'min_samples'), (dict(window=20, min_samples=21), 'min_samples'),
    (dict(min_std=0), 'min_std'), (dict(acceptable_pause=-0.1), 'acceptable_pause'),
    (dict(bootstrap_timeout=0), 'timeout')])
def test_invalid_phi_settings_are_refused_by_name(kw, message):
    with pytest.raises(ValueError, match=message):
        phi_monitor(**kw)


def test_a_peer_heard_again_says_whether_it_stalled_lost_beats_arrived_late_or_started_again():
    """The peer_back alarm tells the cause of a false suspicion apart, from the beats' own numbers and
    send stamps: the next beat sent late (the sender stalled), sent on time but heard late (the way or
    this receiver), beats missing in between, or counting from the start again (a new process)."""
    period, timeout = 0.01, 0.03
    stalled = why_heard_again((41, 100.000), (42, 100.045), period, timeout)
    assert stalled.startswith('the sender stalled') and '45.0 ms' in stalled
    late = why_heard_again((41, 100.000), (42, 100.010), period, timeout)
    assert 'sent on time' in late and 'arrived late' in late
    slow = why_heard_again((41, 100.000), (42, 100.025), period, timeout)
    assert slow.startswith('the sender was slow') and '25.0 ms' in slow
    lost = why_heard_again((41, 100.000), (45, 100.040), period, timeout)
    assert lost.startswith('3 beat(s) between seq 41 and 45 were not heard')
    assert 'started again' in why_heard_again((41, 100.000), (1, 130.0), period, timeout)
    assert why_heard_again(None, (42, 100.01), period, timeout) is None     # a peer watched afresh: nothing known


def test_a_site_runs_while_its_beats_are_heard_even_declared_failed_and_not_once_it_announced_its_stop():
    """What a primary asks before it admits a joiner: does the joiner's site run? Its beats within the
    timeout, in any state (a site relaunched beats again while its old verdict stands), and not since
    it announced its fail-stop (a site stopping whose After still joins)."""
    clock = FakeClock()
    monitor = HeartbeatMonitor(timeout=0.03, stall_after=0.01)
    assert not monitor.heard_within(clock.now, 0.03)                  # never heard
    monitor.beat(clock.now)
    assert monitor.heard_within(clock.advance(0.02), 0.03)
    assert checked_every(monitor, clock, 0.002, 0.1) is not None       # silent: declared failed
    assert not monitor.heard_within(clock.now, 0.03)
    monitor.beat(clock.advance(0.5))                                    # it beats again: it runs
    assert monitor.state == PeerState.FAILED and monitor.heard_within(clock.advance(0.01), 0.03)
    monitor.announced(clock.advance(0.001), 'the required node /b/server died')
    assert not monitor.heard_within(clock.now, 0.03)                    # it said it stops
    monitor.beat(clock.advance(2.0))                                    # a new site process beats
    assert monitor.heard_within(clock.now, 0.03)


@pytest.mark.parametrize('make', [lambda: HeartbeatMonitor(timeout=0.03),
                                  lambda: PhiAccrualMonitor(threshold=8, bootstrap_timeout=0.03)])
def test_the_last_word_of_an_older_incarnation_does_not_fail_the_one_that_runs(make):
    """Review of stop 39: a site started again and re-joined; a late 'stopping' beat of its old
    incarnation (another launcher pid) declared the healthy new one failed, and it was failed over."""
    import types
    clock = FakeClock()
    monitor = make()
    new = types.SimpleNamespace(host='slave', pid=2002)
    for _ in range(20):
        monitor.beat(clock.advance(0.01), new)
    old = types.SimpleNamespace(host='slave', pid=1001)
    assert monitor.announced(clock.advance(0.001), 'fail-stop of the old incarnation', old) is False
    assert monitor.state == PeerState.ALIVE and monitor.stale_announcements == 1
    assert monitor.check(clock.advance(0.005)) is None
    # one that names no incarnation (pid 0) is not judged stale: nothing to tell it by
    unnamed = types.SimpleNamespace(host='slave', pid=0)
    other = make()
    other.beat(clock.advance(0.01), new)
    assert other.announced(clock.advance(0.001), 'unnamed', unnamed) is True
    assert monitor.announced(clock.advance(0.001), 'its own fail-stop', new) is True   # its own last word counts
    assert monitor.check(clock.advance(0.001)).reason.endswith('its own fail-stop')
