"""The Monitoring Engine's review (M1, M2, M8): decisions only to targets a shipped script reaches,
sites not lost for the monitor's own stalls or a late start, and alarms for what it cannot fix.
The core with a fake clock, no ROS; the node's alarm glue with fake publishers, no master."""
import queue
import threading
import time

import pytest
import rospy

from aft_ftm.adaptation import ScriptError
from aft_ftm.change_model import Application, ChangeModel, Resources, consistent, select
from aft_ftm.mechanisms import CRASH, SAFETY_VIOLATION, TAMPERING, TRANSIENT_VALUE
from aft_ftm.errors import ConfigError
from aft_ftm.monitor import MonitorCore, MonitorState, transition
from fakes import FakeClock, FakePublisher

# The kinds of the monitor's alarms (aft_msgs/Alarm.kind, mechanism 'monitor'), as operators filter them.
ADAPTATION_FAILED, ROLLBACK_FAILED, ADAPTATION_INCOMPLETE = 'adaptation_failed', 'rollback_failed', 'adaptation_incomplete'
DEGRADED, NO_MECHANISM_FITS = 'degraded', 'no_mechanism_fits'

SITES = ['master', 'slave']
DET_STATE = Application(deterministic=True, state_access=True)
LOST_AFTER = 2.0
PERIOD = 0.1   # the node's ~period


def monitor(running=('pbr',), faults=(CRASH,), application=DET_STATE, start=100.0):
    """A monitor as monitor.launch starts it by default (pbr, deterministic, state access, F=[crash])."""
    clock = FakeClock(start)
    return MonitorCore(frozenset(faults), application, SITES, running, clock.now, lost_after=LOST_AFTER), clock


def reachable(from_, to, alive):
    """Whether a shipped script carries out from_ -> to."""
    try:
        transition(from_, to, alive)
    except ConfigError:
        return False
    return True


class Node(object):
    """What monitor_node does with the core, without ROS: beats, ticks, carries decisions out with the
    script transition() names (a ConfigError there is the node's adaptation_failed)."""

    def __init__(self, core, clock, alarms=False):
        self.core, self.clock, self.collect = core, clock, alarms
        self.decisions, self.scripts, self.alarms = [], [], []

    def run(self, seconds, sites=SITES, beat_every=PERIOD):
        beats = max(1, int(round(beat_every / PERIOD)))
        for i in range(int(round(seconds / PERIOD))):
            self.clock.advance(PERIOD)
            if i % beats == 0:
                for site in sites:
                    self.core.heartbeat(site, self.clock.now)
            self.tick()

    def tick(self):
        decision = self.core.decide(self.clock.now)
        if decision is not None:
            self.decisions.append(decision)
            try:
                move = transition(decision.from_, decision.to, self.core.alive_sites())
            except Exception as e:
                self.core.adaptation_failed(str(e), self.clock.now)
            else:
                self.scripts.append((move.script, move.overrides))
                self.core.adapted(decision.to, self.clock.now)
        if self.collect:
            self.alarms.extend(self.core.take_alarms())


# -- M1: a decision names a target a shipped script reaches ----------------------------------------
@pytest.mark.parametrize('mechanism,kind,fault,to', [
    ('tr', 'value_fault_masked', TRANSIENT_VALUE, ('pbr', 'tr')),
    ('tr', 'no_majority', TRANSIENT_VALUE, ('pbr', 'tr')),
    ('ad', 'assertion_violated', SAFETY_VIOLATION, ('pbr', 'ad')),
])
def test_an_alarm_under_pbr_composes_the_mechanism_onto_pbr_and_is_carried_out(mechanism, kind, fault, to):
    core, clock = monitor()
    node = Node(core, clock)
    node.run(1.0)
    assert core.alarm(mechanism, kind, clock.now) == fault
    node.run(60.0)
    assert [(d.from_, d.to) for d in node.decisions] == [(('pbr',), to)]
    assert node.scripts == [('compose', ['mechanism:=%s' % to[1], 'site:=master,slave'])]
    assert core.state == MonitorState.WATCHING and core.running == to
    assert consistent(core.running, core.model())[0]


def test_every_decision_is_reachable_from_the_running_composition():
    """Table-driven over the changes a deployment sees: whatever the cheapest composition overall,
    the decision is one transition() carries out, and none is handed out where none is."""
    cases = [
        # running, F, application, cpus, bandwidth
        (('pbr',), {CRASH, TRANSIENT_VALUE}, DET_STATE, 2, None),
        (('lfr',), {CRASH, TRANSIENT_VALUE}, DET_STATE, 2, None),
        (('pbr',), {CRASH, SAFETY_VIOLATION}, DET_STATE, 2, None),
        (('pbr',), {CRASH}, DET_STATE, 2, 5e4),
        (('lfr',), {CRASH}, Application(deterministic=False, state_access=True), 2, None),
        (('pbr',), {CRASH}, DET_STATE, 1, None),
        (('pbr',), {CRASH, TAMPERING}, DET_STATE, 2, None),
        (('tr',), {CRASH}, DET_STATE, 2, None),
        (('pbr',), {CRASH}, Application(deterministic=False, state_access=False), 2, None),
    ]
    for running, faults, application, cpus, bandwidth in cases:
        core, clock = monitor(running, faults, application)
        core.bandwidth(bandwidth, clock.now)
        node = Node(core, clock)
        node.run(1.0)
        node.run(LOST_AFTER + 1.0, sites=SITES[:cpus])
        for d in node.decisions:
            assert reachable(d.from_, d.to, SITES[:cpus]), (running, faults, d)
        assert core.state == MonitorState.WATCHING, (running, faults, list(core.history)[-3:])


def test_no_reachable_target_is_alarmed_once_and_never_handed_out_as_a_decision():
    core, clock = monitor(('tr',))                     # tr on the survivor; the slave is back
    node = Node(core, clock, alarms=True)
    node.run(10.0)
    assert select(core.model()).name == 'lfr'          # what fits: no script adds a replica to tr
    assert node.decisions == [] and core.state == MonitorState.WATCHING and core.running == ('tr',)
    [alarm] = node.alarms
    assert alarm.kind == NO_MECHANISM_FITS and 'tr is kept' in alarm.detail
    assert 'does not cover crash' in alarm.detail and 'lfr, which no shipped adaptation reaches from tr' in alarm.detail


def test_a_composition_nothing_fits_is_alarmed_no_mechanism_fits_and_kept():
    # neither pbr (no state access) nor lfr (non-deterministic) can run this server
    core, clock = monitor(('pbr',), application=Application(deterministic=False, state_access=False))
    node = Node(core, clock, alarms=True)
    node.run(5.0)
    assert node.decisions == [] and core.state == MonitorState.WATCHING and core.running == ('pbr',)
    [alarm] = node.alarms
    assert alarm.kind == NO_MECHANISM_FITS and 'getState/setState' in alarm.detail and 'pbr keeps running' in alarm.detail


def test_select_restricted_to_reachable_targets_keeps_the_running_replication():
    model = ChangeModel({CRASH, TRANSIENT_VALUE}, DET_STATE, Resources(2))
    assert select(model).mechanisms == ('lfr', 'tr')
    kept = select(model, allowed=lambda c: c == ('pbr',) or reachable(('pbr',), c, SITES), keep=('pbr',))
    assert kept.mechanisms == ('pbr', 'tr') and not kept.degraded


# -- M2: the monitor's own stall, or a late start, loses no site ------------------------------------
@pytest.mark.parametrize('beat_every,stall', [(0.1, 2.5), (0.1, 10.0), (0.3, 1.9)])
def test_a_stall_of_the_monitor_loses_no_site(beat_every, stall):
    core, clock = monitor()
    node = Node(core, clock)
    node.run(3.0, beat_every=beat_every)
    clock.advance(stall)     # the monitor stalls; the sites beat on, their beats queued unread
    node.tick()              # its tick runs before the queued heartbeats
    for site in SITES:
        core.heartbeat(site, clock.now)
    node.run(5.0, beat_every=beat_every)
    assert core.alive_sites() == SITES and core.model().resources.cpus == 2
    assert node.decisions == [] and core.stalls == 1
    core.bandwidth(5e4, clock.now)       # a later change is acted on
    node.run(1.0, beat_every=beat_every)
    assert [(d.from_, d.to) for d in node.decisions] == [(('pbr',), ('lfr',))]


def test_sites_starting_long_after_the_monitor_are_not_lost():
    core, clock = monitor()
    node = Node(core, clock)
    node.run(30.0, sites=[])            # the monitor runs, the sites are not up yet
    assert core.alive_sites() == SITES and node.decisions == []
    node.run(10.0)
    assert core.alive_sites() == SITES and node.decisions == []


def test_a_site_dead_during_a_stall_is_still_lost_for_good_after_it():
    core, clock = monitor()
    node = Node(core, clock)
    node.run(3.0)
    clock.advance(5.0)                  # the monitor stalls; the slave dies meanwhile
    node.tick()
    core.heartbeat('master', clock.now)
    node.run(LOST_AFTER, sites=['master'])
    node.run(LOST_AFTER, sites=['master'])
    assert core.alive_sites() == ['master']
    assert [(d.from_, d.to) for d in node.decisions] == [(('pbr',), ('tr',))]
    assert core.heartbeat('slave', clock.now) is False and core.alive_sites() == ['master']   # fail-silence


def test_a_monitor_stalled_at_every_tick_still_loses_a_dead_site():
    core, clock = monitor()
    node = Node(core, clock)
    node.run(1.0)
    for _ in range(20):                 # every tick 1.5 s late
        clock.advance(1.5)
        core.heartbeat('master', clock.now)
        node.tick()
    assert core.alive_sites() == ['master']


def test_a_stall_before_a_site_was_last_heard_is_no_excuse_for_its_later_silence():
    core, clock = monitor()
    node = Node(core, clock)
    node.run(1.0)
    clock.advance(5.0)
    node.tick()
    node.run(1.0)                       # both heard after the stall
    node.run(LOST_AFTER + 0.3, sites=['master'])
    assert core.alive_sites() == ['master']


# -- M8: alarms for what the monitor cannot fix, once per change ------------------------------------
def test_a_failed_or_refused_adaptation_is_alarmed_once():
    core, clock = monitor(('lfr',), application=Application(deterministic=False, state_access=True))
    decision = core.decide(clock.now)
    assert decision.to == ('pbr',)
    core.adaptation_failed('pbr_backup did not answer get_state', clock.now)
    [alarm] = core.take_alarms()
    assert alarm.kind == ADAPTATION_FAILED and 'lfr -> pbr' in alarm.detail and 'get_state' in alarm.detail
    Node(core, clock).run(10.0)
    assert core.take_alarms() == [] and core.state == MonitorState.FAILED


def test_a_rollback_that_failed_is_alarmed_rollback_failed():
    core, clock = monitor(('lfr',), application=Application(deterministic=False, state_access=True))
    core.decide(clock.now)
    core.adaptation_failed('could not kill /slave/after', clock.now, rollback_failed=True)
    [alarm] = core.take_alarms()
    assert alarm.kind == ROLLBACK_FAILED and 'check by hand' in alarm.detail


def test_an_adaptation_that_stands_with_an_alarm_is_alarmed_incomplete():
    core, clock = monitor(('lfr',), application=Application(deterministic=False, state_access=True))
    core.decide(clock.now)
    core.adapted(('pbr',), clock.now, alarm='resume /master/proceed: timed out')
    [alarm] = core.take_alarms()
    assert alarm.kind == ADAPTATION_INCOMPLETE and '/master/proceed' in alarm.detail


def test_a_degraded_composition_is_alarmed_once_per_change_not_at_every_tick():
    core, clock = monitor()
    node = Node(core, clock, alarms=True)
    node.run(1.0)
    node.run(LOST_AFTER + 1.0, sites=['master'])      # pbr -> tr on the survivor: crash uncovered
    node.run(20.0, sites=['master'])
    core.bandwidth(5e6, clock.now)                    # a measurement at the same level: no change
    node.run(5.0, sites=['master'])
    assert core.running == ('tr',)
    [alarm] = node.alarms
    assert alarm.kind == DEGRADED and 'does not cover crash' in alarm.detail
    core.declare_faults({CRASH, SAFETY_VIOLATION}, clock.now)   # a change: tr -> tr+ad, still degraded
    node.run(5.0, sites=['master'])
    assert core.running == ('tr', 'ad')
    assert [a.kind for a in node.alarms] == [DEGRADED, DEGRADED]


# -- the node publishes the core's alarms (no master) ------------------------------------------------
class FakeEngine(object):
    def __init__(self, outcome):
        self.outcome = outcome

    def run(self, script, mode):
        if isinstance(self.outcome, Exception):
            raise self.outcome
        return dict(self.outcome)


def monitor_node(core, engine):
    """A MonitorNode as __init__ and setup() leave it, without parameters, master or threads."""
    from aft_ftm.ros.monitor_node import MonitorNode
    node = MonitorNode.__new__(MonitorNode)
    node.core, node.lock, node.suffix, node.script_args, node.mode = core, threading.Lock(), '', {}, 'prepared'
    node.engine, node.forged, node.work = engine, 0, queue.Queue()
    node.witness, node.ftm_ns = '/aft/witness/request', '/ftm'
    node.alarms, node.events, node.model_pub = FakePublisher(), FakePublisher(), FakePublisher()
    return node


@pytest.fixture
def no_ros(monkeypatch):
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))
    from aft_ftm.ros import adapt_command
    monkeypatch.setattr(adapt_command, 'load_script', lambda spec, overrides=(): (spec, overrides))
    monkeypatch.setattr(adapt_command, 'declared_args', lambda spec: {'witness'} | (
        {'ftm_ns'} if spec in ('switch', 'update_after') else set()))


@pytest.mark.parametrize('outcome,kind', [
    ({'ok': False, 'error': 'suspend /slave/after timed out', 'state': 'ROLLED_BACK', 'alarm': ''},
     ADAPTATION_FAILED),
    ({'ok': False, 'error': 'suspend /slave/after timed out', 'state': 'FAILED',
      'alarm': 'adaptation switch: rolled back, but the rollback failed'}, ROLLBACK_FAILED),
    (ScriptError('switch: /master/after_pbr is not in the graph'), ADAPTATION_FAILED),
])
def test_the_node_publishes_an_alarm_for_a_failed_adaptation(no_ros, monkeypatch, outcome, kind):
    core, clock = monitor(('lfr',), application=Application(deterministic=False, state_access=True))
    node = monitor_node(core, FakeEngine(outcome))
    node.work.put((core.decide(clock.now), SITES))
    running = iter([False, True])                        # the adapter thread's loop: one decision, then shutdown
    monkeypatch.setattr(rospy, 'is_shutdown', lambda: next(running))
    node._adapter()
    [published] = node.alarms.published
    assert (published.mechanism, published.kind) == ('monitor', kind)
    assert 'lfr -> pbr' in published.detail and core.state == MonitorState.FAILED


def test_the_node_publishes_a_degraded_composition_once(no_ros):
    core = MonitorCore({CRASH}, DET_STATE, ['master'], ('tr',), time.monotonic())   # one site: crash uncovered
    node = monitor_node(core, FakeEngine({}))
    for _ in range(10):
        node._tick(None)
    [published] = node.alarms.published
    assert (published.mechanism, published.kind) == ('monitor', DEGRADED)
    assert len(node.model_pub.published) == 10


def test_a_change_while_an_adaptation_runs_is_acted_on_after_it_failed():
    """Review of the monitor (session 33): the failed adaptation's model was taken when it failed, so a
    change that came while it ran (here the slave site lost during a PBR -> PBR+TR that then failed)
    was absorbed into it: the monitor never decided again, and TR on the survivor never came."""
    core, clock = monitor()
    node = Node(core, clock)
    node.run(1.0)
    core.alarm('tr', 'value_fault_masked', clock.now, source='/master/tr/after', sender='/master/tr/after')
    decision = core.decide(clock.now)
    assert decision is not None and core.state == MonitorState.ADAPTING
    for _ in range(40):                        # meanwhile the slave falls silent: lost for good
        clock.advance(PERIOD)
        core.heartbeat('master', clock.now)
        core.tick(clock.now)
    assert core.alive_sites() == ['master']
    core.adaptation_failed('rolled back', clock.now)
    assert core.state == MonitorState.FAILED
    again = core.decide(clock.now)
    assert again is not None and again.to == ('tr',), list(core.history)[-3:]   # decided on the model as it is now


def test_a_bandwidth_figure_no_longer_renewed_is_alarmed_once_stale():
    """Review of the monitor (session 33): a link too slow for the probe to finish publishes nothing,
    and the monitor kept an hour-old 50 MB/s figure, silently: a drop was never seen."""
    core, clock = monitor()
    node = Node(core, clock, alarms=True)
    node.run(5.0)
    assert node.alarms == []                             # no link monitor at all: nothing to say
    core.bandwidth(50e6, clock.now)
    node.run(29.0)
    assert [a.kind for a in node.alarms] == []
    node.run(3.0)
    assert [a.kind for a in node.alarms] == ['bandwidth_stale'] and '5e+07 B/s' in node.alarms[0].detail
    node.run(60.0)
    assert len(node.alarms) == 1                         # once, until a figure comes again
    core.bandwidth(40e6, clock.now)
    node.run(31.0)
    assert [a.kind for a in node.alarms] == ['bandwidth_stale'] * 2


def test_with_both_sites_alive_pbr_is_never_traded_for_tr_alone():
    """Review of this session's fixes: F = {crash, transient_value} and a low bandwidth, both sites
    alive: lfr+tr (the best) is not reachable in one step, and tr alone was chosen among the reachable
    ones; compose then ran pbr+tr while the monitor held 'tr', from which no transition leads."""
    assert not reachable(('pbr',), ('tr',), SITES) and reachable(('pbr',), ('tr',), ['master'])
    core, clock = monitor(faults=(CRASH, TRANSIENT_VALUE))
    node = Node(core, clock)
    core.bandwidth(5e4, clock.now)
    node.run(5.0)
    assert all(d.to != ('tr',) for d in node.decisions), [(d.from_, d.to) for d in node.decisions]


def test_a_site_never_heard_is_said_once_past_its_grace():
    """Review of this session's fixes: a site never heard is counted alive until its first beat; one
    dead before the monitor started was counted alive for ever, silently."""
    core, clock = monitor()
    node = Node(core, clock, alarms=True)
    node.run(29.0, sites=['master'])
    assert node.alarms == []
    node.run(2.0, sites=['master'])
    assert [a.kind for a in node.alarms] == ['site_never_heard'] and 'slave' in node.alarms[0].detail
    node.run(60.0, sites=['master'])
    assert len(node.alarms) == 1


class RecordingEngine(FakeEngine):
    def __init__(self):
        super(RecordingEngine, self).__init__({'ok': True, 'error': '', 'state': 'DONE', 'alarm': ''})
        self.scripts = []

    def run(self, script, mode):
        self.scripts.append(script)
        return super(RecordingEngine, self).run(script, mode)


@pytest.mark.parametrize('witness, given', [('/nav/witness/request', '/nav/witness/request'), ('', 'none')])
def test_every_script_the_monitor_runs_is_given_the_replicas_witness_first(no_ros, monkeypatch, witness, given):
    """Session 40: the monitor ran its scripts with their default witness (/aft/witness/request), so the
    nodes a switch or a composition started followed another service's witness on a shared master. The
    operator's script_args come after, and may still say otherwise."""
    core, clock = monitor(('lfr',), application=Application(deterministic=False, state_access=True))
    engine = RecordingEngine()
    node = monitor_node(core, engine)
    node.witness, node.ftm_ns, node.script_args = witness, '/nav_ftm', {'switch': ['state_manager:=planner']}
    node.work.put((core.decide(clock.now), SITES))
    running = iter([False, True])
    monkeypatch.setattr(rospy, 'is_shutdown', lambda: next(running))
    node._adapter()
    [(spec, overrides)] = engine.scripts
    assert spec == 'switch' and overrides[:3] == ['witness:=' + given, 'ftm_ns:=/nav_ftm', 'state_manager:=planner'], \
        overrides


def test_only_the_arguments_a_script_declares_are_given_to_it():
    from aft_ftm.ros import adapt_command
    assert {'witness', 'ftm_ns'} <= adapt_command.declared_args('switch')
    assert 'witness' in adapt_command.declared_args('compose') and 'ftm_ns' not in adapt_command.declared_args('compose')


def test_every_shipped_adaptation_script_takes_the_witness():
    import glob
    import os
    from aft_ftm import adaptation
    folder = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                          'catkin_ws', 'src', 'aft_ftm', 'adaptations')
    paths = sorted(glob.glob(os.path.join(folder, '*.yaml')))
    assert len(paths) >= 4
    for path in paths:
        with open(path) as f:
            script = adaptation.load(f.read(), {'witness': '/nav/witness/request'}, source=path)
        assert script.args['witness'] == '/nav/witness/request', path


def test_another_service_s_alarms_on_the_shared_topic_do_not_choose_this_service_s_mechanisms():
    """Review of session 40: /aft/alarms is shared by every service on a ROS master; a navigation
    service's A&D alarm added safety_violation to the bank's F, and the monitor composed A&D onto the
    bank. Only the alarms of the service's own nodes (its sites', and those ~alarms_from names) count."""
    clock = FakeClock(100.0)
    core = MonitorCore(frozenset([CRASH]), DET_STATE, SITES, ('pbr',), clock.now, lost_after=LOST_AFTER,
                       alarms_from=['/proxy', '/sec_gate'])
    for source, mechanism, kind in (('/nav_a/ad/after', 'ad', 'assertion_violated'),
                                    ('/masterx/tr/after', 'tr', 'no_majority'),   # a prefix is no namespace
                                    ('/nav_proxy', 'sec', 'bad_signature'),
                                    ('/nav_a/ad/after', 'ad', 'assertion_violated')):
        assert core.alarm(mechanism, kind, clock.now, source=source, sender=source) is None
    assert core.model().faults == frozenset([CRASH])
    assert core.foreign == {'/nav_a/ad/after': 2, '/masterx/tr/after': 1, '/nav_proxy': 1}
    assert core.alarm('sec', 'bad_signature', clock.now, source='/sec_gate', sender='/sec_gate') == TAMPERING
    assert core.alarm('ad', 'assertion_violated', clock.now, source='/slave/ad/after',
                      sender='/slave/ad/after') == SAFETY_VIOLATION
    assert core.alarm('tr', 'no_majority', clock.now, source='/master', sender='/master') == TRANSIENT_VALUE
    assert core.model().faults == frozenset([CRASH, TAMPERING, SAFETY_VIOLATION, TRANSIENT_VALUE])
    for bad in (['proxy'], ['/'], ['/proxy/'], [3]):
        with pytest.raises(ConfigError, match='alarms_from'):
            MonitorCore(frozenset([CRASH]), DET_STATE, SITES, ('pbr',), clock.now, alarms_from=bad)


def test_a_witness_never_heard_naming_the_sites_is_said_once_and_a_late_one_is_noted():
    """Review of session 40: a monitor following a witness that does not run (or another service's)
    never saw a lost site re-join, and said nothing: R stayed low for good."""
    clock = FakeClock(100.0)
    core = MonitorCore(frozenset([CRASH]), DET_STATE, SITES, ('pbr',), clock.now, lost_after=LOST_AFTER,
                       follows_witness=True)
    node = Node(core, clock, alarms=True)
    node.run(29.0)
    assert [a for a in node.alarms if a[0] == 'witness_unheard'] == []
    node.run(2.0)
    unheard = [a for a in node.alarms if a[0] == 'witness_unheard']
    assert len(unheard) == 1 and 'master, slave' in unheard[0][1], node.alarms
    node.run(40.0)
    assert len([a for a in node.alarms if a[0] == 'witness_unheard']) == 1   # once
    core.witness_heard(clock.now)
    assert 'the witness heard at last' in core.history[-1][1]
    # Heard in time: never said; without a witness followed: never said.
    for follows, heard in ((True, True), (False, False)):
        clock = FakeClock(100.0)
        core = MonitorCore(frozenset([CRASH]), DET_STATE, SITES, ('pbr',), clock.now, lost_after=LOST_AFTER,
                           follows_witness=follows)
        node = Node(core, clock, alarms=True)
        if heard:
            clock.advance(1.0)
            core.witness_heard(clock.now)
        node.run(60.0)
        assert [a for a in node.alarms if a[0] == 'witness_unheard'] == []


def test_a_switch_after_a_failover_names_the_witness_s_primary_its_primary():
    """Review of session 40: transition() names alive[0] the primary, and alive was in the configured
    order: after a failover to slave and master's re-join, a switch named master (the backup) primary."""
    clock = FakeClock(100.0)
    core = MonitorCore(frozenset([CRASH]), DET_STATE, SITES, ('pbr',), clock.now, lost_after=LOST_AFTER,
                       follows_witness=True)
    assert core.alive_sites() == ['master', 'slave']
    core.witness_heard(clock.now, 'slave', 3)
    assert core.alive_sites() == ['slave', 'master']
    assert 'primary:=slave' in transition(('pbr',), ('lfr',), core.alive_sites()).overrides
    core.witness_heard(clock.now, 'master', 2)   # an older epoch's, late: nothing changes
    assert core.alive_sites() == ['slave', 'master']
    core.witness_heard(clock.now, 'elsewhere', 4)   # not one of the sites: the configured order
    assert core.alive_sites() == ['master', 'slave']
    core.witness_heard(clock.now, 'slave', 5)
    core.heartbeat('slave', clock.now)
    Node(core, clock).run(LOST_AFTER + 1.0, sites=['master'])   # slave silent: lost
    assert core.alive_sites() == ['master']
