"""The monitoring engine's decisions from (F, A, R) events, with a fake clock. No ROS."""
import json

import pytest

from aft_ftm.change_model import Application, select
from aft_ftm.errors import ConfigError
from aft_ftm.mechanisms import CRASH, SAFETY_VIOLATION, TAMPERING, TRANSIENT_VALUE
from aft_ftm.monitor import ForgedAlarm, MonitorCore, MonitorState, TransitionError, transition
from fakes import FakeClock

SITES = ['master', 'slave']
DET_STATE = Application(deterministic=True, state_access=True)
NONDET_STATE = Application(deterministic=False, state_access=True)
LOST_AFTER = 2.0


def monitor(running, application=DET_STATE, faults=(CRASH,), clock=None):
    clock = clock or FakeClock(100.0)
    return MonitorCore(frozenset(faults), application, SITES, running, clock.now, lost_after=LOST_AFTER), clock


def run(core, clock, seconds, sites=SITES, period=0.5):
    """Let time pass with the given sites beating; return every decision handed out."""
    decisions = []
    for _ in range(int(seconds / period)):
        clock.advance(period)
        for site in sites:
            core.heartbeat(site, clock.now)
        decision = core.decide(clock.now)
        if decision is not None:
            decisions.append(decision)
    return decisions


def test_steady_state_decides_nothing():
    core, clock = monitor(('lfr',))
    assert run(core, clock, 30.0) == []
    assert core.state == MonitorState.WATCHING and core.alive_sites() == SITES


def test_running_composition_is_kept_while_consistent_even_if_not_the_cheapest():
    core, clock = monitor(('pbr',))      # lfr would be cheaper with det+state, pbr stays consistent
    assert select(core.model()).name == 'lfr'
    assert run(core, clock, 10.0) == []


# -- the three required scenarios -------------------------------------------------------------------
def test_a_application_becomes_non_deterministic_lfr_to_pbr():
    core, clock = monitor(('lfr',))
    run(core, clock, 2.0)
    core.declare_application(NONDET_STATE, clock.now)
    [decision] = run(core, clock, 5.0)
    assert (decision.from_, decision.to) == (('lfr',), ('pbr',))
    assert 'deterministic' in decision.reason
    assert decision.model.application == NONDET_STATE
    json.dumps(decision.to_dict())


def test_b_bandwidth_drops_below_high_pbr_to_lfr():
    core, clock = monitor(('pbr',))
    core.bandwidth(5e6, clock.now)
    assert run(core, clock, 2.0) == []
    core.bandwidth(5e4, clock.now)
    [decision] = run(core, clock, 5.0)
    assert (decision.from_, decision.to) == (('pbr',), ('lfr',))
    assert 'pbr needs high' in decision.reason


def test_c_backup_lost_for_good_pbr_to_tr_on_the_survivor():
    core, clock = monitor(('pbr',))
    assert run(core, clock, 3.0) == []
    decisions = run(core, clock, LOST_AFTER + 1.0, sites=['master'])   # the slave falls silent
    assert [(d.from_, d.to) for d in decisions] == [(('pbr',), ('tr',))]
    assert decisions[0].selection.degraded and decisions[0].selection.uncovered == {CRASH}
    assert core.alive_sites() == ['master']
    assert core.model().resources.cpus == 1
    # a heartbeat from the lost site does not bring it back (fail-silence)
    assert core.heartbeat('slave', clock.now) is False
    assert core.alive_sites() == ['master']


def test_site_is_lost_only_after_lost_after_of_silence():
    core, clock = monitor(('pbr',))
    run(core, clock, 1.0)
    run(core, clock, LOST_AFTER, sites=['master'])        # exactly lost_after: not yet
    assert core.alive_sites() == SITES
    run(core, clock, 0.5, sites=['master'])
    assert core.alive_sites() == ['master']


def test_site_never_heard_waits_for_its_first_beat_then_is_judged_by_its_silence():
    core, clock = monitor(('pbr',))
    assert run(core, clock, 5 * LOST_AFTER, sites=['master']) == []   # the slave starts late
    assert core.alive_sites() == SITES
    run(core, clock, 1.0)                                             # its first beats
    [decision] = run(core, clock, LOST_AFTER + 1.0, sites=['master'])
    assert decision.to == ('tr',) and core.alive_sites() == ['master']


# -- the adaptation state machine -------------------------------------------------------------------
def test_no_decision_while_adapting_then_watching_the_new_composition():
    core, clock = monitor(('lfr',))
    core.declare_application(NONDET_STATE, clock.now)
    first = core.decide(clock.now)
    assert first.to == ('pbr',) and core.state == MonitorState.ADAPTING
    core.declare_faults({CRASH, SAFETY_VIOLATION}, clock.now)   # the model changes again meanwhile
    assert run(core, clock, 5.0) == []
    core.adapted(first.to, clock.now)
    assert core.state == MonitorState.WATCHING and core.running == ('pbr',)
    [decision] = run(core, clock, 1.0)                 # the change is taken into account now
    assert (decision.from_, decision.to) == (('pbr',), ('pbr', 'ad'))


def test_adaptation_failed_is_not_retried_until_the_model_changes():
    core, clock = monitor(('lfr',))
    core.declare_application(NONDET_STATE, clock.now)
    assert core.decide(clock.now).to == ('pbr',)
    core.adaptation_failed('pbr_backup did not answer get_state', clock.now)
    assert core.state == MonitorState.FAILED and core.running == ('lfr',)
    core.bandwidth(5e6, clock.now)                     # same level as before (unknown = high)
    assert run(core, clock, 10.0) == []
    assert core.state == MonitorState.FAILED
    core.declare_faults({CRASH}, clock.now)           # same F: no change either
    assert run(core, clock, 1.0) == []
    core.declare_application(Application(deterministic=False, state_access=True), clock.now)
    assert core.decide(clock.now) is None             # an equal application is no change
    core.declare_faults({CRASH, TRANSIENT_VALUE}, clock.now)
    decision = core.decide(clock.now)
    assert decision is not None and core.state == MonitorState.ADAPTING
    assert decision.to == select(core.model()).mechanisms


@pytest.mark.parametrize('seed', range(10))
def test_a_failing_adaptation_under_a_flapping_bandwidth_is_retried_ever_less_often(seed):
    """Review of session 33: the bandwidth measured around a threshold changed the model every few
    seconds, and each change retried an adaptation that kept failing (each a pause of the application
    and a rollback). Now each failure in a row doubles the hold before a retry (2 s, 4 s, ... at most
    120 s), whatever the model does; one success starts the count afresh. Property over random flaps:
    no retry comes before its hold, and the holds grow."""
    import random
    rng = random.Random(seed)
    core, clock = monitor(('pbr',))
    high = core.high
    attempts, elapsed = [], 0.0
    while elapsed < 600.0:
        step = rng.uniform(0.1, 3.0)
        clock.advance(step)
        elapsed += step
        for site in SITES:
            core.heartbeat(site, clock.now)
        core.bandwidth(high * rng.choice([0.1, 10.0]), clock.now)   # flapping across the threshold
        decision = core.decide(clock.now)
        if decision is not None:
            if attempts:
                assert clock.now - attempts[-1] >= min(120.0, 2.0 * 2 ** (len(attempts) - 1)), 'seed %d' % seed
            attempts.append(clock.now)
            core.adaptation_failed('the new nodes did not start', clock.now)
    gaps = [b - a for a, b in zip(attempts, attempts[1:])]
    assert 3 <= len(attempts) <= 12, 'seed %d: %d attempts in 600 s: %s' % (seed, len(attempts), gaps)
    assert max(n for n, _ in core.holds.values()) == len(attempts)
    alarms = [a for a in core.take_alarms() if a.kind == 'adaptation_failed']
    assert 'on this model not before 4 s from now (2 failed in a row)' in alarms[1].detail
    # a success starts afresh
    core.holds = {k: (n, clock.now) for k, (n, _) in core.holds.items()}
    while core.decide(clock.now) is None:
        clock.advance(0.5)
        for site in SITES:
            core.heartbeat(site, clock.now)
        core.bandwidth(high * rng.choice([0.1, 10.0]), clock.now)
    core.adapted(core.pending.to, clock.now)
    assert core.holds == {}


def test_inconsistent_but_no_better_choice_decides_nothing():
    core, clock = monitor(('pbr',))
    run(core, clock, 1.0)
    [decision] = run(core, clock, LOST_AFTER + 1.0, sites=['master'])
    core.adapted(decision.to, clock.now)               # tr on the survivor: crash stays uncovered
    assert run(core, clock, 10.0, sites=['master']) == []
    assert core.running == ('tr',) and core.state == MonitorState.WATCHING
    notes = [t for _, t in core.history if 'remains the best choice' in t]
    assert len(notes) == 1 and 'does not cover crash' in notes[0]


@pytest.mark.parametrize('call', [
    lambda core, now: core.adapted(('pbr',), now),
    lambda core, now: core.adaptation_failed('boom', now),
])
def test_outcome_without_an_adaptation_under_way_is_refused(call):
    core, clock = monitor(('pbr',))
    with pytest.raises(TransitionError):
        call(core, clock.now)
    assert core.state == MonitorState.WATCHING and core.running == ('pbr',)


# -- alarms extend F ---------------------------------------------------------------------------------
def test_masked_value_fault_extends_f_and_adds_time_redundancy():
    core, clock = monitor(('pbr',))
    run(core, clock, 1.0)
    assert core.alarm('tr', 'value_fault_masked', clock.now) == TRANSIENT_VALUE
    assert core.model().faults == {CRASH, TRANSIENT_VALUE}
    [decision] = run(core, clock, 1.0)
    # lfr+tr would be cheaper, but no shipped script goes there from pbr: tr is composed onto pbr
    assert select(core.model()).mechanisms == ('lfr', 'tr')
    assert (decision.from_, decision.to) == (('pbr',), ('pbr', 'tr'))
    move = transition(decision.from_, decision.to, core.alive_sites())   # reachable: no ConfigError
    assert (move.script, move.overrides) == ('compose', ['mechanism:=tr', 'site:=master,slave'])
    assert not decision.selection.degraded and 'keeping pbr' in decision.reason
    core.adapted(decision.to, clock.now)
    core.declare_faults({CRASH}, clock.now)           # the observed fault is remembered
    assert core.model().faults == {CRASH, TRANSIENT_VALUE}
    assert run(core, clock, 5.0) == []


def test_alarm_showing_no_fault_changes_nothing():
    core, clock = monitor(('pbr',))
    assert core.alarm('pbr', 'checkpoint_late', clock.now) is None
    assert core.model().faults == {CRASH}
    assert 'checkpoint_late' in core.history[-1][1]


def test_an_alarm_in_another_nodes_name_is_refused_and_changes_nothing():
    core, clock = monitor(('pbr',))
    with pytest.raises(ForgedAlarm) as error:
        core.alarm('sec', 'bad_signature', clock.now, source='/master/sec_gate', sender='/slave/protocol')
    assert '/master/sec_gate' in str(error.value) and '/slave/protocol' in str(error.value)
    assert core.model().faults == {CRASH}
    assert run(core, clock, 5.0) == []                 # no adaptation chosen by it
    assert core.alarm('sec', 'bad_signature', clock.now, source='/master/sec_gate',
                      sender='/master/sec_gate') == TAMPERING   # the node itself: taken
    assert core.alarm('tr', 'no_majority', clock.now) == TRANSIENT_VALUE   # no sender known (a unit's own call)


# -- invalid input changes nothing -------------------------------------------------------------------
@pytest.mark.parametrize('call,words', [
    (lambda core, now: core.declare_faults({'gremlins'}, now), 'gremlins'),
    (lambda core, now: core.bandwidth(-5.0, now), 'bandwidth'),
    (lambda core, now: core.heartbeat('nobody', now), 'nobody'),
    (lambda core, now: core.declare_application({'deterministic': False}, now), 'Application'),
])
def test_invalid_event_raises_and_changes_nothing(call, words):
    core, clock = monitor(('pbr',))
    before = core.model()
    with pytest.raises(ConfigError) as err:
        call(core, clock.now)
    assert words in str(err.value)
    assert core.model() == before


@pytest.mark.parametrize('kwargs,words', [
    (dict(sites=[]), 'sites'),
    (dict(sites=['a', 'a']), 'sites'),
    (dict(running=('pbr', 'xyz')), "'xyz'"),
    (dict(declared_faults={'crash', 'typo'}), "'typo'"),
    (dict(lost_after=0), 'lost_after'),
])
def test_invalid_configuration_raises(kwargs, words):
    args = dict(declared_faults={CRASH}, application=DET_STATE, sites=SITES, running=('pbr',), now=0.0)
    args.update(kwargs)
    with pytest.raises(ConfigError) as err:
        MonitorCore(**args)
    assert words in str(err.value)


def test_history_records_the_adaptation():
    core, clock = monitor(('lfr',))
    core.declare_application(NONDET_STATE, clock.now)
    decision = core.decide(clock.now)
    core.adapted(decision.to, clock.now)
    text = [t for _, t in core.history]
    assert any('WATCHING -> ADAPTING' in t for t in text) and any('ADAPTING -> WATCHING' in t for t in text)
    assert all(now == clock.now for now, _ in core.history)


# -- from a decision to a shipped script -----------------------------------------------------------


@pytest.mark.parametrize('from_,to,alive,suffix,script,overrides,new_suffix', [
    (('pbr',), ('lfr',), ['master', 'slave'], '', 'switch',
     ['to:=lfr', 'old:=', 'new:=_lfr', 'primary:=master', 'backup:=slave'], '_lfr'),
    (('lfr',), ('pbr',), ['master', 'slave'], '_lfr', 'switch',
     ['to:=pbr', 'old:=_lfr', 'new:=_pbr', 'primary:=master', 'backup:=slave'], '_pbr'),
    (('pbr',), ('tr',), ['slave'], '', 'compose', ['mechanism:=tr', 'site:=slave'], ''),
    (('pbr',), ('pbr', 'ad'), ['master', 'slave'], '_pbr', 'compose', ['mechanism:=ad', 'site:=master,slave'],
     '_pbr'),
])
def test_each_supported_decision_maps_to_a_shipped_script(from_, to, alive, suffix, script, overrides, new_suffix):
    move = transition(from_, to, alive, suffix)
    assert (move.script, move.overrides, move.suffix) == (script, overrides, new_suffix)


@pytest.mark.parametrize('from_,to,alive', [
    (('pbr',), ('lfr', 'tr'), ['master', 'slave']),   # a switch and a composition at once
    (('pbr',), ('lfr',), ['master']),                  # a switch needs both replicas
    (('tr',), ('pbr',), ['master', 'slave']),          # adding a replica needs a state transfer
])
def test_a_decision_without_a_shipped_script_is_refused_naming_it(from_, to, alive):
    with pytest.raises(ConfigError, match='no shipped adaptation for'):
        transition(from_, to, alive)


def test_a_lost_site_that_re_joins_counts_again():
    core = MonitorCore({'crash'}, Application(deterministic=True, state_access=True), ['master', 'slave'],
                       ['pbr'], now=0.0, lost_after=1.0)
    core.heartbeat('master', 0.5)
    core.heartbeat('slave', 0.5)
    assert core.tick(0.5) == [] and core.tick(1.0) == []     # the monitor ticks (its gaps are no stall)
    core.heartbeat('master', 1.5)
    assert core.tick(1.5) == []
    core.heartbeat('master', 2.0)
    assert core.tick(2.0) == ['slave'] and core.model().resources.cpus == 1
    assert not core.heartbeat('slave', 2.1)      # heard again, but holds no state yet: still lost
    assert core.rejoined('slave', 3.0) and core.model().resources.cpus == 2
    assert not core.rejoined('slave', 3.1)
