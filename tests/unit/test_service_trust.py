"""What the service manager trusts (issue 16): its private state directory and pid file, a process
named by pid, start time and command line, and heartbeats judged by who sent them. No ROS."""
import json
import os
import subprocess
import time

import psutil
import pytest

from aft_service_manager import trust
from aft_service_manager.services import ServiceConfigError


def test_the_state_directory_is_made_private_and_anything_else_is_refused_naming_it(tmp_path):
    made = tmp_path / 'fresh' / 'state'
    assert trust.ensure_private_dir(str(made)) == str(made)
    assert oct(os.stat(made).st_mode & 0o777) == oct(0o700)
    assert trust.ensure_private_dir(str(made)) == str(made)            # again: still fine
    shared = tmp_path / 'shared'
    shared.mkdir()
    os.chmod(shared, 0o777)
    link = tmp_path / 'link'
    link.symlink_to(made)
    plain = tmp_path / 'plain'
    plain.write_text('')
    foreign = tmp_path / 'foreign'
    foreign.mkdir()
    os.chown(foreign, 65534, 65534)   # the tests run as root, as the documented manager does
    for path, words in [(shared, 'writable by others (mode 777)'), (link, 'symbolic link'),
                        (plain, 'not a directory'), (foreign, 'belongs to uid 65534')]:
        with pytest.raises(ServiceConfigError) as error:
            trust.ensure_private_dir(str(path))
        assert str(path) in str(error.value) and words in str(error.value)
    assert trust.default_state_dir({'ROS_HOME': '/x/ros'}) == '/x/ros/aft_service_state'


def test_the_pid_file_is_written_0600_and_read_only_while_it_is_the_managers_own(tmp_path):
    path = str(tmp_path / 'manager.pids')
    assert trust.read_private_json(path) is None
    trust.write_private_json(path, {'a': {'pid': 1}})
    assert oct(os.stat(path).st_mode & 0o777) == oct(0o600)
    assert trust.read_private_json(path) == {'a': {'pid': 1}}
    assert [n for n in os.listdir(str(tmp_path)) if n.startswith('.tmp-')] == []
    os.chmod(path, 0o666)
    with pytest.raises(ValueError, match='not the manager'):
        trust.read_private_json(path)
    os.chmod(path, 0o600)
    os.chown(path, 65534, 65534)
    with pytest.raises(ValueError, match='uid 65534'):
        trust.read_private_json(path)
    target = tmp_path / 'elsewhere.json'
    target.write_text(json.dumps({'a': {'pid': 1}}))
    linked = tmp_path / 'linked.pids'
    linked.symlink_to(target)
    with pytest.raises(ValueError, match='not a regular file'):
        trust.read_private_json(str(linked))


def test_a_process_is_signalled_only_while_pid_start_time_and_command_line_all_match():
    child = subprocess.Popen(['sleep', '30'])
    try:
        proc = psutil.Process(child.pid)
        entry = trust.describe(proc)
        assert trust.same_process(entry, proc) is None
        assert 'was reused' in trust.same_process(dict(entry, create_time=entry['create_time'] - 3), proc)
        assert 'runs' in trust.same_process(dict(entry, cmdline=['sleep', '31']), proc)
        assert 'malformed' in trust.same_process({'pid': 'x'}, proc)
        assert 'is not' in trust.same_process(dict(entry, pid=child.pid + 1), proc)
    finally:
        child.kill()
        child.wait()


def test_a_process_described_in_the_middle_of_its_exec_is_recorded_with_its_command_line():
    """Popen returns once the exec has closed the child's descriptors, before the kernel set the new
    program's arguments: /proc/PID/cmdline read then is empty. Recorded so, the next manager judged the
    process another one and left it running (test_service_manager_lost, one run in two)."""
    class Exec(object):   # this process, its command line read empty twice, as during an exec
        pid = os.getpid()
        reads = 0

        def cmdline(self):
            self.reads += 1
            return [] if self.reads <= 2 else psutil.Process(self.pid).cmdline()
    proc = Exec()
    entry = trust.describe(proc)
    assert entry['cmdline'] == psutil.Process(os.getpid()).cmdline() and proc.reads == 3
    assert trust.same_process(entry, psutil.Process(os.getpid())) is None
    zombie = subprocess.Popen(['true'])   # ended, not reaped: no command line to wait for
    deadline = time.monotonic() + 10
    while psutil.Process(zombie.pid).status() != psutil.STATUS_ZOMBIE and time.monotonic() < deadline:
        time.sleep(0.01)
    began = time.monotonic()
    assert trust.describe(psutil.Process(zombie.pid))['cmdline'] == [] and time.monotonic() - began < trust.EXEC_WAIT
    zombie.wait()
    for _ in range(50):   # and for real: described as soon as Popen returns
        child = subprocess.Popen(['sleep', '30'], start_new_session=True)
        try:
            assert trust.describe(psutil.Process(child.pid))['cmdline'] == ['sleep', '30']
        finally:
            child.kill()
            child.wait()


@pytest.mark.parametrize('pid,owned,published,why', [
    (0, True, True, 'names no process'),
    (-1, True, True, 'names no process'),
    (42, False, True, 'not a process of this service'),
    (42, True, None, 'cannot be found'),
    (42, True, False, 'is another process'),
    (42, True, True, None),
])
def test_a_heartbeat_counts_only_from_the_services_own_publishing_process(pid, owned, published, why):
    asked = []
    origins = trust.HeartbeatOrigins(lambda connection, p: asked.append((connection, p)) or published)
    verdict = origins.judge({'callerid': '/svc'}, pid, lambda p: owned)
    assert (verdict is None) if why is None else (why in verdict)


def test_a_verified_sender_is_remembered_per_connection_and_checked_again_otherwise():
    asked = []
    origins = trust.HeartbeatOrigins(lambda connection, p: asked.append(p) or p == connection['pid'])
    first = {'callerid': '/svc', 'pid': 7}
    for _ in range(5):
        assert origins.judge(first, 7, lambda p: True) is None
    assert asked == [7]                                   # one check, then remembered
    # the restarted service: same node name, a new connection and pid; an old connection with it
    again = {'callerid': '/svc', 'pid': 8}
    assert origins.judge(again, 8, lambda p: True) is None
    assert 'is another process' in origins.judge(first, 8, lambda p: True)
    assert origins.judge(first, 7, lambda p: False) is not None              # no longer the service's
