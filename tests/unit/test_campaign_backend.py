"""The campaign's backends, without a ROS master or namespaces: the host-level one drives
aft_ftm.hosts_exec.Hosts as the schedule says (a fake Hosts records the calls); the adapting one runs
the shipped adaptation scripts with the names of the nodes running then."""
import os
import random
import time

import pytest

from aft_ftm import adaptation
from aft_examples.schedule import Fault
from aft_examples.ros.campaign import (INNER_NODES, CampaignDeployment, CampaignError, HostsBackend, ProcessBackend,
                                       adaptation_plan)


class FakeHosts(object):
    def __init__(self):
        self.calls = []

    def __getattr__(self, name):
        if name in ('partition', 'heal', 'rate', 'unrate', 'power_off'):
            return lambda *args: self.calls.append((name,) + args)
        raise AttributeError(name)


HOST_OF = {'master': 'h_master', 'slave': 'h_slave', 'witness': 'h_witness', 'proxy1': 'h_client'}


def fault(kind, target, duration=0.01):
    return Fault(0, 0, 'pbr', kind, target, duration, 0.0)


@pytest.mark.parametrize('kind,target,expected', [
    ('partition', 'primary', [('partition', 'h_slave'), ('heal', 'h_slave')]),
    ('partition_pair', 'client-witness', [('partition', 'h_client', 'h_witness'), ('heal', 'h_client', 'h_witness')]),
    ('partition_pair', 'primary-backup', [('partition', 'h_slave', 'h_master'), ('heal', 'h_slave', 'h_master')]),
    ('bandwidth', 'backup', [('rate', 'h_master', HostsBackend.RATE_KBIT), ('unrate', 'h_master')]),
    ('power_loss', 'primary', [('power_off', 'h_slave')]),
])
def test_host_faults_reach_the_hosts_of_the_roles_serving_now(kind, target, expected):
    hosts = FakeHosts()
    backend = HostsBackend(hosts, HOST_OF)
    roles = {'primary': 'slave', 'backup': 'master'}   # after a failover
    done = backend.inject(fault(kind, target), None, roles.get, random.Random(0))
    assert hosts.calls == expected
    assert done['end'] >= done['start'] and done['proxy_killed'] is None


def test_one_host_refuses_what_needs_hosts_by_name():
    assert 'hosts' not in ProcessBackend.offered and 'hosts' in HostsBackend.offered
    with pytest.raises(CampaignError, match='partition is not a fault of one host'):
        ProcessBackend().inject(fault('partition', 'primary'), None, {'primary': 'master'}.get, random.Random(0))


class FakeCore(object):
    log_path = '/nowhere/roscore.log'

    def __init__(self):
        self.calls = []

    def power_off(self):
        self.calls.append(('power_off', time.monotonic()))
        return 3

    def start(self):
        self.calls.append(('start', time.monotonic()))
        return self


def test_the_master_death_kills_the_roscore_keeps_it_down_then_starts_it_again(monkeypatch):
    import aft_examples.ros.campaign as campaign
    assert 'master' in ProcessBackend.offered and 'master' in campaign.AdaptingBackend.offered
    with pytest.raises(CampaignError, match='no roscore of its own'):
        ProcessBackend().inject(fault('kill', 'ros_master'), None, {}.get, random.Random(0))
    core = FakeCore()
    monkeypatch.setattr(campaign, 'master_answers', lambda timeout, caller: (True, ''))
    done = ProcessBackend(core).inject(fault('kill', 'ros_master', 0.2), None, {}.get, random.Random(0))
    assert [c[0] for c in core.calls] == ['power_off', 'start']
    assert core.calls[1][1] - core.calls[0][1] >= 0.2
    assert 'down 0.20 s' in done['what'] and '3 processes' in done['what'] and done['proxy_killed'] is None
    monkeypatch.setattr(campaign, 'master_answers', lambda timeout, caller: (False, 'refused'))
    monkeypatch.setattr(campaign, 'MASTER_PATIENCE', 0.1)
    with pytest.raises(CampaignError, match='did not answer within'):
        ProcessBackend(FakeCore()).inject(fault('kill', 'ros_master', 0.0), None, {}.get, random.Random(0))


# -- adaptations in the campaign: what each one is, given what the pair runs now ---------------------

SCRIPTS = os.path.join(os.path.dirname(__file__), '..', '..', 'catkin_ws', 'src', 'aft_ftm', 'adaptations')


def load(plan):
    with open(os.path.join(SCRIPTS, plan.script + '.yaml')) as f:
        return adaptation.load(f.read(), adaptation.parse_overrides(plan.overrides), source=plan.script)


def launched_graph(site, inner):
    """The nodes of a replica's mechanism its launch file starts (their graph names)."""
    stages = ['protocol', 'before', 'after'] + (['%s/%s' % (inner, n) for n in INNER_NODES] if inner else ['proceed'])
    return {'/%s/%s' % (site, n) for n in stages}


def new_nodes(script):
    """The nodes a script starts, as its bindings to topics name them."""
    return {b.node for b in script.bind if b.topic}


@pytest.mark.parametrize('seed', range(40))
def test_every_adaptation_names_the_nodes_running_then_whatever_came_before(seed):
    """Updates, switches, compositions, failovers and re-joins drawn from a seed: each script the
    campaign runs suspends, unbinds and retires only nodes that run, and afterwards the deployment
    names the nodes that run (what its faults then target)."""
    rng = random.Random(seed)
    deployment = CampaignDeployment('/tmp/unused', 'pbr', clients=2, seed=seed, adaptable=True)
    graph = launched_graph('master', '') | launched_graph('slave', '')
    primary, backup = 'master', 'slave'
    for index in range(30):
        step = rng.choice(['update', 'switch', 'compose', 'failover', 'rejoin'])
        if step == 'failover':
            primary, backup = backup, primary
            continue
        if step == 'rejoin':   # the backup failed and came back from its launch file
            deployment.comes_back(backup)
            args = deployment.launch[backup][2]
            assert (args['mechanism'], args['inner'], args['role']) == (deployment.mechanism, deployment.inner, 'backup')
            graph = {n for n in graph if not n.startswith('/%s/' % backup)} | launched_graph(backup, args['inner'])
            continue
        fault = Fault(index, 0, 'pbr', 'adapt', step, 0.0, 0.0)
        plan = adaptation_plan(fault, deployment, primary, backup)
        script = load(plan)
        if step == 'update':   # PBR or LFR: the new After of the mechanism that runs, beside the Before that runs
            launched = dict(script.launch[0].args)
            assert launched['mechanism'] == deployment.mechanism, (seed, index)
            assert '/%s/%s' % (primary, launched['before']) == deployment.node(primary, 'before'), (seed, index)
        touched = set(script.suspend) | set(script.retire) | {b.node for b in script.bind if not b.topic}
        assert touched <= graph, 'seed %d step %d %s: not running: %s' % (seed, index, plan.what, touched - graph)
        graph = (graph - set(script.retire)) | new_nodes(script)
        if step == 'compose' and not deployment.inner:
            graph |= {'/%s/tr/%s' % (site, n) for site in (primary, backup) for n in INNER_NODES} - new_nodes(script)
        plan.apply(deployment)
        for site in (primary, backup):
            for stage in ('before', 'after'):
                assert deployment.node(site, stage) in graph, (seed, index, plan.what)
            assert launched_graph(site, deployment.inner) - {'/%s/before' % site, '/%s/after' % site} <= graph


def test_an_update_switch_and_composition_are_described_by_what_they_change():
    deployment = CampaignDeployment('/tmp/unused', 'pbr', clients=2, adaptable=True)
    plan = adaptation_plan(Fault(4, 0, 'pbr', 'adapt', 'switch', 0.0, 0.0), deployment, 'slave', 'master')
    assert plan.script == 'switch' and 'to:=lfr' in plan.overrides and 'primary:=slave' in plan.overrides
    plan.apply(deployment)
    assert deployment.shape() == 'lfr' and deployment.node('master', 'after') == '/master/after_lfr4'
    plan = adaptation_plan(Fault(5, 0, 'pbr', 'adapt', 'compose', 0.0, 0.0), deployment, 'slave', 'master')
    assert plan.script == 'compose' and 'server_timeout:=1.0' in plan.overrides
    plan.apply(deployment)
    assert deployment.shape() == 'lfr+tr'
    plan = adaptation_plan(Fault(6, 0, 'pbr', 'adapt', 'compose', 0.0, 0.0), deployment, 'slave', 'master')
    assert plan.script == 'decompose' and plan.what == 'decompose lfr+tr -> lfr'
    with pytest.raises(CampaignError, match='not offered'):
        adaptation_plan(Fault(7, 0, 'pbr', 'adapt', 'rewrite', 0.0, 0.0), deployment, 'slave', 'master')


class UpSite(object):
    proc = object()

    def failure(self, ignore=()):
        return None


class FakeMaster(object):
    offered = set()

    def __init__(self, caller_id):
        pass

    def lookupService(self, name):
        if name not in self.offered:
            raise Exception('no provider')
        return 'rosrpc://x:1'


def test_a_relaunched_proxy_counts_once_its_service_is_offered_not_once_its_roslaunch_runs(monkeypatch):
    """Seed 2411, fault 92: the heal of a killed Proxy saw its roslaunch run and went on; the master
    was then killed before the Proxy had read its parameters, and it died of it."""
    import aft_examples.ros.campaign as campaign

    class Deployment(object):
        sites = {'master': UpSite(), 'slave': UpSite(), 'proxy1': UpSite(), 'proxy2': UpSite(), 'client1': UpSite()}
        retired = {}

        def shape_problem(self, site, master):
            return None

    class Status(object):
        epoch, primary, backup = 3, 'master', 'slave'
    monkeypatch.setattr(campaign, 'witness_status', lambda: Status)
    monkeypatch.setattr(campaign.rosgraph, 'Master', FakeMaster)
    FakeMaster.offered = {'/account2'}
    assert campaign.whole(Deployment()) == 'proxy1 does not offer /account1 yet'
    FakeMaster.offered = {'/account1', '/account2'}
    assert campaign.whole(Deployment()) is None


def test_a_fault_whose_role_no_site_plays_now_is_not_injected_rather_than_a_crash(monkeypatch):
    """The 1000-fault hosts run (seed 2611) died at fault 690: the witness named no backup at the moment a
    backup fault came, and the runner looked up site ''. Such a fault is recorded not injected, naming
    the witness's configuration, and nothing is touched."""
    import types
    from aft_examples import schedule
    from aft_examples.ros import campaign
    monkeypatch.setattr(campaign, 'witness_status',
                        lambda *a, **k: types.SimpleNamespace(epoch=7, primary='master', backup=''))
    # The pair was seen whole (the backup excluded just after: heal first is the next test's).
    monkeypatch.setattr(campaign, 'whole', lambda deployment: None)
    touched = []

    class Deployment(object):
        sites = {'master': object()}

        def shape(self):
            return 'pbr'

        def node(self, site, name):
            touched.append((site, name))

        def __getattr__(self, name):
            touched.append(name)
            raise AssertionError('the deployment was touched: %s' % name)
    segment = campaign.Segment([], '/nonexistent', campaign.ProcessBackend(), log=lambda *a: None)
    for kind, target in (('power_loss', 'backup'), ('kill', 'backup/after'), ('freeze_site', 'backup')):
        fault = schedule.Fault(index=690, segment=27, mechanism='pbr', kind=kind, target=target, duration=0.1,
                               gap=0.0)
        record = segment._one(fault, Deployment(), random.Random(1))
        assert record['outcome'] == 'not_injected', record
        assert "no site is the backup now (witness: epoch 7, primary 'master', backup '')" in record['what']
    assert not touched


def test_a_pair_not_whole_when_a_fault_comes_is_healed_before_it_and_never_hit_twice(monkeypatch):
    """Test campaign seed 26369: a freeze of the backup absorbed, its exclusion came after the heal had
    looked; a kill of the lone primary's Proceed 0.2 s later lost the only state. A fault now comes
    only once the pair is whole again; one that cannot be healed ends the segment, not injected."""
    import types
    from aft_examples import schedule
    from aft_examples.ros import campaign
    healed = []
    monkeypatch.setattr(campaign, 'whole', lambda deployment: 'the pair is not whole')
    monkeypatch.setattr(campaign, 'witness_status',
                        lambda *a, **k: types.SimpleNamespace(epoch=9, primary='slave', backup=''))
    monkeypatch.setattr(campaign, 'heal', lambda *a, **k: healed.append(a) or ([], 'still not whole'))

    class Backend(campaign.ProcessBackend):
        def inject(self, *args):
            raise AssertionError('a fault was injected into a pair that is not whole')

    class Deployment(object):
        def shape(self):
            return 'pbr'
    segment = campaign.Segment([], '/nonexistent', Backend(), log=lambda *a: None)
    fault = schedule.Fault(index=6, segment=0, mechanism='pbr', kind='kill', target='primary/proceed', duration=0.0,
                           gap=0.0)
    record = segment._one(fault, Deployment(), random.Random(1))
    assert len(healed) == 1 and record['outcome'] == 'unhealed: still not whole', record


def test_heal_powers_off_no_site_while_the_witness_cannot_be_asked(monkeypatch):
    """Seed 15, segment 20: the ROS master did not answer in a 10 s stall; heal read 'nobody is primary'
    from that silence and powered off the fail-stopped site the witness named primary (with the only
    state). While witness_status() is None, heal judges nothing; once it answers, it acts on what it says."""
    import types
    from aft_examples.ros import campaign
    answers = [None] * 5 + [types.SimpleNamespace(epoch=11, primary='slave', backup='')] * 3
    monkeypatch.setattr(campaign, 'SETTLE', 0.0)
    monkeypatch.setattr(campaign.time, 'sleep', lambda s: None)
    monkeypatch.setattr(campaign, 'witness_status', lambda: answers.pop(0) if len(answers) > 1 else answers[0])
    monkeypatch.setattr(campaign, 'whole', lambda deployment: None if not answers[:-1] else 'not whole')
    powered_off = []

    class Site(object):
        def __init__(self, name):
            self.name = name

        def alive(self):
            return True

        def power_off(self):
            powered_off.append((self.name, len(answers)))

    class Deployment(object):
        sites = {'master': Site('master'), 'slave': Site('slave')}
    monkeypatch.setattr(campaign, '_down', lambda deployment, name: False)
    fail_stopped = {'master': 10.0, 'slave': 10.0}   # both said they fail-stopped
    campaign.heal(Deployment(), log=lambda *a: None, fail_stopped=fail_stopped)
    # Nothing while the witness was unknown; then master only (slave is the witness's primary).
    assert powered_off and all(name == 'master' for name, _ in powered_off), powered_off
    assert all(left <= 3 for _, left in powered_off), powered_off


class ProceedDiedSite(UpSite):
    """A replica site whose roslaunch printed that /master/proceed died (exit code -9)."""

    def failure(self, ignore=()):
        return None if '/master/proceed' in ignore else 'site master: /master/proceed died (exit code -9)'


def test_a_node_an_adaptation_killed_is_no_failure_of_its_site_but_any_other_death_is(monkeypatch, tmp_path):
    """Seed 36054: a compose's kill step had to SIGKILL the old Proceeds (the ROS master did not
    answer their unregistration); the heal took both replica sites for down and relaunched them,
    the new primary among them, and its state was lost."""
    import aft_examples.ros.campaign as campaign
    deployment = campaign.CampaignDeployment(str(tmp_path), adaptable=True)
    deployment.sites = {'master': ProceedDiedSite(), 'slave': UpSite(), 'proxy1': UpSite(), 'proxy2': UpSite()}
    monkeypatch.setattr(deployment, 'shape_problem', lambda site, master: None)

    class Status(object):
        epoch, primary, backup = 5, 'slave', 'master'
    monkeypatch.setattr(campaign, 'witness_status', lambda: Status)
    monkeypatch.setattr(campaign.rosgraph, 'Master', FakeMaster)
    FakeMaster.offered = {'/account1', '/account2'}
    assert campaign.whole(deployment) == 'site master: /master/proceed died (exit code -9)'
    deployment.retire('/slave/proceed')   # another site's node: master's death still counts
    assert campaign.whole(deployment) == 'site master: /master/proceed died (exit code -9)'
    deployment.retire('/master/proceed')
    assert campaign.whole(deployment) is None
    assert deployment.retired == {'master': {'/master/proceed'}, 'slave': {'/slave/proceed'}}


def test_a_segment_that_cannot_start_is_started_afresh_up_to_its_tries_each_said(monkeypatch):
    """A clean-clone CI (session 46): a 30 ms detector suspected MASTER while it started, the witness
    deposed it before the clients were up, twice in a row, and the quick campaign failed. A segment's
    start is now tried in START_TRIES fresh deployments, each in a directory of its own, each failure
    said; the last one's error is raised, and every deployment is torn down."""
    from aft_examples import schedule
    from aft_examples.ros import campaign
    made, said = [], []

    class Deployment(object):
        def __init__(self, log_dir):
            self.log_dir, self.torn = log_dir, 0

        def start(self):
            raise campaign.CampaignError('site master exited (code -9) while starting (%s)' % self.log_dir)

        def teardown(self):
            self.torn += 1

    class Backend(campaign.ProcessBackend):
        def deployment(self, log_dir, *args):
            made.append(Deployment(log_dir))
            return made[-1]
    fault = schedule.Fault(index=0, segment=1, mechanism='pbr', kind='kill', target='primary/proceed', duration=0.0,
                           gap=0.0)
    segment = campaign.Segment([fault], '/nonexistent/segment1', Backend(), log=said.append)
    segment.SETTLE_LIMIT = 0.0   # (one second's CPU reading before each new start)
    with pytest.raises(campaign.CampaignError, match='segment1.3'):
        segment._run()
    assert [d.log_dir for d in made] == ['/nonexistent/segment1', '/nonexistent/segment1.2', '/nonexistent/segment1.3']
    assert all(d.torn >= 1 for d in made)
    assert [s.split(' failed')[0] for s in said if 'CPU' not in s] == ['segment 1: start 1 of 3',
                                                                       'segment 1: start 2 of 3']
    assert len([s for s in said if s.startswith('segment 1: CPU ')]) == 2
