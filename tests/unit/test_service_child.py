"""A service's process as the manager holds it (aft_service_manager.ros.service_manager_node.Child),
with real processes and no master: its process group is signalled only while its leader is not
reaped, since a reaped leader's pid, and so its group id, may belong to another process by then."""
import os
import signal
import subprocess
import sys
import time

import psutil

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
