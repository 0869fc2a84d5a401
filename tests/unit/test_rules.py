"""Dynamic binding rules, recovery plans, typed parameters. No ROS."""
import pytest

from aft_ftm import config
from aft_ftm.errors import ConfigError, RebindError
from aft_ftm.ports import PUBLISH, SUBSCRIBE, PortSpec, check_rebind
from aft_ftm.protocol import Role
from aft_ftm.recovery import (Step, failed_steps, incomplete, plan, promoted_unasked, role_after, same_process, start_plan,
                              unfenceable)

SPECS = {'requests': PortSpec('requests', SUBSCRIBE, 'aft_msgs/Request'),
         'replies': PortSpec('replies', PUBLISH, 'aft_msgs/Reply')}
TYPES = {'/ftm/pxy2pro': 'aft_msgs/Request', '/ftm/pro2pxy': 'aft_msgs/Reply', '/chatter': 'std_msgs/String'}


@pytest.mark.parametrize('port,direction,topic,activate,error', [
    ('requests', SUBSCRIBE, '/ftm/pxy2pro', True, None),
    ('replies', PUBLISH, '/ftm/pro2pxy', True, None),
    ('requests', SUBSCRIBE, '/not/yet/existing', True, None),   # a new topic takes the port's type
    ('requests', SUBSCRIBE, '', False, None),                   # unbinding needs no topic
    ('requests', SUBSCRIBE, '/chatter', True, 'topic /chatter has type std_msgs/String but port '
                                              "'requests' has type aft_msgs/Request"),
    ('replies', PUBLISH, '/ftm/pxy2pro', True, 'aft_msgs/Request but port'),
    ('requests', PUBLISH, '/ftm/pxy2pro', True, "port 'requests' is a subscribe port"),
    ('nope', SUBSCRIBE, '/ftm/pxy2pro', True, "unknown port 'nope' \\(this node has: replies, requests\\)"),
    ('requests', 7, '/ftm/pxy2pro', True, 'direction must be'),
    ('requests', SUBSCRIBE, '', True, 'no topic given'),
])
def test_rebind_rules(port, direction, topic, activate, error):
    if error is None:
        assert check_rebind(SPECS, port, direction, topic, TYPES, activate) is SPECS[port]
    else:
        with pytest.raises(RebindError, match=error):
            check_rebind(SPECS, port, direction, topic, TYPES, activate)


@pytest.mark.parametrize('role,waves,after', [
    (Role.BACKUP, [[Step.FAIL_SILENCE, Step.PROMOTE_AFTER], [Step.PROMOTE_PROTOCOL]], Role.ALONE),
    (Role.PRIMARY, [[Step.FAIL_SILENCE, Step.AFTER_ALONE]], Role.ALONE),
    (Role.ALONE, [], Role.ALONE),
])
def test_recovery_plan_per_role(role, waves, after):
    assert plan(role) == waves
    assert role_after(role) == after


@pytest.mark.parametrize('role', list(Role))
def test_a_backup_never_executes_before_the_failed_site_is_silent(role):
    """No two primaries: the Protocol is promoted only in a wave after fail-silence and fencing."""
    wave_of = {step: i for i, wave in enumerate(plan(role)) for step in wave}
    if Step.PROMOTE_PROTOCOL in wave_of:
        assert wave_of[Step.FAIL_SILENCE] < wave_of[Step.PROMOTE_PROTOCOL]
        assert wave_of[Step.PROMOTE_AFTER] < wave_of[Step.PROMOTE_PROTOCOL]


@pytest.mark.parametrize('witness', [False, True])
def test_failover_and_start_plans_only_switch_roles(witness):
    """The clients' topics are bound at set-up: no plan binds a topic (a new subscription needs the ROS
    master, which may be dead at failover). A witness adds only its vote, first."""
    assert plan(Role.BACKUP, witness) == ([[Step.WITNESS_PROMOTE]] if witness else []) + [
        [Step.FAIL_SILENCE, Step.PROMOTE_AFTER], [Step.PROMOTE_PROTOCOL]]
    assert start_plan() == [[Step.PROMOTE_AFTER], [Step.PROMOTE_PROTOCOL]]
    assert set(Step) == {Step.WITNESS_PROMOTE, Step.WITNESS_EXCLUDE, Step.FAIL_SILENCE, Step.PROMOTE_AFTER,
                         Step.PROMOTE_PROTOCOL, Step.AFTER_ALONE}


def test_fail_silence_spares_a_pid_reused_after_the_last_heartbeat():
    assert same_process(age=100.0, since_heard=0.3)            # started long before, heard 0.3 s ago
    assert not same_process(age=0.2, since_heard=0.75)         # started after the last heartbeat
    assert same_process(age=0.74, since_heard=0.75)            # within the tolerance


def test_a_launchers_age_agrees_with_the_boot_clock_whatever_the_wall_clock_did():
    # The age fail-silence compares is the boot clock's now minus the start in ticks since boot: the
    # wall clock, stepped since, plays no part (psutil's create time would be off by the step).
    import os
    import time
    from aft_ftm.process_start import started
    age = time.clock_gettime(time.CLOCK_BOOTTIME) - started(os.getpid())
    assert 0 < age < time.monotonic() + 1 and same_process(age, since_heard=age / 2)


@pytest.mark.parametrize('convert,value,ok', [
    (config.positive_float, 0.01, True), (config.positive_float, 0, False),
    (config.positive_float, 'x', False), (config.positive_float, -1, False),
    (config.positive_float, float('inf'), False), (config.positive_float, 'inf', False),   # (review of session 48:
    (config.positive_float, 1e10, False), (config.positive_float, float('nan'), False),    # a wait on it raised)
    (config.positive_float, 86400.0 * 365, True),
    (config.non_negative_int, 3, True), (config.non_negative_int, -3, False),
    (config.non_negative_int, 2.5, False), (config.non_negative_int, True, False),
    (config.service_type, 'aft_msgs/Account', True), (config.service_type, 'Account', False),
    (config.non_empty_str, ' ', False),
    (config.niceness, -5, True), (config.niceness, 20, False), (config.niceness, -21, False),
    (config.niceness, 'high', False),
])
def test_parameter_converters_name_the_parameter_and_value(convert, value, ok):
    if ok:
        convert('~p', value)
    else:
        with pytest.raises(ConfigError, match=r'~p .*%s' % repr(value).replace('.', r'\.')):
            convert('~p', value)


def test_a_failed_promotion_is_named_for_its_alarm_and_a_refused_witness_is_left_to_its_own():
    def step(name, ok, detail=''):
        return {'step': name, 'ok': ok, 'detail': detail, 'start': 0.0, 'seconds': 0.001}
    done = {'steps': [step('WITNESS_PROMOTE', True), step('FAIL_SILENCE', True), step('PROMOTE_AFTER', True),
                      step('PROMOTE_PROTOCOL', True)]}
    assert failed_steps(done) == ''
    lfr = {'steps': [step('WITNESS_PROMOTE', True), step('FAIL_SILENCE', True),
                     step('PROMOTE_AFTER', False, '/master/after refused: computed 0 of the 1 forwarded requests'),
                     step('PROMOTE_PROTOCOL', False, 'not promoted: the After was not promoted')]}
    assert failed_steps(lfr) == ('PROMOTE_AFTER: /master/after refused: computed 0 of the 1 forwarded requests; '
                                 'PROMOTE_PROTOCOL: not promoted: the After was not promoted')
    refused = {'steps': [step('WITNESS_PROMOTE', False, 'the witness refused PROMOTE: excluded')]}
    assert failed_steps(refused) == ''   # promotion_refused is raised for it already


REMOTE = {'/master/protocol': 'http://10.77.0.2:40001/', '/master/after': 'http://10.77.0.2:40002/',
          '/master/before': 'http://10.77.0.2:40003/', '/master/proceed': 'http://10.77.0.2:40004/'}


@pytest.mark.parametrize('remote,switch,tls,words', [
    ({}, False, False, None),                        # every node of the peer on this machine: killed by pid
    (REMOTE, True, False, None),                     # the power switch silences their host
    (REMOTE, True, True, None),
    (REMOTE, False, False, 'a frozen, hung or cut-off node never answers'),
    (REMOTE, False, True, 'under TLS they refuse'),
])
def test_a_peer_on_another_machine_without_a_power_switch_cannot_be_made_silent(remote, switch, tls, words):
    why = unfenceable(remote, switch, tls)
    if words is None:
        assert why is None
    else:
        assert words in why and why.startswith('4 node(s) of the peer run on another machine')
        assert '/master/after at http://10.77.0.2:40002/' in why and 'and 1 more' in why   # named, bounded


def test_an_incomplete_recovery_says_who_still_serves_by_the_role_it_had():
    """A backup whose promotion failed leaves nobody to serve; a primary whose failed backup could not be
    fenced (a power switch that never confirms) serves on, alone: its alarm must not say nobody may serve.
    A primary whose After could not go alone does not serve: that is said as before."""
    def record(*failed):
        return {'steps': [{'step': s.name, 'ok': s not in failed, 'detail': ''} for s in
                          (Step.WITNESS_EXCLUDE, Step.FAIL_SILENCE, Step.AFTER_ALONE)]}
    kind, consequence = incomplete(Role.BACKUP, record(Step.FAIL_SILENCE))
    assert kind == 'promotion_failed' and 'nobody may serve' in consequence
    kind, consequence = incomplete(Role.PRIMARY, record(Step.FAIL_SILENCE))
    assert kind == 'recovery_incomplete' and 'goes on serving alone' in consequence and 'nobody' not in consequence
    for failed in ((Step.AFTER_ALONE,), (Step.FAIL_SILENCE, Step.AFTER_ALONE)):
        assert incomplete(Role.PRIMARY, record(*failed))[0] == 'promotion_failed'
    assert Step.AFTER_ALONE in plan(Role.PRIMARY, witness=True)[-1]   # alone without waiting for FAIL_SILENCE
    assert Step.FAIL_SILENCE in plan(Role.PRIMARY, witness=True)[-1]


def test_a_site_made_primary_without_its_recovery_asking_is_told_from_its_own_promotion():
    """A late PROMOTE (granted after its Recovery gave it up) names this backup the lone primary: it
    must take over, or nobody serves. Its own promotion (granted to this Recovery), a primary that
    lost its backup, and another site's promotion are not that."""
    from aft_ftm.protocol import Role
    assert promoted_unasked(Role.BACKUP, Role.ALONE, 'slave', 'slave', granted=2, epoch=5)
    assert not promoted_unasked(Role.BACKUP, Role.ALONE, 'slave', 'slave', granted=5, epoch=5)   # its own grant
    assert not promoted_unasked(Role.PRIMARY, Role.ALONE, 'slave', 'slave', granted=2, epoch=5)  # excluded its backup
    assert not promoted_unasked(Role.BACKUP, None, 'slave', 'master', granted=2, epoch=5)        # excluded itself



def test_project_yaml_refuses_a_key_given_twice_and_takes_merge_keys():
    """aft_ftm.config.load_yaml (every YAML file the project reads): a key twice in one mapping is refused
    (the last won, silently); a merge key (<<: *anchor) and a key overriding what it brings are YAML."""
    import yaml
    with pytest.raises(yaml.YAMLError, match="key 'gravity' given twice"):
        config.load_yaml('{gravity: 4, gravity: 1}')
    data = config.load_yaml('base: &b {timeout: 1, period: 2}\nsvc: {<<: *b, timeout: 5}\n')
    assert data['svc'] == {'timeout': 5, 'period': 2}
