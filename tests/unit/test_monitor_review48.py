"""The Monitoring and Adaptation Engines' fixes of the review of session 48, each failing on the code
before it: a hold that overflowed after 1 024 failures, an older witness configuration that brought a
lost site back, a retired node left running unsaid, and leases without a bound; then three it left: the
monitor's notes without bound, two turns for one master under two names, and a launched node waited for
until the launch timeout. No master."""
import pytest
import rospy
from aft_msgs.msg import Configuration
from aft_msgs.srv import SuspendRequest

from aft_ftm.mechanisms import CRASH
from aft_ftm.monitor import MonitorCore, MonitorState
from aft_ftm.ports import SUBSCRIBE, PortSpec
from aft_ftm.adaptation import StepError
from aft_ftm.ros import adapt_command, adaptation_engine, ports as ros_ports
from aft_ftm.suspension import MAX_LEASE

import test_engine_pause as tep
import test_monitor_review as review
from test_engine_pause import graph  # noqa: F401 (a fixture)

HIGH, LOW = 5e6, 5e4   # bytes/s: above bandwidth_high, below it (PBR needs 'high')


@pytest.fixture(autouse=True)
def own_turns(monkeypatch, tmp_path):
    from aft_ftm.turns import Turn
    monkeypatch.setattr(Turn, 'DIRECTORY', str(tmp_path))


def test_a_model_that_keeps_failing_is_held_at_the_cap_for_ever_not_overflowed():
    """2 ** 1024 overflowed at the 1 025th failure on one model (a bandwidth flapping, a switch that keeps
    failing), before the state left ADAPTING: the monitor's thread died and it never adapted again."""
    clock = review.FakeClock(100.0)
    core = MonitorCore(frozenset([CRASH]), review.DET_STATE, review.SITES, ('pbr',), clock.now,
                       lost_after=review.LOST_AFTER, retry_hold=0.0)
    failures = 0
    for cycle in range(2100):
        clock.advance(0.2)
        for s in review.SITES:
            core.heartbeat(s, clock.now)
        core.bandwidth(LOW if cycle % 2 == 0 else HIGH, clock.now)
        decision = core.decide(clock.now)
        if decision is not None:
            core.adaptation_failed('switch refused: %d' % failures, clock.now)
            failures += 1
    assert failures > 1025 and core.state != MonitorState.ADAPTING


def test_an_older_witness_configuration_brings_no_lost_site_back(monkeypatch):
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))
    clock = review.FakeClock(100.0)
    core = MonitorCore(frozenset([CRASH]), review.DET_STATE, review.SITES, ('pbr',), clock.now,
                       lost_after=review.LOST_AFTER, follows_witness=True)
    node = review.monitor_node(core, review.FakeEngine({}))
    node.sites = list(review.SITES)
    node._on_configuration(Configuration(epoch=3, primary='master', backup='slave'))
    review.Node(core, clock).run(1.0)
    node._on_configuration(Configuration(epoch=4, primary='master', backup=''))   # the slave excluded
    for _ in range(int((review.LOST_AFTER + 0.5) / review.PERIOD)):
        clock.advance(review.PERIOD)
        core.heartbeat('master', clock.now)
        core.tick(clock.now)
    assert core.lost == {'slave'}
    node._on_configuration(Configuration(epoch=3, primary='master', backup='slave'))   # stale, re-published
    assert core.lost == {'slave'} and core.model().resources.cpus == 1
    node._on_configuration(Configuration(epoch=5, primary='master', backup='slave'))   # re-joined for real
    assert core.lost == set()


def test_a_retired_node_the_adaptation_could_not_stop_is_said_in_an_alarm(graph, monkeypatch):  # noqa: F811
    e = tep.engine(graph)

    def kill(node, prepared=None):
        if node == '/master/proceed':
            raise StepError('cannot mark /master/proceed (pid 1234) retired (Permission denied): not killed')
        return adaptation_engine.Killed(2, [], '/', {}, [])
    e._kill = kill
    report = e.run(tep.compose(), 'prepared')
    assert report['ok'] and report['state'] == 'DONE'
    assert '/master/proceed' in report['alarm'] and 'runs on beside the new nodes' in report['alarm']


def test_a_lease_is_bounded_everywhere_a_suspension_is_asked(tmp_path, monkeypatch):
    """adapt --lease inf, a ~suspend call with lease 1e10, an Engine with an infinite lease: refused. Taken,
    a suspender killed in the pause left the node suspended for good, and the lease keeper died."""
    script = tmp_path / 's.yaml'
    script.write_text('name: s\nkind: compose\nsuspend: [/master/protocol]\nretire: [/master/proceed]\n')
    def init_node(*args, **kwargs):   # past every check of its options (the code before: never a master here)
        raise AssertionError('adapt took the lease')
    monkeypatch.setattr(rospy, 'init_node', init_node)
    for lease in ('inf', '1e10', str(MAX_LEASE + 1)):
        with pytest.raises(SystemExit):
            adapt_command.main([str(script), '--lease', lease])
    with pytest.raises(ValueError, match='at most 600'):
        adaptation_engine.Engine(log=lambda t: None, lease=float('inf'), log_dir=str(tmp_path))
    monkeypatch.setattr(ros_ports, 'param', lambda name, convert, default: default)
    ports = ros_ports.Ports([PortSpec('inp', SUBSCRIBE, 'aft_msgs/Request')], {'inp': lambda msg: None})
    ports.suspension(['inp'])
    answer = ports._handle_suspend(SuspendRequest(timeout=1.0, lease=1e10, owner='adapt run 1'))
    assert not answer.success and 'at most 600' in answer.message
    assert ports.gate.state.name == 'OPEN'


# -- left by the review of session 48, fixed since ---------------------------------------------------

def test_the_monitors_history_of_notes_is_bounded_and_what_it_dropped_is_counted():
    """A site lost for good that goes on beating (fail-silence broken: its link came back) added a note at
    each heartbeat, 10 a second, for as long as the monitor ran: its memory grew without bound. The newest
    notes are kept, at most HISTORY_MAX, and the number dropped is said."""
    clock = review.FakeClock(100.0)
    core = MonitorCore(frozenset([CRASH]), review.DET_STATE, review.SITES, ('pbr',), clock.now,
                       lost_after=review.LOST_AFTER)
    review.Node(core, clock).run(1.0)
    for _ in range(int((review.LOST_AFTER + 0.5) / review.PERIOD)):   # the slave falls silent: lost
        clock.advance(review.PERIOD)
        core.heartbeat('master', clock.now)
        core.tick(clock.now)
    assert core.lost == {'slave'}
    for _ in range(5000):   # ... and beats again, for good
        clock.advance(review.PERIOD)
        assert core.heartbeat('slave', clock.now) is False
    assert len(core.history) <= 1000, len(core.history)
    assert 'lost for good: ignored' in core.history[-1][1] and core.history[-1][0] == clock.now   # the newest kept
    assert core.notes_dropped > 4000 and core.notes_dropped + len(core.history) > 5000


def _own_address():
    """An address of this machine other than a loopback one (the one it reaches others from), or None."""
    import socket
    for family, peer in ((socket.AF_INET, ('192.0.2.1', 9)), (socket.AF_INET6, ('2001:db8::1', 9))):
        try:
            with socket.socket(family, socket.SOCK_DGRAM) as s:
                s.connect(peer)   # UDP: nothing is sent, the kernel only picks the route's source address
                address = s.getsockname()[0]
        except OSError:
            continue
        if not address.startswith('127.') and address != '::1':
            return address
    return None


def test_two_adapt_runs_given_the_master_as_localhost_and_as_the_hosts_address_take_one_turn(tmp_path):
    import socket
    from aft_ftm.turns import Busy, Turn, master_key
    address = _own_address()
    if address is None:
        pytest.skip('this machine has no address but a loopback one')
    host = '[%s]' % address if ':' in address else address
    spellings = ['http://localhost:11311', 'http://%s:11311' % host, 'http://%s:11311/' % host,
                 'http://127.0.0.1:11311', 'http://[::1]:11311', 'HTTP://LocalHost:11311/', 'http://localhost',
                 'localhost:11311', 'http://%s:11311' % socket.gethostname()]
    keys = dict((s, master_key(s)) for s in spellings)
    assert len(set(keys.values())) == 1, keys
    assert master_key('http://%s:11312' % host) != master_key('http://localhost:11311')   # another master
    first = Turn('http://localhost:11311', str(tmp_path))
    first.take('adapt A', 1.0)
    try:
        with pytest.raises(Busy, match='adapt A'):
            Turn('http://%s:11311/' % host, str(tmp_path)).take('adapt B', 0.1)
    finally:
        first.give()


def test_a_master_whose_name_cannot_be_resolved_still_has_one_turn_under_its_name(tmp_path, capsys):
    from aft_ftm.turns import Busy, Turn, master_key
    name = 'http://aft-no-such-master.invalid:11311'   # .invalid never resolves (RFC 6761)
    assert master_key(name) == master_key(name.upper() + '/') == master_key('aft-no-such-master.invalid')
    assert master_key(name) != master_key('http://localhost:11311')
    first = Turn(name, str(tmp_path))
    assert first.take('adapt A', 1.0) < 1.0
    with pytest.raises(Busy, match='adapt A'):
        Turn(name + '/', str(tmp_path)).take('adapt B', 0.1)
    first.give()
    assert capsys.readouterr() == ('', '')   # nothing said: a name not resolvable here is no error


# A roslaunch whose node dies in its set-up (before it offers ~rebind) while the launch runs on: it is not
# required, so roslaunch says so and goes on.
LAUNCH_NODE_DIES = ('import time\n'
                    'print("process[site/tr/after-6]: started with pid [4242]", flush=True)\n'
                    'print("[FATAL] [1.0]: /site/tr/after: set-up failed, exiting", flush=True)\n'
                    'print("[site/tr/after-6] process has died [pid 4242, exit code 1, cmd after].", flush=True)\n'
                    'time.sleep(60)\n')


def _waiting_engine(tmp_path, launch_timeout, code, graph):
    """An Engine waiting for the node /site/tr/after of a launch running ``code`` (a real process
    printing what a roslaunch prints), the master's view faked as ``graph`` (nodes, services)."""
    import sys
    from aft_ftm.sites import Site
    e = adaptation_engine.Engine(log=lambda t: None, launch_timeout=launch_timeout, log_dir=str(tmp_path))
    site = Site('adaptation', [sys.executable, '-c', code], log_path=str(tmp_path / 'launch.log')).start()
    e._run_sites = [adaptation_engine.LaunchedSite(site, ['/site/tr/after'])]
    e._graph = lambda: graph
    e._wired = lambda node, silent=None: True
    return e, site


def test_a_launched_node_that_dies_before_offering_its_rebind_ends_the_wait_at_once(tmp_path):
    """Its roslaunch ran on (the node not required): the engine waited for its ~rebind until the launch
    timeout, a minute in which the adaptation's pause (paper order) or its turn (both) was held."""
    import time
    e, site = _waiting_engine(tmp_path, 8.0, LAUNCH_NODE_DIES, (set(), set()))
    try:
        t0 = time.monotonic()
        with pytest.raises(StepError) as failed:
            e._wait_launched()
        took = time.monotonic() - t0
    finally:
        site.stop(grace=1.0)
    assert took < 4.0, (took, str(failed.value))
    why = str(failed.value)
    assert '/site/tr/after' in why and 'exit code 1' in why and '/site/tr/after/rebind' in why, why
    assert 'set-up failed' in why and str(tmp_path / 'launch.log') in why, why


def test_a_launched_node_registered_without_its_rebind_is_named_with_the_missing_service(tmp_path):
    """A node that runs, registered with the master, and never offers ~rebind (not an FTM node, or one
    stuck in its set-up): the wait ends at the launch timeout (an FTM node offers ~rebind only once set
    up, which under load takes tens of seconds), and says which service never came."""
    e, site = _waiting_engine(tmp_path, 0.5, 'import time\ntime.sleep(60)\n',
                              ({'/site/tr/after'}, {'/site/tr/after/get_loggers'}))
    try:
        with pytest.raises(StepError) as failed:
            e._wait_launched()
    finally:
        site.stop(grace=1.0)
    why = str(failed.value)
    assert 'not set up within 0.5 s' in why and '/site/tr/after' in why, why
    assert 'registered with the master' in why and 'offers no /site/tr/after/rebind' in why, why


@pytest.mark.parametrize('output, ended', [
    ('[a/b-1] process has died [pid 7, exit code 1, cmd x].\n', {'/a/b': 'died (exit code 1)'}),
    ('[a/b-1] process has died [pid 7, exit code -9, cmd x].\n[a/b-1] restarting process\n', {}),   # respawn
    ('[a/b-2] process has finished cleanly\nlog file: /x/a-b-2*.log\n', {'/a/b': 'finished cleanly'}),
    ('REQUIRED process [a/b-1] has died!\n', {'/a/b': 'died'}),
    ('process[a/b-1]: started with pid [7]\n[INFO] [1.0]: /a/b: ready\n', {}),
])
def test_the_nodes_a_roslaunch_says_ended(output, ended):
    from aft_ftm.sites import nodes_ended
    assert nodes_ended(output) == ended
