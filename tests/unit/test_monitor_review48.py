"""The Monitoring and Adaptation Engines' fixes of the review of session 48, each failing on the code
before it: a hold that overflowed after 1 024 failures, an older witness configuration that brought a
lost site back, a retired node left running unsaid, and leases without a bound. No master."""
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
