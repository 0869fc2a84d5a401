"""Every process of a service (aft_service_manager.tree), with real processes and no ROS: a service
that daemonizes (double fork, setsid) and one whose children start sessions of their own, as
roslaunch's do, leave nothing running once their tree is killed; by a cgroup where the machine
offers cgroup v2, and by the environment tag otherwise (both are run here when both exist)."""
import os
import subprocess
import sys
import time
import uuid

import pytest

from aft_ftm.sites import pid_gone
from aft_service_manager import tree

# Prints the pids of what it leaves behind, then exits (a daemon) or waits (a launcher).
DAEMON = r'''
import os, sys, time
r, w = os.pipe()
if os.fork() == 0:
    os.setsid()
    if os.fork() == 0:
        os.write(w, b'%d\n' % os.getpid())
        time.sleep(60)
    os._exit(0)
print(os.read(r, 100).decode().strip(), flush=True)
'''
LAUNCHER = r'''
import subprocess, sys, time
kids = [subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'], start_new_session=True)
        for _ in range(3)]
print(' '.join(str(k.pid) for k in kids), flush=True)
time.sleep(60)
'''


def kinds():
    out = [pytest.param(lambda owner: tree.TaggedTree(owner), id='tag')]
    if tree.cgroup2_root():
        out.append(pytest.param(lambda owner: tree.make(owner), id='cgroup'))
    return out


def start(kind, script):
    owner = 'test_%s' % uuid.uuid4().hex[:8]
    t = kind(owner)
    prefix, env, handle = t.prepare('svc-1')
    proc = subprocess.Popen(prefix + [sys.executable, '-c', script], env=dict(os.environ, **env),
                            stdout=subprocess.PIPE, universal_newlines=True, start_new_session=True)
    left = [int(p) for p in proc.stdout.readline().split()]
    assert left and all(not pid_gone(p) for p in left)
    return t, handle, proc, left


def clean_up(t, proc, left):
    """Whatever a failed test left: the processes it started, its tree."""
    for p in left:
        try:
            os.kill(p, 9)
        except OSError:
            pass
    proc.kill()
    t.close()


@pytest.mark.parametrize('kind', kinds())
@pytest.mark.parametrize('script', [DAEMON, LAUNCHER], ids=['daemon', 'sessions'])
def test_killing_the_tree_leaves_nothing_of_the_service(kind, script):
    t, handle, proc, left = start(kind, script)
    try:
        assert all(t.owns(handle, p) for p in left)
        assert not t.owns(handle, os.getpid())
        assert set(left) <= set(t.members(handle))
        assert t.kill(handle, 5.0)
        proc.wait(5)
        deadline = time.monotonic() + 5.0
        while not all(pid_gone(p) for p in left) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert all(pid_gone(p) for p in left), [p for p in left if not pid_gone(p)]
        assert t.members(handle) == []
        if t.kind == 'cgroup':
            assert not os.path.exists(handle)         # its cgroup removed
    finally:
        clean_up(t, proc, left)


@pytest.mark.parametrize('kind', kinds())
def test_a_new_manager_finds_what_an_earlier_one_left(kind):
    t, handle, proc, left = start(kind, DAEMON)
    try:
        proc.wait(5)
        again = kind(t.owner if hasattr(t, 'owner') else os.path.basename(t.base))   # the same owner
        assert again.leftovers() == [handle]
        assert again.kill(handle, 5.0) and again.leftovers() == []
    finally:
        clean_up(t, proc, left)


def test_the_cgroup_v2_mount_is_found_in_mountinfo(tmp_path):
    info = tmp_path / 'mountinfo'
    info.write_text('25 1 0:22 / /sys rw - sysfs sysfs rw\n'
                    '41 31 0:38 / %s rw,relatime - cgroup2 cgroup2 rw\n' % tmp_path)
    (tmp_path / 'cgroup.procs').write_text('')
    assert tree.cgroup2_root(str(info)) == str(tmp_path)
    info.write_text('25 1 0:22 / /sys rw - sysfs sysfs rw\n')
    assert tree.cgroup2_root(str(info)) is None


def test_a_process_read_in_the_middle_of_its_exec_is_still_the_services(monkeypatch):
    """A launcher's child read just after its fork, while the kernel replaces its memory, shows an empty
    environment: it was taken for no member of the service (CI, session 44: the test above failed so),
    and a kill could have left it running. One whose parent carries the tag is read again until its
    exec is done; one that stays empty (it cleared its environment) is waited for once only."""
    t, handle, proc, left = start(lambda owner: tree.TaggedTree(owner), LAUNCHER)
    try:
        child, other = left[0], left[1]
        real = tree.psutil.Process.environ
        reads = {}

        def mid_exec(self):   # the child's first two reads come back empty, as during an exec; the
            reads[self.pid] = reads.get(self.pid, 0) + 1    # other one's always (it ran env -i)
            if self.pid == child and reads[child] <= 2:
                return {}
            return {} if self.pid == other else real(self)
        monkeypatch.setattr(tree.psutil.Process, 'environ', mid_exec)
        assert t.owns(handle, child) and reads[child] == 3
        assert not t.owns(handle, other) and reads[other] > 3   # read again for the whole wait, then known bare
        reads.clear()
        members = t.members(handle)
        assert child in members and other not in members and proc.pid in members
        assert reads[other] == 1, 'a process known bare was waited for again: %d reads' % reads[other]
    finally:
        monkeypatch.undo()
        clean_up(t, proc, left)


def test_a_process_without_an_environment_outside_the_service_costs_no_wait():
    """Kernel threads, zombies, and processes of others without an environment: not waited for."""
    t = tree.TaggedTree('test_%s' % uuid.uuid4().hex[:8])
    _, _, handle = t.prepare('svc-1')
    bare = subprocess.Popen(['env', '-i', sys.executable, '-c', 'import time; time.sleep(30)'])
    real = tree.psutil.Process.environ
    reads = []
    try:
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and real(tree.psutil.Process(bare.pid)):
            time.sleep(0.01)                          # (its exec done: an empty environment)
        tree.psutil.Process.environ = lambda self: reads.append(self.pid) or real(self)
        assert t.members(handle) == [] and not t.owns(handle, bare.pid)
        assert reads.count(bare.pid) == 2, reads.count(bare.pid)   # once by each call: never waited for
    finally:
        tree.psutil.Process.environ = real
        bare.kill()
        bare.wait(5)
