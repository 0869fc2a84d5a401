"""The Adaptation Engine's pause against what others do meanwhile (review of stop 39): the real Engine,
Transaction and LeaseKeeper, and each node's real suspension handlers (aft_ftm.ros.ports.Ports), with
the ROS calls faked (no master, no process started or signalled).

- a node resumed by someone else, or by itself (its lease ran out), in the middle of the rebinds: the
  engine resumed the rest and reported success; now nothing is resumed and the adaptation is rolled
  back while the others are still paused;
- one site's resume failing beside another's that succeeded: the rollback rebound the serving site;
  now the adaptation stands, and the failure is reported with an alarm;
- a node hanging in its answer: the pause lasted for ever; now the call is abandoned past its bound;
- a log line that cannot be written: it abandoned the transaction half-way.
"""
import threading
import time
import types

import pytest
import rospy
from aft_msgs.srv import SuspendRequest

from aft_ftm import adaptation
from aft_ftm.ports import SUBSCRIBE, PortSpec
from aft_ftm.ros import adaptation_engine, ports as ros_ports
from aft_ftm.suspension import GateState, SuspendError

import adaptation_scripts


class Graph(object):
    """The nodes a compose adaptation touches, each a real Ports with its suspension gate, and what
    each service call does (``hooks``: service name -> callable run before the node answers)."""

    def __init__(self):
        self.nodes = {}
        self.hooks = {}
        self.rebinds = []    # (node, 'bind topic' | 'unbind', state of that site's Protocol gate then)

    def node(self, name):
        if name not in self.nodes:
            ports = ros_ports.Ports([PortSpec('inp', SUBSCRIBE, 'aft_msgs/Request')], {'inp': lambda msg: None})
            ports.suspension(['inp'])
            self.nodes[name] = ports
        return self.nodes[name]

    def gate(self, name):
        return self.node(name).gate

    def proxy(self, name, _cls=None):
        graph = self

        class Proxy(object):
            transport = None

            def __call__(self, **kw):
                hook = graph.hooks.get(name)
                if hook is not None:
                    hook(kw)
                node, service = name.rsplit('/', 1)
                if service == 'suspend':
                    return graph.node(node)._handle_suspend(SuspendRequest(**kw))
                if service == 'resume':
                    return graph.node(node)._handle_resume(SuspendRequest(**kw))
                if service == 'rebind':
                    site = node.strip('/').split('/')[0]
                    graph.rebinds.append((node, 'bind %s' % kw['topic'] if kw['activate'] else 'unbind',
                                          graph.gate('/%s/protocol' % site).state))
                    return types.SimpleNamespace(success=True, message='ok',
                                                 previous_topic='' if kw['activate'] else '/%s/bfr2prd' % site)
                raise ValueError(name)

            def close(self):
                pass
        return Proxy()


class FakeLaunch(object):
    def __init__(self):
        self.stopped = False
        self.pid = 4194304 + 1   # above any pid_max: never a process of this machine
        self.nodes = []

    def alive(self):
        return False

    def stop(self, grace=5.0):
        self.stopped = True


@pytest.fixture
def graph(monkeypatch):
    graph = Graph()
    monkeypatch.setattr(ros_ports, 'param', lambda name, convert, default: default)
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))   # a self-resume's alarm stamp
    monkeypatch.setattr(adaptation_engine.rospy, 'ServiceProxy', lambda name, cls, persistent=False: graph.proxy(name))

    def nothing_started(*args, **kwargs):
        raise AssertionError('a test of the pause starts no process')
    monkeypatch.setattr(adaptation_engine, 'Site', nothing_started)
    monkeypatch.setattr(adaptation_engine, 'run_where', nothing_started)
    yield graph
    for hook in graph.hooks.values():
        release = getattr(hook, 'release', None)
        if release is not None:
            release()


def engine(graph, log=None, **kwargs):
    engine = adaptation_engine.Engine(log=log or (lambda text: None), quiesce_timeout=1.0, **kwargs)
    engine.validate = lambda script, mode: adaptation.plan(script, mode)
    engine._proxy = lambda name, cls: graph.proxy(name, cls)
    engine._connect = lambda steps: None
    engine.launched = []

    def launch(entry):
        site = FakeLaunch()
        engine.launched.append(site)
        return site
    engine._launch = launch
    engine._wait_launched = lambda: 0
    engine._kill = lambda node, prepared=None: adaptation_engine.Killed(2, [], '/', {}, [])
    engine._kill_record = lambda node: (None, adaptation_engine.Killed(2, [], '/', {}, []))
    return engine


def compose():
    return adaptation.load(adaptation_scripts.COMPOSE)


def test_a_node_resumed_by_someone_else_during_the_rebinds_fails_the_adaptation_before_any_resume(graph):
    seen = {}

    def operator_resumes(kw):   # an operator, or another engine's rollback: no owner named
        graph.node('/master/protocol')._handle_resume(SuspendRequest())
        seen['master'] = graph.gate('/master/protocol').state
    graph.hooks['/master/proceed/rebind'] = operator_resumes
    report = engine(graph).run(compose(), 'prepared')
    assert seen['master'] == GateState.OPEN
    assert not report['ok'] and report['rolled_back'], report
    assert 'the pause was broken' in report['error'] and '/master/protocol' in report['error'], report['error']
    # Nothing was resumed by the failed group: the rollback's rebinds ran with the slave still paused.
    assert not [r for r in report['steps'] if r['action'] == 'resume' and r['ok']]
    slave = [r for r in graph.rebinds if r[0].startswith('/slave/')]
    assert slave and all(state == GateState.CLOSED for _, _, state in slave), slave
    assert graph.gate('/slave/protocol').state == GateState.OPEN   # resumed by the rollback at the end


def test_a_lease_run_out_while_the_engine_was_stopped_fails_the_adaptation(graph):
    def engine_stopped_past_the_lease(kw):
        graph.gate('/slave/protocol').expire(time.monotonic() + 3600.0)
    graph.hooks['/slave/tr/protocol/rebind'] = engine_stopped_past_the_lease
    report = engine(graph).run(compose(), 'prepared')
    assert not report['ok'] and report['rolled_back'] and 'the pause was broken' in report['error'], report


def test_another_owner_can_neither_suspend_renew_nor_resume_a_suspended_node(graph):
    ports = graph.node('/n')
    mine = ports._handle_suspend(SuspendRequest(timeout=1.0, lease=5.0, owner='engine A'))
    assert mine.success
    theirs = ports._handle_suspend(SuspendRequest(timeout=1.0, lease=5.0, owner='engine B'))
    assert not theirs.success and 'suspended by engine A' in theirs.message
    assert not ports._handle_suspend(SuspendRequest(renew=True, lease=5.0, owner='engine B')).success
    refused = ports._handle_resume(SuspendRequest(owner='engine B'))
    assert not refused.success and ports.gate.state == GateState.CLOSED
    assert ports._handle_suspend(SuspendRequest(renew=True, lease=5.0, owner='engine A')).success
    assert ports._handle_resume(SuspendRequest(owner='engine A')).success
    # The owner's resume of a node no longer suspended is refused: the pause it relied on was broken.
    late = ports._handle_resume(SuspendRequest(owner='engine A'))
    assert not late.success and late.message.startswith(ros_ports.NOT_SUSPENDED)
    # Without an owner (an operator), as before: harmless, said.
    assert ports._handle_resume(SuspendRequest()).success


def test_the_gate_keeps_its_owner_until_it_opens():
    from aft_ftm.suspension import Gate
    gate = Gate({'inp': lambda msg: None})
    gate.close(['inp'], lambda: True, 1.0, lease=5.0, owner='a')
    assert gate.suspended_by('a') and not gate.suspended_by('b')
    with pytest.raises(SuspendError, match='suspended by a'):
        gate.open('b')
    gate.open('a')
    assert gate.owner == '' and not gate.suspended_by('a')
    gate.close(['inp'], lambda: True, 1.0, lease=5.0, owner='b')    # anyone may suspend it again
    assert gate.suspended_by('b')


def test_a_resume_failing_beside_one_that_succeeded_leaves_the_adaptation_standing_and_says_so(graph):
    def master_site_dies(kw):
        raise rospy.ServiceException('transport error completing service call: connection reset')
    graph.hooks['/master/protocol/resume'] = master_site_dies
    report = engine(graph).run(compose(), 'prepared')
    # It stands (a monitor or a campaign goes on from the new configuration), and the alarm says what failed.
    assert report['state'] == 'DONE' and report['ok'] and not report['rolled_back'], report
    assert report['resume_errors'] and '/master/protocol' in report['resume_errors'][0]
    assert 'the new configuration serves' in report['alarm']
    # The serving slave was not rebound after its resume.
    assert not [r for r in graph.rebinds if r[0].startswith('/slave/') and r[2] == GateState.OPEN], graph.rebinds
    assert graph.gate('/slave/protocol').state == GateState.OPEN


def test_a_node_hanging_in_its_answer_holds_the_pause_only_for_the_calls_bound(graph):
    released = threading.Event()

    def hangs(kw):
        released.wait(30.0)
    hangs.release = released.set
    graph.hooks['/slave/tr/protocol/rebind'] = hangs
    e = engine(graph, service_timeout=0.2, connect_timeout=0.1)
    t0 = time.monotonic()
    report = e.run(compose(), 'prepared')
    took = time.monotonic() - t0
    assert not report['ok'] and report['rolled_back'], report
    assert 'did not answer its rebind within 0.5 s' in report['error'], report['error']
    # The abandoned rebind may still be carried out: its undo is asked for and, what it replaced being
    # unknown, fails saying so (the rollback FAILED, with an alarm naming the node); every node is resumed.
    assert report['state'] == 'FAILED' and '/slave/tr/protocol' in report['alarm'] and 'by hand' in report['alarm']
    assert took < 5.0, took
    assert all(graph.gate(n).state == GateState.OPEN for n in ('/master/protocol', '/slave/protocol'))


def test_a_log_that_cannot_be_written_abandons_nothing(graph):
    def log(text):
        if text.startswith('step resume'):
            raise BrokenPipeError(32, 'Broken pipe')   # `adapt ... | head`, an ssh session gone
    report = engine(graph, log=log).run(compose(), 'prepared')
    assert report['ok'] and report['state'] == 'DONE', report
    assert all(graph.gate(n).state == GateState.OPEN for n in ('/master/protocol', '/slave/protocol'))


def test_a_rollback_stops_its_launches_through_the_site_never_by_a_bare_pid(graph, monkeypatch):
    signalled = []
    monkeypatch.setattr(adaptation_engine, 'terminate_tree', lambda pid, grace=5.0: signalled.append(pid),
                        raising=False)

    def refused(kw):
        raise rospy.ServiceException('refused')
    graph.hooks['/slave/tr/protocol/rebind'] = refused
    e = engine(graph)
    report = e.run(compose(), 'prepared')
    assert report['rolled_back'] and e.launched and all(site.stopped for site in e.launched)
    assert signalled == []


def test_a_node_resumed_then_suspended_again_by_nobody_named_is_not_taken_for_paused(graph):
    """A join's quiescence (or an operator) resumes the Protocol and suspends it again, owner-less, in the
    middle of the rebinds: it ran meanwhile. The owner's renewal must not take that suspension for its own."""
    def join_quiesces(kw):
        protocol = graph.node('/slave/protocol')
        protocol._handle_resume(SuspendRequest())
        protocol._handle_suspend(SuspendRequest(timeout=1.0, lease=5.0))
    graph.hooks['/slave/tr/protocol/rebind'] = join_quiesces
    report = engine(graph).run(compose(), 'prepared')
    assert not report['ok'] and report['rolled_back'] and 'the pause was broken' in report['error'], report


def test_the_probes_before_the_pause_are_bounded_too(graph):
    """Review of the monitor (session 33): the connections opened before the pause (a probe of each
    node to suspend, a dry-run rebind) waited for a hung node for ever; the monitor, which runs the
    engine, then acted on nothing more (a site lost meanwhile was never answered)."""
    released = threading.Event()

    def hangs(kw):
        released.wait(30.0)
    hangs.release = released.set
    graph.hooks['/slave/protocol/suspend'] = hangs
    e = engine(graph, service_timeout=0.2)
    e._keeper = adaptation_engine.LeaseKeeper(5.0, lambda text: None)
    e._graph_nodes = lambda: set()
    steps = adaptation.plan(compose(), 'prepared')
    t0 = time.monotonic()
    adaptation_engine.Engine._connect(e, steps)
    assert time.monotonic() - t0 < 3.0


def test_the_monitors_shutdown_leaves_what_a_finished_adaptation_put_in_place_running(graph):
    """Review of session 35: the monitor's shutdown (an operator restarting it) called stop_all, which
    stopped every launch of the engine's runs, done ones too: the TR a composition put in place was
    killed under both sites, whose guards, asked to stop, did not fail-stop them. Both heartbeated on
    while every request hung. A run done leaves its launches to the sites; shutdown stops only those
    of a run that did not finish. (stop_all, for tests and benchmarks tearing everything down, still
    stops them all.)"""
    eng = engine(graph)

    def launch(entry):   # as the real one: the launch is the run's and the engine's
        site = FakeLaunch()
        eng.launched.append(site)
        eng.sites.append(site)
        eng._run_sites.append(site)
        return site
    eng._launch = launch
    report = eng.run(compose(), 'prepared')
    assert report['ok'] and eng.launched, report
    eng.shutdown(wait=0.1)
    assert not any(site.stopped for site in eng.launched) and eng.committed == eng.launched
    eng.stop_all()
    assert all(site.stopped for site in eng.launched)


def test_a_step_whose_clean_up_of_connections_fails_still_has_its_outcome_and_the_run_rolls_back(graph):
    """Review of session 35: in a group run in threads, a failed step's clean-up of its connections
    could raise (the shared table changed under it); its outcome was then missing, the run raised
    AttributeError, and nothing was rolled back."""
    eng = engine(graph)

    def broken(node, cut=False):
        raise RuntimeError('dictionary changed size during iteration')
    eng._forget_proxies = broken

    def refuse(kw):
        raise rospy.ServiceException('the node went away')
    graph.hooks['/master/proceed/rebind'] = refuse
    report = eng.run(compose(), 'prepared')
    assert not report['ok'] and report['rolled_back'] and 'the node went away' in report['error'], report


def test_last_resumes_whose_answers_are_lost_but_that_resumed_the_nodes_let_the_adaptation_stand(graph):
    """Review of session 35: a last resume whose answer came too late (a stalled engine, a large held
    buffer delivered before the answer) was taken as not done; with every site's resume so, the
    rollback rebound sites already serving in the new configuration and stopped its nodes with
    requests inside. The gate is asked over a new connection: open, the resume stands, said."""
    released = threading.Event()

    def resumes_then_hangs(node):
        def hook(kw):
            if kw.get('probe'):
                return
            graph.node(node)._handle_resume(SuspendRequest(**kw))   # the node resumes...
            released.wait(30.0)                                       # ...and its answer never comes
        hook.release = released.set
        return hook
    for site in ('master', 'slave'):
        graph.hooks['/%s/protocol/resume' % site] = resumes_then_hangs('/%s/protocol' % site)
    e = engine(graph, service_timeout=0.2, connect_timeout=0.1)
    report = e.run(compose(), 'prepared')
    assert report['ok'] and report['state'] == 'DONE' and not report['rolled_back'], report
    resumes = [r for r in report['steps'] if r['action'] == 'resume']
    assert resumes and all(r['ok'] and 'its gate says OPEN: resumed' in str(r['detail']) for r in resumes), resumes
    assert all(graph.gate(n).state == GateState.OPEN for n in ('/master/protocol', '/slave/protocol'))
    released.set()


def test_last_resumes_whose_answers_are_lost_and_that_did_not_resume_are_rolled_back(graph):
    """The control of the test above: the gate still closed (the resume never reached the node), the
    step stays failed and the adaptation is rolled back, every node resumed by the rollback."""
    released = threading.Event()

    def hangs(kw):
        if not kw.get('probe'):
            released.wait(30.0)
    hangs.release = released.set
    for site in ('master', 'slave'):
        graph.hooks['/%s/protocol/resume' % site] = hangs
    report = engine(graph, service_timeout=0.2, connect_timeout=0.1).run(compose(), 'prepared')
    released.set()
    assert not report['ok'] and report['rolled_back'] and 'did not answer its resume' in report['error'], report


def test_every_node_of_a_kill_group_is_recorded_before_any_is_signalled_and_nothing_raises_after_the_signal(
        graph, monkeypatch):
    """Review of session 35: the nodes of one required launch go down together; a node recorded after
    another's kill was found dead, its kill "failed" with no record, and the rollback did not start it
    again (while reporting ROLLED_BACK). A failure after the signal (the master not answering) lost
    the record the same way. Now the group is recorded first, and a kill never raises once signalled."""
    import subprocess
    import sys
    import psutil
    eng = engine(graph)
    order = []
    eng._kill_record = lambda node: order.append(('record', node)) or (None, node + ' record')
    eng._kill = lambda node, prepared=None: order.append(('kill', node, prepared[1]))
    steps = [adaptation.Step('kill', '/master/tr/a', None), adaptation.Step('kill', '/master/tr/b', None)]
    outcomes = eng._run_group(steps)
    assert all(o.error is None for o in outcomes)
    assert order[:2] == [('record', '/master/tr/a'), ('record', '/master/tr/b')]
    assert sorted(order[2:]) == [('kill', '/master/tr/a', '/master/tr/a record'),
                                 ('kill', '/master/tr/b', '/master/tr/b record')]
    # the real kill: signalled, then the master does not answer: killed all the same, record returned
    eng = engine(graph)
    del eng._kill
    monkeypatch.setattr(adaptation_engine, 'mark_retired', lambda pid: None)
    monkeypatch.setattr(adaptation_engine, 'disarm_guard_of', lambda pid: None)

    def no_master():
        raise OSError(111, 'Connection refused')
    eng._graph = no_master
    eng._keeper = types.SimpleNamespace(release=lambda node: None)
    victim = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])
    try:
        record = adaptation_engine.Killed(victim.pid, [], '/', {}, [])
        assert eng._kill('/master/tr/a', (psutil.Process(victim.pid), record)) is record
        assert victim.wait(5.0) is not None
    finally:
        if victim.poll() is None:
            victim.kill()
            victim.wait()



class FakeMaster(object):
    """The master's graph as a compose sees it: each site's Before publishes its bfr2prd, the Proceed
    and the TR's Protocol just launched subscribe (or not yet)."""

    def getSystemState(self):
        pubs = [('/master/bfr2prd', ['/master/before']), ('/slave/bfr2prd', ['/slave/before'])]
        subs = [('/master/bfr2prd', ['/master/proceed']), ('/slave/bfr2prd', ['/slave/proceed'])]
        return pubs, subs, []


def checking_engine(graph, monkeypatch):
    monkeypatch.setattr(adaptation_engine.Engine, 'master', property(lambda self: FakeMaster()))
    checked = engine(graph)

    def validate(script, mode):
        checked._script = script
        return adaptation.plan(script, mode)
    checked.validate = validate
    return checked


def test_a_bind_to_a_topic_nobody_publishes_is_rolled_back_before_any_port_moves(graph, monkeypatch):
    """A misspelt topic in a bind: the run said it succeeded, and every request was lost until the
    Protocol's backstop fail-stopped the site 30 s later (review of session 35)."""
    script = adaptation.load(adaptation_scripts.COMPOSE.replace('/$(arg site)/bfr2prd', '/$(arg site)/bfr2pdr'))
    report = checking_engine(graph, monkeypatch).run(script, 'prepared')
    assert not report['ok'] and report['rolled_back'], report
    assert '/master/tr/protocol.requests would be bound to /master/bfr2pdr, which no node publishes' in report['error']
    assert graph.rebinds == [], 'a port moved: %s' % graph.rebinds
    assert graph.gate('/master/protocol').state == GateState.OPEN and graph.gate('/slave/protocol').state == GateState.OPEN


def test_the_same_bind_to_the_published_topic_goes_through(graph, monkeypatch):
    report = checking_engine(graph, monkeypatch).run(compose(), 'prepared')
    assert report['ok'], report
    assert ('/master/tr/protocol', 'bind /master/bfr2prd') in [r[:2] for r in graph.rebinds], graph.rebinds


def test_an_engine_waits_its_turn_behind_another_adaptation_of_the_same_master(graph):
    """Review of session 35: two engines (the monitor's and an operator's) did not take turns."""
    import rosgraph
    from aft_ftm.turns import Turn
    other = Turn(rosgraph.get_master_uri())
    other.take('pid 4242, /aft_adapt_operator, running switch', 1.0)
    try:
        with pytest.raises(adaptation.ScriptError, match='/aft_adapt_operator, running switch'):
            engine(graph, turn_timeout=0.3).run(compose(), 'prepared')
        assert graph.rebinds == [] and all(n.gate.state == GateState.OPEN for n in graph.nodes.values())
        threading.Timer(0.3, other.give).start()   # the other one ends: this one goes
        report = engine(graph, turn_timeout=10.0).run(compose(), 'prepared')
        assert report['ok'] and report['waited_turn_s'] >= 0.2, report
    finally:
        other.give()
