"""A service's process as the manager holds it (aft_service_manager.ros.service_manager_node.Child),
with real processes and no master: its process group is signalled only while its leader is not
reaped, since a reaped leader's pid, and so its group id, may belong to another process by then."""
import os
import signal
import subprocess
import sys
import time

import psutil

from aft_ftm.sites import wait_until
from aft_service_manager.ros.service_manager_node import Child


def test_a_reaped_service_is_never_signalled_by_its_old_group_id(monkeypatch):
    """An operator's stop leaves the service in the manager's ``stopping`` list until the manager's
    shutdown, hours later maybe: the shutdown's SIGTERM must not reach whatever group has its number."""
    ended = subprocess.Popen([sys.executable, '-c', 'import sys; sys.stdin.read()'], start_new_session=True,
                             stdin=subprocess.PIPE)
    child = Child(ended, 1.0)
    ended.stdin.close()   # it ends, and is reaped
    ended.wait(10)
    sent = []
    monkeypatch.setattr(os, 'killpg', lambda pgid, sig: sent.append((pgid, sig)))
    assert child.signal_session(signal.SIGTERM) is False and sent == []


def test_a_running_service_s_whole_group_is_signalled():
    leader = subprocess.Popen([sys.executable, '-c', 'import subprocess, sys, time\n'
                               'worker = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])\n'
                               'print(worker.pid, flush=True)\ntime.sleep(60)\n'],
                              start_new_session=True, stdout=subprocess.PIPE)
    worker = int(leader.stdout.readline())
    try:
        assert Child(leader, 1.0).signal_session(signal.SIGTERM) is True
        assert leader.wait(10) == -signal.SIGTERM
        for _ in range(200):   # the worker, in the same group, is ended too (a zombie, or reaped)
            try:
                if psutil.Process(worker).status() == psutil.STATUS_ZOMBIE:
                    break
            except psutil.NoSuchProcess:
                break
            time.sleep(0.05)
        else:
            raise AssertionError('the worker %d of the group outlived the SIGTERM' % worker)
    finally:
        for pid in (leader.pid, worker):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        leader.stdout.close()
        leader.wait(5)


def _node(tmp_path):
    """A manager without ROS: only what starting a process needs (a service beating on ROS, no spare)."""
    import threading
    from aft_service_manager.ros.service_manager_node import ServiceManagerNode
    from aft_service_manager.services import Supervisor, parse_config
    config = parse_config('manager: {state_dir: %s}\nservices:\n  a: {command: [%s, -c, "import time; time.sleep(60)"], '
                          'heartbeat_channel: ros}\n' % (tmp_path, sys.executable))
    node = ServiceManagerNode.__new__(ServiceManagerNode)
    node.unacted, node.counted, node.already_counted = {}, set(), set()   # (the set-up's lost instances)
    node.config, node.supervisor, node.closing, node.instances = config, Supervisor(config), False, 0
    node.heartbeat_topic, node.local, node.lock = '/aft/service_heartbeat', None, threading.RLock()
    node.children, node.spares, node.own_trees = {}, {}, []

    class NoTree(object):
        def prepare(self, name):
            return [], {}, None
    node.tree = NoTree()
    return node


def test_a_service_spawned_while_the_manager_shuts_down_on_the_same_thread_is_stopped(tmp_path, monkeypatch):
    """rospy runs the shutdown hook in the signal handler of the main thread, which spawns the services
    at set-up (the lock is re-entrant): a SIGINT between the manager's check and the fork let the
    service start after the shutdown's sweep, to run on unsupervised."""
    from aft_service_manager.ros import service_manager_node
    node, started = _node(tmp_path), []
    real = subprocess.Popen

    def popen_interrupted(*args, **kwargs):   # the signal comes as the fork is under way
        node.closing = True
        started.append(real(*args, **kwargs))
        return started[-1]
    monkeypatch.setattr(service_manager_node.subprocess, 'Popen', popen_interrupted)
    try:
        node._start_process('a', spare=False)
        raise AssertionError('a process was started during the shutdown and kept')
    except OSError as e:
        assert 'shutting down' in str(e)
    assert started and started[0].wait(10) == -signal.SIGKILL


def test_what_a_spawn_added_after_the_shutdown_took_its_list_is_stopped(tmp_path):
    node = _node(tmp_path)
    child = node._start_process('a', spare=False)
    node.children['a'] = child     # added after the shutdown had emptied the list
    node.closing = True
    node._stop_left_by_shutdown()
    assert node.children == {} and child.popen.wait(10) == -signal.SIGKILL


def test_the_memory_cpu_and_stop_of_a_worker_the_service_forked_are_the_service_s():
    """Review of session 36: only the leader was measured. A wrapper (sh -c) whose worker holds
    memory and spins never tripped a limit, and a stopped worker never looked hung."""
    worker_code = ('import time\nb = bytearray(200 * 2 ** 20)\nfor i in range(0, len(b), 4096): b[i] = 1\n'
                   'print("ready", flush=True)\nt = time.time()\nwhile time.time() - t < 30: pass\n')
    leader = subprocess.Popen(['/bin/sh', '-c', '"$0" -c "$1"; exit 0', sys.executable, worker_code],
                              start_new_session=True, stdout=subprocess.PIPE)
    try:
        assert leader.stdout.readline().strip() == b'ready'
        child = Child(leader, 0.5)
        first = child.sample(True)
        assert first.alive and not first.stopped
        assert first.rss > 150 * 2 ** 20, 'the worker\'s 200 MB not counted: %d bytes' % first.rss
        worker = psutil.Process(leader.pid).children()[0]
        time.sleep(0.7)
        spun = sum(worker.cpu_times()[:2])          # the worker's CPU so far (it spins): all of it counted
        second = child.sample(True)
        assert second.cpu_percent is not None and second.cpu_percent > 0.0, second
        # (>= but for float rounding: the same ticks summed in another order read 0.8999999999999999 once)
        assert child.cpu_total >= spun - 1e-6 and spun > 0.05, (child.cpu_total, spun)
        worker.suspend()
        # SIGSTOP takes effect when the kernel next handles the worker, not at once: once it shows stopped
        assert wait_until(lambda: worker.status() == psutil.STATUS_STOPPED, 5.0, 0.01), worker.status()
        assert child.sample(True).stopped, 'a stopped worker is a stopped service'
    finally:
        os.killpg(leader.pid, signal.SIGKILL)
        leader.wait(10)
