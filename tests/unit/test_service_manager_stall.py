"""Two defects of the service manager the review of session 34 found and left, each test failing on
the code before its fix: a stall of the manager's own (SIGSTOP/SIGCONT, swapped out) took the
services beating on the ROS channel for hung, and a new instance given a recycled pid had its beats
dropped as a replaced instance's. No master, no process spawned: a fake clock and fake children."""
import os
import threading
import time
import types

import pytest

from aft_service_manager import services, trust
from aft_service_manager.services import Sample, State, Supervisor, parse_config

ALIVE = Sample(alive=True, exit_code=None, stopped=False, cpu_percent=5.0, rss=50e6)
GB = 1e9
SERVICES = ('  a: {command: x, heartbeat_timeout: 0.2, heartbeat_channel: ros}\n'
            '  b: {command: x, heartbeat_timeout: 0.2}\n')


def config(services=SERVICES, manager='  period: 0.01\n'):
    return parse_config('manager:\n' + manager + 'services:\n' + services, source='test.yaml')


def running_since(sup, heard_at):
    """a (ROS channel, its beats stamped when handled) and b (local channel, its own time), heard at heard_at."""
    for name in ('a', 'b'):
        sup[name].spawned(0.0)
        sup[name].heard(heard_at, 'ok', stamped_here=name == 'a')
        assert sup[name].state == State.RUNNING


# -- 1: a stall of the manager's own ---------------------------------------------------------------
def test_after_a_stall_a_ros_service_gets_one_heartbeat_timeout_and_a_local_one_is_judged_at_once():
    """Stopped from 1.0 to 6.0, the manager checked before rospy handled the backlog: a restarted."""
    sup = Supervisor(config())
    running_since(sup, 1.0)
    assert sup.woke(6.0, 1.2) == pytest.approx(4.8)   # meant to wake at 1.2, woke at 6.0
    assert sup.stalls == 1
    assert sup.check('a', ALIVE, 6.0, GB) is None      # its beats of the stall are still in the socket
    assert sup.check('b', ALIVE, 6.0, GB).kind == 'heartbeat_timeout'   # its slot said 1.0: silent indeed
    sup['a'].heard(6.03, 'ok', stamped_here=True)       # the backlog, handled
    assert sup.check('a', ALIVE, 6.2, GB) is None and sup['a'].errors['heartbeat_timeout'] == 0


def test_a_real_hang_coinciding_with_a_stall_is_detected_one_timeout_after_it():
    sup = Supervisor(config())
    running_since(sup, 1.0)
    sup.woke(6.0, 1.2)
    assert sup.check('a', ALIVE, 6.19, GB) is None
    decision = sup.check('a', ALIVE, 6.21, GB)
    assert decision.kind == 'heartbeat_timeout' and 'no heartbeat for 210 ms' in decision.detail


def test_a_service_configured_local_whose_beats_come_on_ros_is_given_the_time_too():
    sup = Supervisor(config())
    sup['b'].spawned(0.0)
    sup['b'].heard(1.0, 'ok', stamped_here=True)   # e.g. a process that dropped its environment
    sup.woke(6.0, 1.2)
    assert sup.check('b', ALIVE, 6.0, GB) is None


def test_a_ros_service_starting_through_a_stall_is_not_timed_out_before_one_heartbeat_timeout():
    sup = Supervisor(config('  a: {command: x, heartbeat_timeout: 0.2, start_timeout: 1.0, heartbeat_channel: ros}\n'))
    sup['a'].spawned(0.0)
    sup.woke(3.0, 0.5)
    assert sup.check('a', ALIVE, 3.0, GB) is None and sup['a'].start_deadline() == pytest.approx(3.2)
    assert sup.check('a', ALIVE, 3.21, GB).kind == 'start_timeout'
    sup['a'].spawned(4.0)   # a new instance: judged on its own start_timeout again
    assert sup['a'].start_deadline() == pytest.approx(5.0)


@pytest.mark.parametrize('period, meant, woke, stall', [
    (0.01, None, 9.0, False),    # the first wake: nothing to compare with
    (0.01, 1.0, 0.5, False),     # woken early (a command, a process's end)
    (0.01, 1.0, 1.05, False),    # the scheduler's jitter on a busy machine
    (0.01, 1.0, 1.11, True),     # 0.1 s late
    (0.05, 1.0, 1.4, False),     # within 10 periods
    (0.05, 1.0, 1.6, True),
])
def test_only_a_wake_far_later_than_meant_is_a_stall(period, meant, woke, stall):
    sup = Supervisor(config(manager='  period: %s\n' % period))
    running_since(sup, 0.9)
    assert (sup.woke(woke, meant) is not None) == stall and sup.stalls == int(stall)
    assert services.stall_threshold(period) == max(0.1, 10 * period)


def _node(services=SERVICES):
    from aft_service_manager.ros.service_manager_node import ServiceManagerNode
    node = ServiceManagerNode.__new__(ServiceManagerNode)
    node.unacted, node.counted, node.already_counted = {}, set(), set()   # (the set-up's lost instances)
    node.config = config(services)
    node.supervisor, node.children, node.spares, node.replaced = Supervisor(node.config), {}, {}, {}
    node.lock, node.period, node.resource_period = threading.RLock(), 0.01, 0.1
    node.heartbeats = node.stale_heartbeats = node.refused_heartbeats = node.unknown_heartbeats = node.wakes = 0
    node.cycle_cpu = node.diagnostics_cpu = 0.0
    node.wake_r, node.wake_w = os.pipe()
    node.events = []
    node._event = lambda event, name, detail, now, **extra: node.events.append((event, name))
    return node


def test_the_manager_s_loop_notices_its_own_stall_before_it_checks(monkeypatch):
    """The node's loop: a wake 4.8 s later than it meant, and the ROS service is not restarted."""
    from aft_service_manager.ros import service_manager_node as node_module
    node = _node()
    clock, checks, done = [0.0], [], [False]
    monkeypatch.setattr(node_module, 'time', types.SimpleNamespace(monotonic=lambda: clock[0],
                                                                   thread_time=time.thread_time))
    wakes = iter(range(1000))
    monkeypatch.setattr(node_module.rospy, 'is_shutdown', lambda: done[0] or next(wakes) > 20)   # never for ever
    node._publish_diagnostics = lambda: None
    node.tree = types.SimpleNamespace(sweep=lambda: None)
    node.supervisor['a'].spawned(0.0)
    node.supervisor['a'].heard(0.0, 'ok')   # a beats on the ROS channel (its configuration)

    def cycle(now, resources, next_resources, next_diagnostics):
        if now == 0.0:
            clock[0] = 6.0        # stopped after this wake (it meant to wake at 0.2), continued at 6.0
            return [node.wake_r], 0.2
        checks.append(node.supervisor.check('a', ALIVE, now, GB))
        done[0] = True
        return [node.wake_r], now
    node._cycle = cycle
    try:
        node._loop()
    finally:
        os.close(node.wake_r)
        os.close(node.wake_w)
    assert checks == [None]   # (before: a heartbeat_timeout, a restart counted)
    assert node.supervisor.stalls == 1


# -- 2: a recycled pid -------------------------------------------------------------------------------
class _Child(object):
    """The current instance of a service: its pid, and what its tree holds."""

    def __init__(self, pid, beat=None):
        self.pid, self.beat, self.cpu_marks = pid, beat, []

    def owns(self, pid):
        return pid == self.pid

    def read_beat(self):
        return self.beat


def test_a_ros_heartbeat_from_the_current_instance_s_pid_counts_whatever_replaced_says():
    node = _node()
    node.origins = trust.HeartbeatOrigins(lambda header, pid: True)
    node.supervisor['a'].spawned(time.monotonic())
    node.children['a'] = _Child(4242)
    node.replaced['a'] = [17, 4242]   # an instance replaced long ago had that pid
    try:
        node._on_heartbeat(types.SimpleNamespace(name='a', pid=4242, status='ok', detail='',
                                                 _connection_header={'callerid': '/a'}))
        assert node.supervisor['a'].state == State.RUNNING and node.stale_heartbeats == 0
        node._on_heartbeat(types.SimpleNamespace(name='a', pid=17, status='ok', detail='',
                                                 _connection_header={'callerid': '/old_a'}))
        assert node.stale_heartbeats == 1   # a replaced instance's last words are still dropped
    finally:
        os.close(node.wake_r)
        os.close(node.wake_w)


def test_a_local_channel_word_from_the_current_instance_s_pid_counts_whatever_replaced_says():
    node = _node()
    node.supervisor['b'].spawned(0.0)
    node.children['b'] = _Child(4242, beat=(0.5, 'ok'))
    node.replaced['b'] = [4242]
    node.local = types.SimpleNamespace(receive=lambda: [(4242, 'started b')])
    try:
        node._read_channel(0.5)
    finally:
        os.close(node.wake_r)
        os.close(node.wake_w)
    assert node.supervisor['b'].state == State.RUNNING and node.stale_heartbeats == 0


def test_a_spawned_instance_s_pid_is_dropped_from_every_service_s_replaced_pids():
    """A new instance given a recycled pid: no longer a replaced one, for any service, and heard."""
    node = _node()
    node.origins = trust.HeartbeatOrigins(lambda header, pid: True)
    node.closing, node.spare_retry = False, {}
    node._record_pids = lambda: None
    node._start_process = lambda name, spare: _Child(4242)
    node.replaced = {'a': [4242, 17], 'b': [4242]}
    try:
        node._spawn('a', time.monotonic())
        assert node.replaced == {'a': [17], 'b': []}
        node._on_heartbeat(types.SimpleNamespace(name='a', pid=4242, status='ok', detail='',
                                                 _connection_header={'callerid': '/a'}))
        assert node.supervisor['a'].state == State.RUNNING and node.stale_heartbeats == 0
    finally:
        os.close(node.wake_r)
        os.close(node.wake_w)


# -- review of session 36: an alerted silence woke the loop every period ---------------------------
def test_a_silence_alerted_once_does_not_wake_the_loop_every_period_and_its_end_is_seen():
    """A service under on_failure alert that falls silent is alerted once and runs on; its heartbeat
    deadline stayed in the past, so the loop woke every manager period (100 times a second) for as
    long as the silence lasted. Now the next deadline is the next tick; a beat clears the alert."""
    node = _node('  a: {command: x, heartbeat_timeout: 0.2, on_failure: alert}\n')
    try:
        node.children['a'] = types.SimpleNamespace(watchdog=None, slot=None, beats=0)
        node.programs, node.spare_retry = None, {}
        s = node.supervisor['a']
        s.spawned(0.0)
        s.heard(0.1, 'ok')
        assert min(node._deadlines(5.0, 5.0)) == pytest.approx(0.3)   # the heartbeat deadline
        decision = node.supervisor.check('a', ALIVE, 0.5, GB)
        assert decision.kind == 'heartbeat_timeout' and decision.actions == [('alert', 'a')]
        assert s.state == State.RUNNING and 'heartbeat_timeout' in s.alerted
        assert min(node._deadlines(5.0, 5.0)) == 5.0   # (before: 0.3, in the past: every period)
        assert node.supervisor.check('a', ALIVE, 1.0, GB) is None   # said once
        s.heard(2.0, 'ok')
        node.supervisor.check('a', ALIVE, 2.05, GB)   # the next tick sees it beat again
        assert 'heartbeat_timeout' not in s.alerted and min(node._deadlines(5.0, 5.0)) == pytest.approx(2.2)
    finally:
        os.close(node.wake_r)
        os.close(node.wake_w)
