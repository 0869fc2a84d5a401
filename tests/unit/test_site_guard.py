"""Nodes launched by an adaptation belong to their site: the guard's decisions with fake processes
and a fake clock, then the guard itself with real processes (no ROS)."""
import os
import signal
import subprocess
import sys
import time

import psutil
import pytest
from fakes import FakeClock

from aft_ftm.ros.launch_files import stopped_by_launch
from aft_ftm.ros.guarded_launch import create_time_of, disarm_guard_of, guarded
from aft_ftm.site_guard import (GUARD_EDGES, OWNERS_ENV, Action, Guard, GuardError, GuardState, Owner,
                                launcher_among, neighbours, parse_owners, same_process)
from aft_ftm.sites import process_tree, wait_dead


# -- owners --------------------------------------------------------------------------------------

class FakeProcesses(object):
    """pid -> create time; a pid missing is a process gone."""

    def __init__(self, **table):
        self.table = {int(k[1:]): v for k, v in table.items()}

    def create_time_of(self, pid):
        return self.table.get(pid)


def test_an_owner_is_alive_while_its_pid_runs_the_same_process():
    owner = Owner(4242, 1718000000.25)
    assert parse_owners(owner.encode()) == [owner]
    assert same_process(owner, FakeProcesses(p4242=1718000000.25).create_time_of(4242))
    assert not same_process(owner, FakeProcesses(p4242=1718000100.0).create_time_of(4242))   # pid reused
    assert not same_process(owner, FakeProcesses().create_time_of(4242))                     # gone


def test_several_owners_and_bad_ones_named():
    assert parse_owners('10:1.5, 20:2.5') == [Owner(10, 1.5), Owner(20, 2.5)]
    for bad in ('10', 'x:1.0', '10:', '0:1.0', ''):
        with pytest.raises(GuardError, match='pid:create_time'):
            parse_owners(bad)


RUNNING = ['/master/protocol', '/master/bank_server', '/master/tr/before', '/slave/protocol', '/proxy',
           '/master/proceed']


@pytest.mark.parametrize('name,expected', [
    ('/master/tr/protocol', ['/master/tr/before']),            # the deepest namespace with nodes
    ('/master/ad/protocol', ['/master/bank_server', '/master/proceed', '/master/protocol', '/master/tr/before']),
    ('/slave/after_lfr', ['/slave/protocol']),
    ('/elsewhere/x', []),                                       # a namespace no site runs
    ('/x', []),                                                 # the root is no site's
])
def test_a_new_node_joins_the_site_of_the_nodes_nearest_in_the_name_space(name, expected):
    assert neighbours(name, RUNNING) == expected


def test_the_launcher_is_the_nearest_roslaunch_above_the_node():
    chain = [(300, 3.0, ['/usr/bin/python3', '/ws/aft_ftm/nodes/protocol', '__name:=protocol']),
             (200, 2.0, ['/usr/bin/python3', '/usr/bin/roslaunch', '--wait', 'aft_ftm', 'site.launch']),
             (100, 1.0, ['/usr/bin/python3', '-m', 'pytest']),
             (1, 0.5, ['/sbin/init'])]
    assert launcher_among(chain) == Owner(200, 2.0)
    assert launcher_among(chain[:1] + chain[2:]) is None
    # A roslaunch node itself is not its own launcher.
    assert launcher_among(chain[1:2]) is None


# -- the guard's decisions -----------------------------------------------------------------------

class World(object):
    """What a guard sees: its launch running or not, its owners, the processes of its tree."""

    def __init__(self):
        self.clock = FakeClock(50.0)
        self.asked = False
        self.child = True
        self.owners = True
        self.tree = True
        self.looks = []

    def poll(self, guard):
        def owners():
            self.looks.append('owners')
            return self.owners

        def tree():
            self.looks.append('tree')
            return self.tree
        return guard.poll(self.clock.now, self.asked, self.child, owners, tree)


def test_the_guard_does_nothing_while_the_owners_run_and_only_looks_at_them():
    guard, world = Guard(grace=5.0), World()
    for _ in range(3):
        assert world.poll(guard).actions == []
        world.clock.advance(0.2)
    assert guard.state == GuardState.RUNNING and world.looks == ['owners'] * 3


def test_an_owner_gone_interrupts_the_launch_which_stops_in_its_grace():
    guard, world = Guard(grace=5.0), World()
    world.owners = False
    decision = world.poll(guard)
    assert decision.actions == [Action.INTERRUPT] and 'launcher of its site is gone' in decision.reason
    world.clock.advance(1.0)
    assert world.poll(guard).actions == []                    # stopping, within the grace
    world.child, world.tree = False, False                    # roslaunch stopped its nodes and exited
    assert world.poll(guard).actions == [Action.EXIT] and guard.state == GuardState.DONE


def test_a_launch_still_running_after_the_grace_is_killed_whole():
    guard, world = Guard(grace=5.0), World()
    world.asked = True
    assert world.poll(guard).actions == [Action.INTERRUPT]
    world.clock.advance(4.9)
    assert world.poll(guard).actions == []
    world.clock.advance(0.1)
    assert world.poll(guard).actions == [Action.KILL] and guard.state == GuardState.KILLING
    assert world.poll(guard).actions == [Action.KILL]         # again at each look, until gone
    world.child = world.tree = False
    assert world.poll(guard).actions == [Action.EXIT]


def test_a_launch_that_ends_by_itself_leaving_orphans_has_them_killed():
    guard, world = Guard(grace=5.0), World()
    world.child = False
    assert world.poll(guard).actions == [Action.KILL]
    world.tree = False
    assert world.poll(guard).actions == [Action.EXIT]
    assert 'owners' not in world.looks                        # an ended launch has nothing to guard


def test_a_launch_of_required_nodes_that_ends_by_itself_fails_its_site_first():
    guard, world = Guard(grace=5.0, fail_site=True), World()
    world.child = False                                       # a required replacement node died
    decision = world.poll(guard)
    assert decision.actions == [Action.FAIL_SITE, Action.KILL] and 'the site stops with it' in decision.reason
    world.tree = False
    assert world.poll(guard).actions == [Action.EXIT]


def test_a_disarmed_guard_or_one_asked_as_its_launch_ended_does_not_fail_the_site():
    guard, world = Guard(grace=5.0, fail_site=True), World()
    guard.disarm()                                            # its nodes retired on purpose
    world.child = False
    assert Action.FAIL_SITE not in world.poll(guard).actions
    guard, world = Guard(grace=5.0, fail_site=True), World()
    world.asked, world.child = True, False                    # Ctrl-C reached the launch and the guard at once
    assert Action.FAIL_SITE not in world.poll(guard).actions


@pytest.mark.parametrize('stop', ['asked', 'owners'])
def test_a_launch_of_required_nodes_asked_to_stop_or_stopping_with_its_site_never_fails_it(stop):
    guard, world = Guard(grace=5.0, fail_site=True), World()
    setattr(world, stop, stop == 'asked')                     # a rollback or retirement; or the site gone
    assert world.poll(guard).actions == [Action.INTERRUPT]
    world.child = False
    assert Action.FAIL_SITE not in world.poll(guard).actions


def test_processes_that_survive_kill_are_given_up_after_the_grace():
    guard, world = Guard(grace=1.0), World()
    world.child = False
    world.poll(guard)
    world.clock.advance(1.0)
    decision = world.poll(guard)
    assert decision.actions == [Action.EXIT] and 'gives up' in decision.reason


def test_every_edge_of_the_guard_is_in_its_table_with_a_reason():
    taken = set()
    for script in (
            [('owners', False), ('exit', None)],
            [('asked', True), ('grace', None), ('exit', None)],
            [('child', False), ('grace', None)],
            [('asked', True), ('child', False)]):
        guard, world = Guard(grace=1.0), World()
        change = guard._change
        guard._change = lambda cause, now, g=guard, c=change: taken.add((g.state, cause)) or c(cause, now)
        for what, value in script:
            if what == 'grace':
                world.clock.advance(1.0)
            elif what == 'exit':
                world.child = world.tree = False
            else:
                setattr(world, what, value)
            world.poll(guard)
    assert taken == set(GUARD_EDGES)
    assert all(reason for _, reason in GUARD_EDGES.values())
    with pytest.raises(GuardError):
        Guard(grace=0)


# -- the guard with real processes ---------------------------------------------------------------

# A launcher standing in for roslaunch: starts two "nodes" in sessions of their own and, on SIGINT,
# exits without stopping them (the worst case: what it leaves behind must be killed).
LAUNCH = ('import os, signal, subprocess, sys, time\n'
          'signal.signal(signal.SIGINT, lambda *a: sys.exit(0))\n'
          'for _ in range(2):\n'
          '    subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], start_new_session=True)\n'
          'print("owners " + os.environ.get("%s", ""), flush=True)\n'
          'time.sleep(60)\n' % OWNERS_ENV)


class Started(object):
    """Processes started by a test, all killed at the end, pass or fail."""

    def __init__(self):
        self.procs = []
        self.adopted = []   # psutil.Process of processes started by those (pid and create time: no reuse)

    def popen(self, argv, **kwargs):
        proc = subprocess.Popen(argv, start_new_session=True, **kwargs)
        self.procs.append(proc)
        return proc

    def adopt(self, proc):
        self.adopted.append(proc)
        return proc

    def cleanup(self):
        every = [p for proc in self.procs for p in process_tree(proc.pid)]
        every += [p for proc in self.adopted if proc.is_running() for p in process_tree(proc.pid)]
        for proc in every:
            try:
                proc.kill()
            except psutil.NoSuchProcess:
                pass
        for proc in self.procs:
            proc.wait()
        wait_dead(every, 5)


@pytest.fixture
def started():
    s = Started()
    yield s
    s.cleanup()


def owner_of(proc):
    return Owner(proc.pid, create_time_of(proc.pid))


def launch_under_guard(started, owner, grace=1.0):
    guard = started.popen(guarded([sys.executable, '-c', LAUNCH], [owner], poll=0.05, grace=grace),
                          stdout=subprocess.PIPE, text=True)
    while True:   # the guard says what it guards, then the launch says which owners it was given
        line = guard.stdout.readline()
        assert line, 'the guard ended early'
        if line.startswith('owners '):
            break
    assert line.split()[1] == owner.encode()
    deadline = time.monotonic() + 10
    while len(process_tree(guard.pid)) < 4 and time.monotonic() < deadline:   # guard, launch, 2 nodes
        time.sleep(0.01)
    tree = process_tree(guard.pid)
    assert len(tree) == 4
    return guard, tree


def test_when_the_sites_launcher_goes_the_whole_launch_goes_and_its_guard_exits(started):
    site = started.popen([sys.executable, '-c', 'import time; time.sleep(60)'])
    guard, tree = launch_under_guard(started, owner_of(site))
    assert wait_dead(tree, 0.5) == tree            # nothing stops while the site runs
    site.kill()
    site.wait()
    t0 = time.monotonic()
    assert wait_dead(tree, 10) == []
    assert guard.wait(5) == 0
    # Polled every 0.05 s; the launch exits on SIGINT leaving its nodes, killed at once after.
    assert time.monotonic() - t0 < 3


def test_the_guards_own_parent_exiting_does_not_stop_the_launch_but_sigint_does(started):
    site = started.popen([sys.executable, '-c', 'import time; time.sleep(60)'])
    owner = owner_of(site)
    # The engine: a process that starts the guarded launch, says its pid, and exits.
    engine = started.popen([sys.executable, '-c', 'import subprocess, sys; print(subprocess.Popen(sys.argv[1:], '
                            'start_new_session=True, stdout=subprocess.DEVNULL).pid)'] +
                           guarded([sys.executable, '-c', LAUNCH], [owner], poll=0.05, grace=1.0),
                           stdout=subprocess.PIPE, text=True)
    guard = started.adopt(psutil.Process(int(engine.stdout.readline())))
    assert engine.wait(10) == 0
    deadline = time.monotonic() + 10
    while len(process_tree(guard.pid)) < 4 and time.monotonic() < deadline:
        time.sleep(0.01)
    tree = process_tree(guard.pid)
    assert len(tree) == 4
    assert wait_dead(tree, 0.5) == tree            # outlives the engine that started it
    guard.send_signal(signal.SIGINT)               # an engine's rollback, an operator
    assert wait_dead(tree, 10) == []


def test_a_launch_whose_site_is_already_gone_is_not_started(started):
    site = started.popen([sys.executable, '-c', 'import time; time.sleep(60)'])
    owner = owner_of(site)
    site.kill()
    site.wait()
    guard = started.popen(guarded([sys.executable, '-c', LAUNCH], [owner], poll=0.05), stdout=subprocess.PIPE,
                          text=True)
    assert guard.wait(10) == 1
    assert 'already gone' in guard.stdout.read()


def test_a_retired_launch_does_not_fail_its_site(started):
    """An adaptation retiring a guarded launch's node disarms its guard first (SIGUSR1): the launch
    ends, the site runs on."""
    site = started.popen([sys.executable, '-c', 'import time; time.sleep(60)'])
    guard = started.popen(guarded([sys.executable, '-c', 'import time; time.sleep(60)'], [owner_of(site)],
                                  poll=0.05, grace=1.0, fail_site='master'), stdout=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 10
    while len(process_tree(guard.pid)) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    node = process_tree(guard.pid)[1]
    assert disarm_guard_of(node.pid) == guard.pid
    # Its two lines, what it guards and that it is disarmed, in either order: the SIGUSR1 may come
    # before the guard has printed its first line (seen in a clean-clone CI run).
    said = [guard.stdout.readline(), guard.stdout.readline()]
    assert any('stops with it' in line for line in said), said
    assert any('disarmed' in line for line in said), said
    node.kill()
    guard.wait(10)
    assert ' fails: ' not in guard.stdout.read()   # it never told the site to stop
    assert site.poll() is None, 'the site was failed by a retirement'


@pytest.mark.parametrize('args,site', [
    ({'site': 'master', 'mechanism': 'pbr'}, 'master'),      # stages.launch (update, switch)
    ({'ns': '/slave/tr', 'mechanism': 'tr'}, 'slave'),       # mechanism.launch (compose)
    ({'ns': '/pbr_tr'}, 'pbr_tr'),
    ({'mechanism': 'tr'}, ''),                               # says no site: none is failed
])
def test_the_site_a_required_replacement_fails_is_the_one_its_launch_names(args, site):
    from aft_ftm.ros.adaptation_engine import site_of_launch
    assert site_of_launch(args) == site


# -- what retiring a node stops with it ------------------------------------------------------------

STAGES = os.path.join(os.path.dirname(__file__), '..', '..', 'catkin_ws', 'src', 'aft_ftm', 'launch', 'stages.launch')


@pytest.mark.parametrize('args,node,expected', [
    # Before and After in one launch, required: retiring the After stops the Before (the campaign's
    # update after a switch left a primary without Before, silently).
    (['stages:=before+after', 'required:=true'], '/m/after_x', ['/m/before_x']),
    (['stages:=after', 'required:=true'], '/m/after_x', []),          # alone in its launch
    (['stages:=before+after', 'required:=false'], '/m/after_x', []),  # not required: nothing else stops
])
def test_a_required_node_retired_stops_the_rest_of_its_roslaunch(args, node, expected):
    argv = ['/usr/bin/python3', '/usr/bin/roslaunch', '--wait', '--skip-log-check', os.path.abspath(STAGES),
            'site:=m', 'peer:=s', 'role:=primary', 'suffix:=_x'] + args
    assert stopped_by_launch(argv, node) == expected


def test_what_is_not_a_roslaunch_of_a_loadable_file_stops_nothing_known():
    assert stopped_by_launch(['/usr/bin/python3', '-m', 'pytest'], '/m/after') == []
    assert stopped_by_launch(['/usr/bin/python3', '/usr/bin/roslaunch', '/nowhere/x.launch'], '/m/after') == []
