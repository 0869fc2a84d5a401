"""The crash detector's watch of its site's required nodes (aft_ftm.site_watch): names read as roslaunch
gives them, the required ones read from the launch file, a death seen the moment it happens. No master."""
import os
import signal
import subprocess
import sys
import time

import psutil
import pytest

from aft_ftm import site_watch
from aft_ftm.ros.launch_files import replaceable_by_launch, required_by_launch
from aft_ftm.site_watch import SiteWatch, children_nodes, mark_retired, node_name

SRC = os.path.join(os.path.dirname(__file__), '..', '..', 'catkin_ws', 'src')
SITE_LAUNCH = os.path.abspath(os.path.join(SRC, 'aft_examples', 'launch', 'demo_replica_site.launch'))


@pytest.mark.parametrize('cmdline,environ,name', [
    (['/x/proceed', '__name:=proceed', '__log:=/l.log'], {'ROS_NAMESPACE': '/master/'}, '/master/proceed'),
    (['/x/proceed', '__name:=proceed'], {'ROS_NAMESPACE': '/master/tr'}, '/master/tr/proceed'),
    (['/x/proceed', '__name:=proceed'], {}, '/proceed'),
    (['/x/proceed', '__name:=proceed', '__ns:=/slave'], {'ROS_NAMESPACE': '/master/'}, '/slave/proceed'),
    (['/x/proceed', '__name:=/abs/p'], {'ROS_NAMESPACE': '/master/'}, '/abs/p'),
    (['/usr/bin/python3', '/usr/bin/roslaunch', 'a', 'b.launch'], {'ROS_NAMESPACE': '/m'}, None),   # not a node
])
def test_a_node_is_named_as_roslaunch_started_it(cmdline, environ, name):
    assert node_name(cmdline, environ) == name


def site_argv(*args):
    return ['/usr/bin/python3', '/usr/bin/roslaunch', '--wait', '--skip-log-check', SITE_LAUNCH,
            'site:=master', 'peer:=slave', 'role:=primary'] + list(args)


STAGES = {'/master/before', '/master/proceed', '/master/after'}
ALWAYS = {'/master/bank_server', '/master/protocol', '/master/crash_detector', '/master/recovery'}


@pytest.mark.parametrize('args,required', [
    ([], ALWAYS | STAGES),
    (['adaptable:=true'], ALWAYS),      # replaceable stages: their death alone is not the site's
    (['inner:=tr'], ALWAYS | {'/master/before', '/master/after', '/master/tr/protocol', '/master/tr/before',
                              '/master/tr/proceed',
                              '/master/tr/after'}),
])
def test_the_required_nodes_are_those_of_the_launch_file(args, required):
    assert required_by_launch(site_argv(*args)) == required


@pytest.mark.parametrize('args,replaceable', [
    ([], set()),                         # every stage required already
    (['adaptable:=true'], STAGES),       # an adaptation may retire them: watched, unless retired
    (['adaptable:=true', 'inner:=tr'], {'/master/before', '/master/after', '/master/tr/protocol',
                                        '/master/tr/before', '/master/tr/proceed', '/master/tr/after'}),
    (['adaptable:=true', 'link_monitor:=true'], STAGES),   # the link monitor is no stage
])
def test_the_replaceable_nodes_are_the_stages_an_adaptable_launch_does_not_require(args, replaceable):
    assert replaceable_by_launch(site_argv(*args)) == replaceable


def test_a_launcher_that_is_not_a_loadable_roslaunch_requires_nothing_known():
    assert required_by_launch(['/usr/bin/python3', '-m', 'pytest']) == set()
    assert required_by_launch(['/usr/bin/python3', '/usr/bin/roslaunch', '/nowhere/x.launch']) == set()
    assert required_by_launch(['/usr/bin/roslaunch', '-p', '11411', 'aft_ftm', 'replica.launch']) == set()


@pytest.fixture
def nodes():
    """Child processes named as roslaunch names nodes; all killed at the end."""
    started = []

    def start(name, ns='/m'):
        proc = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)', '__name:=' + name],
                                env=dict(os.environ, ROS_NAMESPACE=ns))
        started.append(proc)
        deadline = time.monotonic() + 5.0    # named once the child has run python (not yet at fork)
        while time.monotonic() < deadline and ('__name:=' + name) not in psutil.Process(proc.pid).cmdline():
            time.sleep(0.005)
        return proc
    yield start
    for proc in started:
        if proc.poll() is None:
            proc.kill()
        proc.wait()


def test_the_death_of_a_watched_node_is_seen_at_once_and_only_the_required_ones_count(nodes):
    a, b, other = nodes('a'), nodes('b'), nodes('c')
    watch = SiteWatch({'/m/a', '/m/b', '/m/late'})
    try:
        assert sorted(watch.adopt(children_nodes(os.getpid()))) == ['/m/a', '/m/b']
        assert watch.missing() == {'/m/late'}
        assert watch.wait(0.05) == []
        other.kill()          # not required: nothing to tell
        other.wait()
        assert watch.wait(0.1) == []
        killed = time.monotonic()
        b.send_signal(signal.SIGKILL)
        died = watch.wait(5.0)
        seen_after = time.monotonic() - killed
        assert died == [(b.pid, '/m/b')]
        assert seen_after < 5.0
        late = nodes('late')
        assert watch.adopt(children_nodes(os.getpid())) == ['/m/late']     # adopted once it runs
        assert watch.adopt(children_nodes(os.getpid())) == []              # and once only
        late.terminate()
        assert watch.wait(5.0) == [(late.pid, '/m/late')]
        assert a.poll() is None and watch.wait(0.05) == []
    finally:
        watch.close()


def test_a_node_dead_before_it_is_adopted_is_left_to_roslaunch(nodes):
    gone = nodes('a')
    gone.kill()
    gone.wait()
    watch = SiteWatch({'/m/a'})
    try:
        assert watch.adopt([(gone.pid, '/m/a')]) == []
        assert watch.missing() == {'/m/a'}
    finally:
        watch.close()


def test_a_node_marked_retired_dies_without_failure_once_and_any_other_death_is_one(nodes, tmp_path, monkeypatch):
    """An adaptation marks the node it retires before stopping it (mark_retired, by pid and create time):
    the watch of an adaptable site lets that death go, once; an unmarked death is a failure."""
    monkeypatch.setattr(site_watch, 'RETIRED_DIR', str(tmp_path / 'retired'))
    retired, crashed = nodes('proceed'), nodes('before')
    watch = SiteWatch({'/m/proceed', '/m/before'})
    try:
        assert sorted(watch.adopt(children_nodes(os.getpid()))) == ['/m/before', '/m/proceed']
        assert mark_retired(retired.pid)
        retired.terminate()
        assert watch.wait(5.0) == [(retired.pid, '/m/proceed')]
        assert watch.retired(retired.pid)
        assert not watch.retired(retired.pid)        # the mark is taken once
        assert os.listdir(str(tmp_path / 'retired')) == []
        crashed.kill()
        assert watch.wait(5.0) == [(crashed.pid, '/m/before')]
        assert not watch.retired(crashed.pid)
    finally:
        watch.close()
    gone = nodes('x')
    gone.kill()
    gone.wait()
    assert mark_retired(gone.pid) is None             # nothing to mark: the process is gone


def test_a_mark_nobody_took_is_removed_once_stale(nodes, tmp_path, monkeypatch):
    """A node retired whose site died first leaves its mark: the next mark written removes the stale ones."""
    monkeypatch.setattr(site_watch, 'RETIRED_DIR', str(tmp_path))
    stale, fresh = tmp_path / '1-100.00', tmp_path / '2-200.00'
    stale.touch()
    fresh.touch()
    old = time.time() - site_watch.STALE_MARK_S - 5
    os.utime(str(stale), (old, old))
    node = nodes('proceed')
    path = mark_retired(node.pid)
    assert sorted(os.listdir(str(tmp_path))) == sorted(['2-200.00', os.path.basename(path)])


def test_a_mark_left_by_an_engine_stopped_before_its_signal_hides_no_later_crash(nodes, tmp_path, monkeypatch):
    """An engine stopped between its mark and its SIGINT leaves the mark behind. The node's real crash
    later is a failure all the same: a mark counts only for a death soon after it was written (on the
    boot clock, which no wall-clock step moves). A mark that does not hold its time counts for nothing."""
    monkeypatch.setattr(site_watch, 'RETIRED_DIR', str(tmp_path))
    node = nodes('proceed')
    ticks = site_watch.start_ticks(node.pid)
    path = mark_retired(node.pid)
    with open(path) as f:
        written = float(f.read())
    assert not site_watch.take_retired(node.pid, ticks, now=written + site_watch.MARK_VALID_S + 1)
    assert not os.path.exists(path)                       # taken all the same: it can hide nothing more
    mark_retired(node.pid)
    assert site_watch.take_retired(node.pid, ticks, now=written + site_watch.MARK_VALID_S - 1)
    with open(path, 'w') as f:
        f.write('garbage')
    assert not site_watch.take_retired(node.pid, ticks) and not os.path.exists(path)
    watch = SiteWatch({'/m/proceed'})
    try:
        assert watch.adopt(children_nodes(os.getpid())) == ['/m/proceed']
        mark_retired(node.pid)
        with open(path, 'w') as f:                        # written long ago by an engine that stopped
            f.write('%.6f\n' % (time.clock_gettime(time.CLOCK_BOOTTIME) - site_watch.MARK_VALID_S - 1))
        node.kill()
        assert watch.wait(5.0) == [(node.pid, '/m/proceed')]
        assert not watch.retired(node.pid)
    finally:
        watch.close()
    assert os.listdir(str(tmp_path)) == []


def test_marks_count_only_in_a_directory_of_this_user_alone(nodes, tmp_path, monkeypatch):
    """A directory others may write into could hold planted marks that hide a crash: no mark is written
    there, and none found there counts."""
    shared = tmp_path / 'shared'
    shared.mkdir()
    monkeypatch.setattr(site_watch, 'RETIRED_DIR', str(shared))
    node = nodes('proceed')
    path = mark_retired(node.pid)
    ticks = site_watch.start_ticks(node.pid)
    os.chmod(str(shared), 0o777)
    with pytest.raises(PermissionError):
        mark_retired(node.pid)
    assert not site_watch.take_retired(node.pid, ticks)   # planted or not: not trusted
    os.chmod(str(shared), 0o700)
    assert site_watch.take_retired(node.pid, ticks) and not os.path.exists(path)
