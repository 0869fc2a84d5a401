"""The change model (F, A, R) -> selection of a consistent composition, table-driven. No ROS.

The preference between PBR and LFR comes only from Table I (mechanisms.TABLE): both need 2 CPUs,
LFR needs 'low' bandwidth and PBR 'high', so where both fit LFR is the cheaper one.
"""
import json

import pytest

from aft_ftm import mechanisms
from aft_ftm.change_model import (ALARM_FAULTS, Application, ChangeModel, Resources, bandwidth_level,
                                  consistent, observed_fault, select)
from aft_ftm.errors import ConfigError
from aft_ftm.mechanisms import CRASH, EAVESDROPPING, SAFETY_VIOLATION, TAMPERING, TRANSIENT_VALUE

DET, NONDET = True, False
STATE, NOSTATE = True, False
HIGH, LOW, NIL = 5e6, 5e4, 5e3   # bytes/s, with the default thresholds high=1e6, low=1e4


def model(faults, deterministic=DET, state_access=STATE, cpus=2, bandwidth=None):
    return ChangeModel(frozenset(faults), Application(deterministic, state_access), Resources(cpus, bandwidth))


# -- F, A, R -> selection ---------------------------------------------------------------------------
@pytest.mark.parametrize('faults,det,state,cpus,bw,name,degraded,uncovered', [
    # crash: PBR or LFR by A, then by cost (LFR needs less bandwidth)
    ({CRASH}, DET, STATE, 2, HIGH, 'lfr', False, set()),
    ({CRASH}, DET, STATE, 2, None, 'lfr', False, set()),        # unknown bandwidth = unlimited
    ({CRASH}, NONDET, STATE, 2, HIGH, 'pbr', False, set()),
    ({CRASH}, DET, NOSTATE, 2, HIGH, 'lfr', False, set()),
    ({CRASH}, NONDET, NOSTATE, 2, HIGH, 'none', True, {CRASH}),  # neither replication fits A
    ({CRASH}, DET, STATE, 2, LOW, 'lfr', False, set()),
    ({CRASH}, NONDET, STATE, 2, LOW, 'none', True, {CRASH}),     # pbr needs high, lfr determinism
    ({CRASH}, DET, STATE, 2, NIL, 'none', True, {CRASH}),        # no replication fits 'nil'
    ({CRASH}, DET, STATE, 3, HIGH, 'lfr', False, set()),
    # crash with one site left: degraded to TR on the survivor
    ({CRASH}, DET, STATE, 1, HIGH, 'tr', True, {CRASH}),
    ({CRASH}, NONDET, STATE, 1, HIGH, 'none', True, {CRASH}),    # TR needs determinism too
    ({CRASH, TRANSIENT_VALUE}, DET, STATE, 1, HIGH, 'tr', True, {CRASH}),
    ({CRASH, SAFETY_VIOLATION}, NONDET, NOSTATE, 1, HIGH, 'ad', True, {CRASH}),
    # compositions
    ({CRASH, TRANSIENT_VALUE}, DET, STATE, 2, HIGH, 'lfr+tr', False, set()),
    ({CRASH, TRANSIENT_VALUE}, DET, STATE, 2, LOW, 'lfr+tr', False, set()),
    ({CRASH, TRANSIENT_VALUE}, DET, NOSTATE, 2, HIGH, 'lfr', True, {TRANSIENT_VALUE}),  # tr needs state
    ({CRASH, SAFETY_VIOLATION}, NONDET, STATE, 2, HIGH, 'pbr+ad', False, set()),
    ({CRASH, TAMPERING}, NONDET, STATE, 2, HIGH, 'sec+pbr', False, set()),
    ({TAMPERING, TRANSIENT_VALUE, SAFETY_VIOLATION}, DET, STATE, 1, LOW, 'sec+tr+ad', False, set()),
    # single fault kinds
    ({TRANSIENT_VALUE}, DET, STATE, 1, NIL, 'tr', False, set()),
    ({TRANSIENT_VALUE}, NONDET, STATE, 2, HIGH, 'none', True, {TRANSIENT_VALUE}),
    ({SAFETY_VIOLATION}, NONDET, NOSTATE, 1, NIL, 'ad', False, set()),
    ({TAMPERING}, NONDET, NOSTATE, 1, HIGH, 'sec', False, set()),
    ({EAVESDROPPING}, NONDET, NOSTATE, 1, LOW, 'sec', False, set()),
    ({TAMPERING}, NONDET, NOSTATE, 1, NIL, 'none', True, {TAMPERING}),  # sec needs 'low'
    # nothing to tolerate
    (set(), DET, STATE, 2, HIGH, 'none', False, set()),
    (set(), NONDET, NOSTATE, 0, NIL, 'none', False, set()),
])
def test_selection(faults, det, state, cpus, bw, name, degraded, uncovered):
    m = model(faults, det, state, cpus, bw)
    s = select(m)
    assert (s.name, s.degraded, s.uncovered) == (name, degraded, frozenset(uncovered)), s.reason
    assert s.name == ('+'.join(s.mechanisms) or 'none')
    assert s.reason
    if not degraded:
        # what is selected is consistent with the model it was selected for
        assert consistent(s.mechanisms, m)[0] or not s.mechanisms
    json.dumps(s.to_dict())


def test_selection_is_table_driven_pbr_wins_when_it_becomes_the_cheaper(monkeypatch):
    """Nothing is special-cased by name: swap the bandwidth needs and the choice follows."""
    table = mechanisms.TABLE.copy()
    table['pbr'] = table['pbr']._replace(bandwidth='low')
    table['lfr'] = table['lfr']._replace(bandwidth='high')
    monkeypatch.setattr(mechanisms, 'TABLE', table)
    assert select(model({CRASH}, DET, STATE, 2, HIGH)).name == 'pbr'


@pytest.mark.parametrize('faults,det,state,cpus,bw,words', [
    ({CRASH}, NONDET, STATE, 2, HIGH, ['lfr needs a deterministic server', 'pbr']),
    ({CRASH}, DET, STATE, 2, LOW, ["supports only 'low'", 'pbr needs high', 'lfr']),
    ({CRASH}, DET, STATE, 1, HIGH, ['crash cannot be tolerated', 'tr']),
    ({CRASH}, NONDET, NOSTATE, 2, HIGH, ['deterministic', 'state', 'crash']),
    (set(), DET, STATE, 2, HIGH, ['no mechanism is needed']),
])
def test_selection_reason_names_the_deciding_facts(faults, det, state, cpus, bw, words):
    reason = select(model(faults, det, state, cpus, bw)).reason
    for word in words:
        assert word in reason


@pytest.mark.parametrize('bytes_per_s,level', [
    (None, 'high'), (1e9, 'high'), (1e6, 'high'), (999999.0, 'low'), (1e4, 'low'), (9999, 'nil'), (0, 'nil'),
])
def test_bandwidth_level(bytes_per_s, level):
    assert bandwidth_level(bytes_per_s) == level


# -- consistency of the running composition ---------------------------------------------------------
@pytest.mark.parametrize('running,faults,det,state,cpus,bw,ok,words', [
    # pbr is not the cheapest here (lfr is), but it is consistent: no adaptation for cost alone
    (('pbr',), {CRASH}, DET, STATE, 2, HIGH, True, ['pbr covers crash']),
    (('lfr',), {CRASH}, NONDET, STATE, 2, HIGH, False, ['deterministic']),
    (('pbr',), {CRASH}, DET, STATE, 2, NIL, False, ['pbr needs high']),
    (('pbr',), {CRASH}, DET, STATE, 2, LOW, False, ['pbr needs high']),
    (('pbr',), {CRASH}, DET, STATE, 1, HIGH, False, ['pbr needs 2 CPUs']),
    (('pbr',), {CRASH}, DET, NOSTATE, 2, HIGH, False, ['state']),
    (('pbr',), {CRASH, TRANSIENT_VALUE}, DET, STATE, 2, HIGH, False, ['does not cover transient_value']),
    (('pbr', 'tr'), {CRASH, TRANSIENT_VALUE}, DET, STATE, 2, HIGH, True, []),
    (('tr',), {CRASH}, DET, STATE, 1, HIGH, False, ['does not cover crash']),
    ((), set(), DET, STATE, 2, HIGH, True, []),
    ((), {SAFETY_VIOLATION}, DET, STATE, 2, HIGH, False, ['none does not cover safety_violation']),
    (('pbr',), set(), NONDET, STATE, 2, HIGH, True, []),
])
def test_consistency(running, faults, det, state, cpus, bw, ok, words):
    result, reason = consistent(running, model(faults, det, state, cpus, bw))
    assert result == ok, reason
    for word in words:
        assert word in reason


# -- alarms -> observed faults ----------------------------------------------------------------------
@pytest.mark.parametrize('mechanism,kind,fault', [
    ('tr', 'value_fault_masked', TRANSIENT_VALUE),
    ('tr', 'no_majority', TRANSIENT_VALUE),
    ('ad', 'assertion_violated', SAFETY_VIOLATION),
    ('sec', 'replay', TAMPERING),
    ('sec', 'tampered', TAMPERING),
    ('sec', 'bad_signature', TAMPERING),
    ('sec', 'unsigned', TAMPERING),
    ('sec', 'forged', TAMPERING),
    ('sec', 'something_new', TAMPERING),
    ('sec', 'ca_unreachable', None),   # a frozen or dead CA is no attack
    ('sec', 'ca_silent', None),
    ('pbr', 'checkpoint_late', None),
])
def test_observed_fault(mechanism, kind, fault):
    assert observed_fault(mechanism, kind) == fault


def test_alarm_faults_are_known_fault_kinds():
    assert set(ALARM_FAULTS.values()) <= {CRASH, TRANSIENT_VALUE, SAFETY_VIOLATION, EAVESDROPPING, TAMPERING}


# -- invalid input ----------------------------------------------------------------------------------
@pytest.mark.parametrize('build,words', [
    (lambda: model({'byzantine'}), "'byzantine'"),
    (lambda: ChangeModel('crash', Application(DET, STATE), Resources(2)), 'string'),
    (lambda: Resources(-1, None), 'cpus'),
    (lambda: Resources(1.5, None), 'cpus'),
    (lambda: Resources(2, -3.0), 'bandwidth'),
    (lambda: Resources(2, float('nan')), 'bandwidth'),
    (lambda: Application('yes', True), 'deterministic'),
    (lambda: bandwidth_level(-1), 'bandwidth'),
    (lambda: bandwidth_level(5, high=10, low=100), 'low'),
    (lambda: consistent(('xyz',), model({CRASH})), "'xyz'"),
])
def test_invalid_input_raises_config_error(build, words):
    with pytest.raises(ConfigError) as err:
        build()
    assert words in str(err.value)


def test_model_to_dict_is_json():
    d = model({CRASH, TAMPERING}, DET, NOSTATE, 2, LOW).to_dict()
    assert json.loads(json.dumps(d)) == {
        'faults': ['crash', 'tampering'], 'application': {'deterministic': True, 'state_access': False},
        'resources': {'cpus': 2, 'bandwidth': LOW}}
