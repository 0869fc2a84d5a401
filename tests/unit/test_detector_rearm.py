"""A crash detector whose verdict reached no Recovery (none connected yet, as while a site starts) and
whose peer is then heard again, as the same incarnation: it watches the peer again, with a fake clock
and no master. Before session 50 the FAILED it left was final with no witness to re-arm it: a pair
without a witness whose detectors suspected each other while they started stayed so, and once its
primary was powered off nobody was told, nobody took over (session 48's clean-clone CI)."""
import threading
import types

import pytest

detector_node = pytest.importorskip('aft_ftm.ros.detector_node')
import rospy  # noqa: E402
from aft_ftm.detector import HeartbeatMonitor, PeerState  # noqa: E402


class Clock(object):
    t = 0.0

    def monotonic(self):
        return self.t


@pytest.fixture
def node(monkeypatch):
    clock, alarms, published = Clock(), [], []
    monkeypatch.setattr(detector_node, 'time', clock)
    monkeypatch.setattr(detector_node, 'alarm', lambda ports, mechanism, kind, detail, request=None:
                        alarms.append((kind, detail)))
    monkeypatch.setattr(rospy.Time, 'now', lambda: rospy.Time(1))
    monkeypatch.setattr(rospy, 'get_name', lambda: '/master/crash_detector')
    connections = {'failures': 0}
    ports = types.SimpleNamespace(
        topic=lambda port: '/master/' + port,
        publisher=lambda port: types.SimpleNamespace(get_num_connections=lambda: connections.get(port, 0)),
        publish=lambda port, msg: published.append((port, msg)))
    n = object.__new__(detector_node.CrashDetectorNode)
    n.__dict__.update(lock=threading.Lock(), site='master', peer='slave', host='h', site_pid=7, period=0.01,
                      timeout=0.03, grace=0.0, phi=None, stopped=None, ports=ports, undelivered=None,
                      peer_back_told=False, watched_since=0)
    n.monitor = n._new_monitor(0.0)
    return n, clock, alarms, published, connections


def beat(pid=4242):
    return types.SimpleNamespace(site='slave', host='h', pid=pid, seq=0, stopping='')


def run(n, clock, until, beats=True, pid=4242):
    """The detector's loop until ``until``: the peer beats every period (or not), checked every tick."""
    while clock.t < until - 1e-9:
        clock.t += 0.002
        if beats and round(clock.t * 500) % 5 == 0:
            with n.lock:
                n.monitor.beat(clock.t, beat(pid))
        with n.lock:
            verdict = n.monitor.check(clock.t)
        if verdict is not None and n.stopped is None:
            n._report(verdict)
        elif n.undelivered is not None:
            n._deliver_late()


def kinds(alarms):
    return [k for k, _ in alarms]


def test_a_peer_suspected_before_recovery_connected_and_heard_again_is_watched_and_its_real_failure_reported(node):
    n, clock, alarms, published, connections = node
    run(n, clock, 0.2)                          # heard
    run(n, clock, 0.26, beats=False)            # a false suspicion while the sites start: nobody to tell
    assert kinds(alarms) == ['failure_undelivered'] and n.monitor.state == PeerState.FAILED
    run(n, clock, 0.5)                          # it beats again, as the same incarnation
    assert n.monitor.state == PeerState.ALIVE, 'the peer heard again is never watched again'
    assert kinds(alarms) == ['failure_undelivered', 'peer_watched'] and published == []
    connections['failures'] = 1                 # Recovery is up now
    run(n, clock, 0.6)
    assert published == [], 'a moot report was sent'
    run(n, clock, 0.7, beats=False)             # then it really fails (powered off)
    reports = [m for port, m in published if port == 'failures']
    assert len(reports) == 1 and reports[0].site == 'slave' and reports[0].pid == 4242, published


def test_a_peer_heard_again_as_another_incarnation_stays_failed(node):
    """Started again (another launcher pid), it holds nothing: it must re-join, never be watched as before."""
    n, clock, alarms, published, connections = node
    run(n, clock, 0.2)
    run(n, clock, 0.26, beats=False)
    run(n, clock, 0.5, pid=5555)
    assert n.monitor.state == PeerState.FAILED and 'peer_watched' not in kinds(alarms)
    connections['failures'] = 1
    run(n, clock, 0.7, beats=False)
    assert published == []


def test_a_peer_that_announced_its_fail_stop_is_not_watched_again(node):
    n, clock, alarms, published, connections = node
    run(n, clock, 0.2)
    with n.lock:
        n.monitor.announced(clock.t, 'its server died', beat())
    run(n, clock, 0.22, beats=False)
    assert kinds(alarms) == ['failure_undelivered']
    run(n, clock, 0.5)                          # beats of it heard after its last word
    assert n.monitor.state == PeerState.FAILED and 'peer_watched' not in kinds(alarms)


def test_a_fail_stopped_site_watches_nothing_again(node):
    n, clock, alarms, published, connections = node
    run(n, clock, 0.2)
    run(n, clock, 0.26, beats=False)
    n.stopped = 'its server died'
    run(n, clock, 0.5)
    assert n.monitor.state == PeerState.FAILED and 'peer_watched' not in kinds(alarms)


def test_a_peer_never_heard_within_the_start_up_grace_then_heard_is_watched(node):
    """Declared failed for not starting in time, with nobody to tell: once it starts, it is watched."""
    n, clock, alarms, published, connections = node
    n.grace = 0.1
    n.monitor = n._new_monitor(0.0)
    run(n, clock, 0.15, beats=False)
    assert kinds(alarms) == ['failure_undelivered']
    run(n, clock, 0.4)
    assert n.monitor.state == PeerState.ALIVE and kinds(alarms) == ['failure_undelivered', 'peer_watched']
    connections['failures'] = 1
    run(n, clock, 0.5, beats=False)
    assert [m.pid for port, m in published if port == 'failures'] == [4242]


def test_a_peer_that_beats_once_then_announces_its_fail_stop_is_not_watched_again(node):
    """Heard again after the verdict, then its stopping beat within the same check: it stopped (review)."""
    n, clock, alarms, published, connections = node
    run(n, clock, 0.2)
    run(n, clock, 0.26, beats=False)
    with n.lock:
        n.monitor.beat(clock.t, beat())
        n.monitor.announced(clock.t, 'its server died', beat())
    n._deliver_late()
    assert n.monitor.state == PeerState.FAILED and 'peer_watched' not in kinds(alarms)
