"""The crash detector's watch of its site's After (``~alive_timeout``), with a fake clock and no master:
when a hung After fail-stops its board, and when it is only said. Review of session 38."""
import threading
import types

import pytest

detector_node = pytest.importorskip('aft_ftm.ros.detector_node')
import rospy  # noqa: E402
from aft_ftm.detector import HeartbeatMonitor, PeerState  # noqa: E402
from std_msgs.msg import Bool  # noqa: E402


@pytest.fixture
def node(monkeypatch):
    alarms, stops = [], []
    monkeypatch.setattr(detector_node, 'alarm', lambda ports, mechanism, kind, detail, request=None:
                        alarms.append((kind, detail)))
    monkeypatch.setattr(rospy.Time, 'now', lambda: rospy.Time(1))
    n = object.__new__(detector_node.CrashDetectorNode)
    n.__dict__.update(lock=threading.Lock(), site='board_b', peer='board_a', host='h', site_pid=7, period=0.01,
                      timeout=1.0, stopped=None, alive_timeout=0.25, alive_from='', alive_strangers=0,
                      alive_replaceable=False, alive_hang=None, peer_heard_within=0.1,
                      ports=types.SimpleNamespace(topic=lambda port: '/board_b/after_alive'))
    n.monitor = HeartbeatMonitor(1.0, 0.0, 0.0, stall_after=0.01)
    n.alive = HeartbeatMonitor(0.25, 0.0, 0.0, stall_after=0.01)

    def fail_stop(failure):
        stops.append(failure.reason)
        n.stopped = failure.reason
    n._on_fail_stop = fail_stop
    return n, alarms, stops


def run(n, start, end, peer=True, sign=None, step=0.01):
    """The loop from start to end: the peer beats (or not), the After gives a sign (or not), each check."""
    t = start
    while t < end - 1e-9:
        if peer:
            n.monitor.beat(t, types.SimpleNamespace(pid=1, host='h'))
        if sign is not None:
            n._on_alive(Bool(data=sign))   # (its arrival: the clock below is the monitor's)
            n.alive.last_heard = n.alive.last_check = t
        n.monitor.check(t)
        n._check_alive(t)
        t += step
    return t


def test_a_hung_primary_after_is_failed_over_though_its_peer_was_declared_failed_and_came_back(node):
    """board_b took over from board_a, which came back and re-joined: board_b's verdict on it stands
    (no witness in the car), and the first version asked can_take_over, which said 'declared failed'
    for ever: a hang of board_b's After was never failed over."""
    n, alarms, stops = node
    t = run(n, 0.0, 1.0, sign=False)
    t = run(n, t, t + 1.2, peer=False, sign=False)          # board_a loses power: declared failed
    assert n.monitor.state == PeerState.FAILED
    t = run(n, t, t + 1.0, sign=True)                        # it is back, re-joined: board_b replaceable
    run(n, t, t + 0.5)                                       # board_b's After hangs
    assert len(stops) == 1 and 'no sign of life on /board_b/after_alive' in stops[0] and alarms == []


def test_a_hang_while_the_peer_is_not_heard_is_said_then_failed_over_once_it_is(node):
    n, alarms, stops = node
    t = run(n, 0.0, 1.0, sign=True)
    t = run(n, t, t + 0.4, peer=False)                       # the After hangs, and the peer is silent meanwhile
    assert stops == [] and [k for k, _ in alarms] == ['node_hung'] and 'not heard now' in alarms[0][1]
    run(n, t, t + 0.1)                                       # the peer beats again: judged again
    assert len(stops) == 1 and len(alarms) == 1


def test_a_backup_or_a_lone_primary_s_hung_after_is_said_once_and_serves_again(node):
    n, alarms, stops = node
    t = run(n, 0.0, 1.0, sign=False)
    t = run(n, t, t + 2.0)                                   # hung for 2 s: said once
    assert stops == [] and [k for k, _ in alarms] == ['node_hung'] and 'no backup could take over' in alarms[0][1]
    t = run(n, t, t + 0.1, sign=False)                       # it resumes
    assert n.alive_hang is None and [k for k, _ in alarms] == ['node_hung', 'node_resumed']
    run(n, t, t + 1.0)                                       # and hangs again: said again
    assert [k for k, _ in alarms] == ['node_hung', 'node_resumed', 'node_hung'] and stops == []
