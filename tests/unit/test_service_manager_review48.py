"""The service manager's fixes of the review of session 48, each failing on the code before it: a new
instance's faults alerted afresh, the pids of a killed instance read before its kill, and an operator's
start of a dependant held while the service it is restarted with is held. No master."""
import os
import signal
import subprocess
import sys
import threading
import types

from aft_service_manager import trust, tree
from aft_service_manager.services import Sample, State, Supervisor, parse_config

OK = Sample(alive=True, exit_code=None, stopped=False, cpu_percent=5.0, rss=50e6)


def alerting(extra):
    return Supervisor(parse_config('services:\n  a: {command: x, on_failure: alert%s}\n' % extra))


def test_a_new_instance_over_its_memory_limit_is_alerted_though_the_one_before_was():
    """On the code before, the set of faults alerted outlived the instance: the new one's was never said."""
    sup = alerting(', memory_limit: 100MB')
    sup['a'].spawned(0.0)
    big = OK._replace(rss=500e6)
    first = sup.check('a', big, 0.1, 8e9)
    assert first is not None and first.kind == 'memory_limit'
    ok, actions, _ = sup.restart('a', 1.0)                      # an operator's restart: a new process
    assert ok and ('spawn', 'a') in actions
    sup['a'].spawned(1.0)
    decisions = [sup.check('a', big, t, 8e9) for t in (1.1, 1.2, 2.0)]
    assert [d.kind for d in decisions if d is not None] == ['memory_limit'], decisions


def test_a_new_instance_that_hangs_is_alerted_though_the_one_before_was():
    sup = alerting('')
    sup['a'].spawned(0.0)
    assert sup.check('a', OK, 1.0, 8e9) is None and sup['a'].state == State.RUNNING
    stopped = OK._replace(stopped=True)
    assert sup.check('a', stopped, 1.1, 8e9).kind == 'hang'
    assert sup.stop('a', 2.0)[0] and sup.start('a', 3.0)[0]
    sup['a'].spawned(3.0)
    decisions = [sup.check('a', stopped, t, 8e9) for t in (3.6, 3.7, 4.0)]
    assert [d.kind for d in decisions if d is not None] == ['hang'], decisions


WORKER_UNDER_LAUNCHER = ('import subprocess, sys, time\n'
                         'w = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])\n'
                         'print(w.pid, flush=True)\ntime.sleep(30)\n')


def test_the_workers_of_a_killed_instance_are_remembered_so_their_last_heartbeats_are_stale_not_forged(monkeypatch):
    """A service whose heartbeats come from a worker under its launcher (roslaunch, sh -c). On the code
    before, the instance's members were read after its SIGKILL, the worker was gone, and its last
    heartbeat (queued meanwhile) counted as refused, a lasting WARN in the diagnostics."""
    from aft_service_manager.ros import service_manager_node as m
    monkeypatch.setattr(m.rospy, 'logerr', lambda *a, **k: None)
    monkeypatch.setattr(m.rospy, 'logwarn_throttle', lambda *a, **k: None)
    cfg = parse_config('manager: {kill_timeout: 0.5}\nservices:\n  a: {command: x, heartbeat_timeout: 1.0, '
                       'heartbeat_channel: ros}\n')
    node = m.ServiceManagerNode.__new__(m.ServiceManagerNode)
    node.config, node.supervisor = cfg, Supervisor(cfg)
    node.children, node.spares, node.replaced, node.lock = {}, {}, {}, threading.RLock()
    node._record_pids = lambda: None
    node.heartbeats = node.stale_heartbeats = node.refused_heartbeats = node.unknown_heartbeats = 0
    node.origins = trust.HeartbeatOrigins(lambda header, pid: True)
    tagged = tree.TaggedTree('review48_%d' % os.getpid())
    prefix, env, handle = tagged.prepare('a-1')
    popen = subprocess.Popen(prefix + [sys.executable, '-c', WORKER_UNDER_LAUNCHER], env=dict(os.environ, **env),
                             stdout=subprocess.PIPE, universal_newlines=True, start_new_session=True)
    worker = None
    try:
        worker = int(popen.stdout.readline())
        child = m.Child(popen, 1.0, tree=tagged, handle=handle)
        assert child.owns(worker)
        node.children['a'] = child
        node.supervisor['a'].spawned(0.0)
        node._kill_from(node.children, 'a')                      # a fault's kill
        assert worker in node.replaced.get('a', []), node.replaced
        node.children['a'] = types.SimpleNamespace(owns=lambda pid: False, cpu_marks=[])   # the new instance
        node.supervisor['a']._change(State.RESTARTING, 1.0, 'restarted')
        node.supervisor['a'].spawned(1.0)
        node._on_heartbeat(types.SimpleNamespace(name='a', pid=worker, status='ok', detail='',
                                                 _connection_header={'callerid': '/a'}))
        assert (node.stale_heartbeats, node.refused_heartbeats) == (1, 0)
    finally:
        for pid in (popen.pid, worker):
            if pid is not None:
                try:
                    os.kill(pid, signal.SIGKILL)
                except OSError:
                    pass
        popen.stdout.close()
        popen.wait(5)


def test_an_operators_restart_of_a_dependant_waits_for_the_service_it_is_restarted_with(monkeypatch):
    """a: restart_delay 5 s, restart_with [b]. a faults at 10: both held until 15. An operator restarts b
    at 10.5. On the code before, b was spawned at once, ran without a, and was not restarted after it."""
    from aft_service_manager.ros import service_manager_node as m
    monkeypatch.setattr(m.time, 'monotonic', lambda: 10.5)
    node = m.ServiceManagerNode.__new__(m.ServiceManagerNode)
    node.config = parse_config('services:\n'
                               '  a: {command: x, heartbeat_timeout: 1.0, restart_delay: 5.0, restart_with: [b]}\n'
                               '  b: {command: y, heartbeat_timeout: 1.0}\n')
    node.supervisor, node.children, node.spares, node.replaced = Supervisor(node.config), {}, {}, {}
    node.stopping, node.lock, node.events, node.spawns = {}, threading.RLock(), [], []
    node._event = lambda event, name, detail, now, **extra: node.events.append((event, name, detail))
    node._sync_safe_state = lambda: True
    node._wake = lambda: None
    node.status = lambda name=None: {}
    node._kill = lambda name: node.children.pop(name, None)

    def spawn(name, now):
        node.spawns.append((name, now))
        node.children[name] = object()
        node.supervisor[name].spawned(now)
    node._spawn = spawn
    sup = node.supervisor
    for name in ('a', 'b'):
        sup[name].spawned(0.0)
        sup[name].heard(0.1, 'ok')
    sup.fault('a', 'exit', 'status 1', 10.0)
    assert sup['a'].spawn_at == 15.0 and sup['b'].state == State.RESTARTING
    reply = node._on_command('restart', types.SimpleNamespace(name='b'))
    assert node.spawns == [] and 'b held' in reply.message, (node.spawns, reply.message)
    actions = sup.due(15.0)
    assert actions == [('spawn', 'a'), ('spawn', 'b')], actions   # a first, then b after it
