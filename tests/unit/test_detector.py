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
