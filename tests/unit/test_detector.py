"""Failure detection from heartbeat timing, with a fake clock. No ROS."""
import pytest

from aft_ftm.detector import HeartbeatMonitor, PeerState
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
