"""The service manager's policies without processes or a master: configuration checking, the
state machine, detection with a fake clock, restart limits, dependencies, escalation, and state
restoration with its sanity check."""
import json

import pytest

from aft_service_manager.services import (EDGES, Sample, ServiceConfigError, State, Supervisor, detect, documentation,
                              parse_config)
from aft_ftm.state_store import StateStore, from_environment

ALIVE = Sample(alive=True, exit_code=None, stopped=False, cpu_percent=5.0, rss=50e6)
GB = 1e9


def config(services, manager=''):
    text = (('manager:\n' + manager) if manager else '') + 'services:\n' + services
    return parse_config(text, source='test.yaml')


def running(supervisor, name, now=0.0):
    supervisor[name].spawned(now)
    supervisor[name].heard(now + 0.01, 'ok')
    assert supervisor[name].state == State.RUNNING


# -- configuration -------------------------------------------------------------------------------
def test_defaults_fill_every_key():
    c = config('  a: {command: rosrun pkg a}\n')
    a = c['services']['a']
    assert a['command'] == ['rosrun', 'pkg', 'a'] and a['on_failure'] == 'restart' and a['restart_limit'] == 3
    assert a['heartbeat_timeout'] is None and a['critical'] is False and a['restart_with'] == []
    assert c['manager']['period'] == 0.01


@pytest.mark.parametrize('limit,expected', [('80%', 80.0), (150, 150.0)])
def test_cpu_limits_are_percent_of_a_core(limit, expected):
    assert config('  a: {command: x, cpu_limit: %r}\n' % limit)['services']['a']['cpu_limit'] == expected


@pytest.mark.parametrize('limit,expected', [('200MB', ('bytes', 200e6)), ('1GiB', ('bytes', 1024.0 ** 3)),
                                            (1000, ('bytes', 1000.0)), ('10%', ('percent', 10.0))])
def test_memory_limits_are_bytes_or_a_percentage(limit, expected):
    assert config('  a: {command: x, memory_limit: %r}\n' % limit)['services']['a']['memory_limit'] == expected


@pytest.mark.parametrize('services,message', [
    ('  a: {command: x, colour: red}\n', 'services.a: unknown key colour'),
    ('  a: {period: 1}\n', 'services.a: missing key command'),
    ('  a: {command: x, heartbeat_timeout: -1}\n', 'services.a.heartbeat_timeout must be a finite number > 0'),
    ('  a: {command: x, restart_limit: -2}\n', 'services.a.restart_limit must be an integer >= 0'),
    ('  a: {command: x, cpu_limit: lots}\n', 'services.a.cpu_limit must be a percentage'),
    ('  a: {command: x, memory_limit: -5MB}\n', 'services.a.memory_limit must be bytes'),
    ('  a: {command: x, memory_limit: 150%}\n', 'cannot exceed 100'),
    ('  a: {command: x, on_failure: reboot}\n', 'on_failure must be one of restart, terminate, run, alert'),
    ('  a: {command: x, on_failure: run}\n', 'on_failure run needs a program'),
    ('  a: {command: x, restart_with: [ghost]}\n', "restart_with names 'ghost', which is not a service"),
    ('  a: {command: x, terminate_with: [a]}\n', 'terminate_with names the service itself'),
    ('  a: {command: x, restart_with: [b]}\n  b: {command: y, restart_with: [c]}\n  c: {command: z, restart_with: [a]}\n',
     'restart_with makes a cycle: a -> b -> c -> a'),
    ('  a: {command: x, restart_with: [b], terminate_with: [b]}\n  b: {command: y}\n',
     'b both restarted and terminated'),
    ('  1a: {command: x}\n', "service name '1a'"),
    ('  a: {command: []}\n', 'must be a command'),
    ('  a: {command: x, critical: yes please}\n', 'critical must be true or false'),
    # a restart that would start a service and stop it at once (it stayed STARTING with no process)
    ('  tg: {command: x, restart_with: [c4g]}\n  c4g: {command: y, terminate_with: [tg]}\n',
     r'a restart of tg would start and stop tg at once: it restarts tg \(itself\) and c4g \(restart_with: tg -> c4g\), '
     r'whose terminate_with names tg'),
    ('  a: {command: x, restart_with: [b, c]}\n  b: {command: y}\n  c: {command: z, terminate_with: [b]}\n',
     r'a restart of a would start and stop b at once: it restarts b \(restart_with: a -> b\) and c '
     r'\(restart_with: a -> c\), whose terminate_with names b'),
    ('  a: {command: x, restart_with: [b]}\n  b: {command: y, restart_with: [c]}\n  c: {command: z, terminate_with: [a]}\n',
     r'a restart of a would start and stop a at once: .* c \(restart_with: a -> b -> c\), whose terminate_with names a'),
    ('  a: {command: x, memory_limit: 1.2.3MB}\n', 'services.a.memory_limit must be bytes'),
    ('  a: {command: x, memory_limit: .inf}\n', 'services.a.memory_limit must be a finite number'),
    ('  a: {command: x, cpu_limit: .inf}\n', 'services.a.cpu_limit must be a finite number'),
    ('  a: {command: x, heartbeat_timeout: .nan}\n', 'services.a.heartbeat_timeout must be a finite number > 0'),
    ('  a: {command: x, restart_delay_factor: .inf}\n', 'restart_delay_factor must be a finite number >= 1'),
    ('  a: {command: x, critical: true, critical: false}\n', "key 'critical' given twice"),
    ('  a: {command: x}\n  a: {command: y}\n', "key 'a' given twice"),
])
def test_a_bad_configuration_is_refused_naming_the_problem(services, message):
    with pytest.raises(ServiceConfigError, match=message):
        config(services)


@pytest.mark.parametrize('text,message', [
    ('services: {}\n', 'non-empty mapping'),
    ('servics:\n  a: {command: x}\n', 'must be a mapping with a services key'),
    ('services:\n  a: {command: x}\nextra: 1\n', 'unknown key extra'),
    ('manager: {period: 0}\nservices:\n  a: {command: x}\n', 'manager.period must be a finite number > 0'),
    ('services: [\n', 'not valid YAML'),
    ('manager: {kill_timeout: .inf}\nservices:\n  a: {command: x}\n', 'manager.kill_timeout must be a finite number'),
    ('manager: {period: .inf}\nservices:\n  a: {command: x}\n', 'manager.period must be a finite number'),
    ('manager: {period: 3000000}\nservices:\n  a: {command: x}\n', 'manager.period must be at most 3600 s'),
    ('manager: []\nservices:\n  a: {command: x}\n', 'manager must be a mapping'),
    ('manager: {}\nmanager: {period: 1}\nservices:\n  a: {command: x}\n', "key 'manager' given twice"),
])
def test_a_bad_file_is_refused(text, message):
    with pytest.raises(ServiceConfigError, match=message):
        parse_config(text, source='f.yaml')


def test_every_key_is_documented_with_its_default():
    doc = documentation()
    for key in ('command', 'heartbeat_timeout', 'memory_limit', 'restart_window', 'terminate_with', 'period'):
        assert '.%s`' % key in doc
    assert '| `services.NAME.restart_limit` | 3 |' in doc


# -- detection -----------------------------------------------------------------------------------
SERVICE = config('  a: {command: x, heartbeat_timeout: 0.05, cpu_limit: 80%, memory_limit: 100MB}\n')['services']['a']


@pytest.mark.parametrize('sample,last_heard,reported,expected', [
    (ALIVE, 0.98, None, None),
    (ALIVE._replace(alive=False, exit_code=-11), 0.98, None, 'exit'),
    (ALIVE._replace(stopped=True), 0.98, None, 'hang'),
    (ALIVE, 0.9, None, 'heartbeat_timeout'),
    (ALIVE, 0.98, 'joint limit exceeded', 'reported_error'),
    (ALIVE._replace(cpu_percent=95.0), 0.98, None, 'cpu_limit'),
    (ALIVE._replace(cpu_percent=None), 0.98, None, None),          # not a whole window yet
    (ALIVE._replace(rss=150e6), 0.98, None, 'memory_limit'),
])
def test_each_kind_of_fault_is_detected(sample, last_heard, reported, expected):
    found = detect(SERVICE, sample, 1.0, last_heard, reported, 0.0, 8 * GB)
    assert (found[0] if found else None) == expected


def test_a_memory_limit_in_percent_is_of_the_machine():
    c = config('  a: {command: x, memory_limit: 10%}\n')['services']['a']
    assert detect(c, ALIVE._replace(rss=0.9 * GB), 1.0, None, None, 0.0, 16 * GB) is None
    assert detect(c, ALIVE._replace(rss=0.9 * GB), 1.0, None, None, 0.0, 8 * GB)[0] == "memory_limit"


# -- the state machine and the policies ----------------------------------------------------------
def test_a_service_is_running_once_heard_and_a_silent_one_fails_to_start():
    sup = Supervisor(config('  a: {command: x, heartbeat_timeout: 0.1, start_timeout: 2}\n'))
    sup['a'].spawned(0.0)
    assert sup.check('a', ALIVE, 1.0, GB) is None and sup['a'].state == State.STARTING
    decision = sup.check('a', ALIVE, 2.5, GB)
    assert decision.kind == 'start_timeout' and sup['a'].state == State.RESTARTING


def test_without_heartbeats_alive_past_the_start_grace_is_running():
    sup = Supervisor(config('  a: {command: x, start_grace: 0.5}\n'))
    sup['a'].spawned(0.0)
    assert sup.check('a', ALIVE, 0.2, GB) is None and sup['a'].state == State.STARTING
    assert sup.check('a', ALIVE, 0.6, GB) is None and sup['a'].state == State.RUNNING


def test_a_heartbeat_timeout_with_a_fake_clock():
    sup = Supervisor(config('  a: {command: x, heartbeat_timeout: 0.05}\n'))
    running(sup, 'a')
    for t in (0.02, 0.04, 0.06):
        sup['a'].heard(t, 'ok')
        assert sup.check('a', ALIVE, t + 0.01, GB) is None
    decision = sup.check('a', ALIVE, 0.12, GB)
    assert decision.kind == 'heartbeat_timeout' and decision.actions == [('kill', 'a'), ('spawn', 'a')]


def test_restarts_within_the_limit_then_the_limit_escalates_to_the_safe_state():
    sup = Supervisor(config('  a: {command: x, restart_limit: 2, restart_window: 10}\n'))
    dead = ALIVE._replace(alive=False, exit_code=1)
    for t in (0.0, 1.0):
        running(sup, 'a', t)
        decision = sup.check('a', dead, t + 0.5, GB)
        assert decision.actions == [('kill', 'a'), ('spawn', 'a')] and decision.escalate is None
    running(sup, 'a', 2.0)
    decision = sup.check('a', dead, 2.5, GB)
    assert sup['a'].state == State.FAILED and decision.actions == [('kill', 'a')]
    assert 'restart limit exhausted' in decision.escalate and sup.safe_state == decision.escalate
    assert sup['a'].errors['exit'] == 3


def test_the_back_off_grows_with_consecutive_faults_up_to_its_cap_and_a_stable_run_resets_it():
    sup = Supervisor(config('  a: {command: x, restart_limit: 100, restart_delay: 0.1, restart_delay_factor: 3,'
                            ' restart_delay_max: 1.0, stable_after: 5}\n'))
    dead = ALIVE._replace(alive=False, exit_code=1)
    now, delays = 0.0, []
    for _ in range(5):
        running(sup, 'a', now)
        decision = sup.check('a', dead, now + 0.5, GB)
        assert decision.actions == [('kill', 'a')] and sup['a'].state == State.RESTARTING   # the spawn is held
        held = sup.next_due()
        delays.append(round(held - (now + 0.5), 6))
        assert sup.due(held - 1e-6) == [] and sup.due(held) == [('spawn', 'a')] and sup.due(held) == []
        now = held
    assert delays == [0.1, 0.3, 0.9, 1.0, 1.0]
    running(sup, 'a', now)
    assert sup.check('a', ALIVE, now + 5.01, GB) is None        # ran 5 s: the run of faults is over
    sup.check('a', dead, now + 6.0, GB)
    assert round(sup.next_due() - (now + 6.0), 6) == 0.1
    assert sup['a'].restarts_in_window(now + 6.0) == 6          # the restart limit still counts every one


def test_a_restart_the_back_off_holds_can_be_stopped_or_hurried_by_an_operator_and_limits_still_apply():
    sup = Supervisor(config('  a: {command: x, restart_limit: 1, restart_delay: 10}\n'
                            '  b: {command: y, restart_delay: 10}\n'))
    dead = ALIVE._replace(alive=False, exit_code=1)
    running(sup, 'a')
    sup.check('a', dead, 1.0, GB)
    ok, actions, _ = sup.stop('a', 2.0)
    assert ok and sup['a'].state == State.STOPPED and sup.next_due() is None and sup.due(20.0) == []
    running(sup, 'b')
    sup.check('b', dead, 1.0, GB)
    ok, actions, _ = sup.restart('b', 2.0)
    assert ok and actions == [('kill', 'b'), ('spawn', 'b')] and sup.next_due() is None
    running(sup, 'a', 3.0)                                       # a: its one restart is used
    decision = sup.check('a', dead, 4.0, GB)
    assert sup['a'].state == State.FAILED and 'restart limit' in decision.escalate


def test_restarts_older_than_the_window_do_not_count():
    sup = Supervisor(config('  a: {command: x, restart_limit: 1, restart_window: 5}\n'))
    dead = ALIVE._replace(alive=False, exit_code=1)
    for t in (0.0, 10.0, 20.0):
        running(sup, 'a', t)
        assert sup.check('a', dead, t + 1, GB).escalate is None


def test_the_trajectory_sender_terminates_the_generator_first_then_restarts_its_dependants():
    sup = Supervisor(config('  tg: {command: x}\n  pub: {command: z}\n'
                            '  c4g: {command: y, terminate_with: [tg], restart_with: [pub]}\n'))
    for name in ('tg', 'pub', 'c4g'):
        running(sup, name)
    decision = sup.fault('c4g', 'exit', 'segfault', 1.0)
    assert decision.actions == [('kill', 'tg'), ('kill', 'c4g'), ('spawn', 'c4g'), ('kill', 'pub'), ('spawn', 'pub')]
    assert sup['tg'].state == State.STOPPED and sup['c4g'].state == sup['pub'].state == State.RESTARTING


@pytest.mark.parametrize('action,critical,state,actions,escalates', [
    ('terminate', False, State.STOPPED, [('kill', 'a')], False),
    ('terminate', True, State.STOPPED, [('kill', 'a')], True),
    ('run', False, State.STOPPED, [('kill', 'a'), ('run', 'a')], False),
    ('alert', False, State.RUNNING, [('alert', 'a')], False),
    ('restart', True, State.RESTARTING, [('kill', 'a'), ('spawn', 'a')], False),
])
def test_each_failure_action(action, critical, state, actions, escalates):
    program = ', program: [echo, x]' if action == 'run' else ''
    sup = Supervisor(config('  a: {command: x, on_failure: %s, critical: %s%s}\n'
                            % (action, str(critical).lower(), program)))
    running(sup, 'a')
    decision = sup.fault('a', 'cpu_limit', 'CPU 95%', 1.0)
    assert sup['a'].state == state and decision.actions == actions
    assert (decision.escalate is not None) == escalates == (sup.safe_state is not None)


def test_a_service_whose_failure_stops_the_movement_escalates_even_when_restarted():
    sup = Supervisor(config('  tg: {command: x, safe_state_on_failure: true}\n'))
    running(sup, 'tg')
    decision = sup.fault('tg', 'exit', 'status 1', 1.0)
    assert decision.actions == [('kill', 'tg'), ('spawn', 'tg')] and 'movement stopped' in decision.escalate
    assert sup['tg'].state == State.RESTARTING


def test_the_safe_state_stays_until_an_operator_clears_it_with_critical_services_running():
    sup = Supervisor(config('  a: {command: x, on_failure: terminate, critical: true}\n  b: {command: y}\n'))
    running(sup, 'a')
    running(sup, 'b')
    sup.fault('a', 'exit', 'status 1', 1.0)
    assert sup.safe_state is not None
    ok, message = sup.clear_safe_state(2.0)
    assert not ok and 'critical services not running: a' in message
    ok, actions, _ = sup.start('a', 3.0)
    assert ok and actions == [('spawn', 'a')]
    running(sup, 'a', 3.0)
    assert sup.clear_safe_state(4.0)[0] and sup.safe_state is None
    assert sup.escalations == 1


def test_operator_commands_follow_the_state_machine():
    sup = Supervisor(config('  a: {command: x}\n'))
    assert sup.stop('a', 0.0) == (False, [], 'a is already stopped')
    assert sup.start('a', 0.0)[:2] == (True, [('spawn', 'a')])
    running(sup, 'a')
    assert sup.start('a', 1.0) == (False, [], 'a is already running')
    assert sup.restart('a', 1.0)[:2] == (True, [('kill', 'a'), ('spawn', 'a')])
    sup['a'].spawned(1.1)
    assert sup.stop('a', 2.0)[:2] == (True, [('kill', 'a')]) and sup['a'].state == State.STOPPED
    sup['a'].restarts.extend([2.5] * 3)          # its allowance used: the spawn failure exhausts it
    sup.spawn_failed('a', 3.0, 'gone')
    assert sup['a'].state == State.FAILED
    assert sup.restart('a', 3.5) == (False, [], 'a has failed: start it instead')


def test_a_service_that_cannot_be_spawned_fails_and_a_critical_one_escalates():
    sup = Supervisor(config('  a: {command: x, critical: true}\n'))
    now = 0.0
    for _ in range(3):                            # retried within its restart limit (review of session 34)
        decision = sup.spawn_failed('a', now, 'no such file')
        assert sup['a'].state == State.RESTARTING and decision.escalate is None
        now = sup.next_due()
        assert sup.due(now) == [('spawn', 'a')]
    decision = sup.spawn_failed('a', now, 'no such file')
    assert sup['a'].state == State.FAILED and 'restart limit exhausted after spawn' in sup.safe_state
    assert sup['a'].errors['spawn'] == 4


def test_an_alert_is_raised_once_per_fault_until_it_clears():
    sup = Supervisor(config('  a: {command: x, on_failure: alert, cpu_limit: 50%}\n'))
    running(sup, 'a')
    hot = ALIVE._replace(cpu_percent=90.0)
    assert sup.check('a', hot, 1.0, GB).actions == [('alert', 'a')]
    assert all(sup.check('a', hot, 1.0 + i * 0.01, GB) is None for i in range(1, 100))
    assert sup.check('a', ALIVE, 3.0, GB) is None                  # it cleared...
    assert sup.check('a', hot, 4.0, GB).actions == [('alert', 'a')]  # ...so it is alerted again
    assert sup['a'].errors['cpu_limit'] == 2 and sup['a'].state == State.RUNNING
    assert sup['a'].alerted == {'cpu_limit'} and sup['a'].reason.startswith('alerted (cpu_limit: CPU 90%')
    assert sup.check('a', ALIVE, 5.0, GB) is None and not sup['a'].alerted   # what diagnostics show as WARN, gone
    assert sup['a'].reason == 'running; the fault alerted (cpu_limit) has cleared'


def test_an_ok_heartbeat_withdraws_a_reported_error():
    sup = Supervisor(config('  a: {command: x, on_failure: alert}\n'))
    running(sup, 'a')
    sup['a'].heard(1.0, 'error', 'sensor lost')
    assert sup.check('a', ALIVE, 1.01, GB).kind == 'reported_error'
    sup['a'].heard(1.02, 'ok')
    assert sup.check('a', ALIVE, 1.03, GB) is None and not sup['a'].alerted


def test_a_service_terminated_or_out_of_restarts_terminates_what_must_not_run_without_it():
    for action, extra in (('terminate', ''), ('restart', ', restart_limit: 0')):
        sup = Supervisor(config('  tg: {command: x}\n  c4g: {command: y, on_failure: %s, terminate_with: [tg]%s}\n'
                                % (action, extra)))
        running(sup, 'tg')
        running(sup, 'c4g')
        decision = sup.fault('c4g', 'exit', '', 1.0)
        assert decision.actions[:2] == [('kill', 'tg'), ('kill', 'c4g')] and sup['tg'].state == State.STOPPED


def test_a_critical_service_terminated_with_a_failed_one_puts_the_system_in_the_safe_state():
    """The trajectory generator, critical, must not run without the trajectory sender: the sender's
    failure stops it, and a critical service stopped is the safe state (it was left stopped, shown
    STALE like an operator's stop, with no escalation)."""
    for action in ('restart', 'terminate'):
        sup = Supervisor(config('  tg: {command: x, critical: true}\n  c4g: {command: y, on_failure: %s, '
                                'terminate_with: [tg]}\n' % action))
        running(sup, 'tg')
        running(sup, 'c4g')
        decision = sup.fault('c4g', 'exit', 'status 1', 1.0)
        assert sup['tg'].state == State.STOPPED
        assert decision.escalate == sup.safe_state == 'tg (critical) terminated with c4g after its exit', action
    # Not critical: stopped with it, and no safe state.
    sup = Supervisor(config('  tg: {command: x}\n  c4g: {command: y, terminate_with: [tg]}\n'))
    running(sup, 'tg')
    running(sup, 'c4g')
    assert sup.fault('c4g', 'exit', '', 1.0).escalate is None and sup.safe_state is None


def test_dependants_are_restarted_transitively_but_stopped_ones_stay_stopped():
    sup = Supervisor(config('  a: {command: x, restart_with: [b, c]}\n  b: {command: y, restart_with: [d]}\n'
                            '  c: {command: z, autostart: false}\n  d: {command: w}\n'))
    for name in ('a', 'b', 'd'):
        running(sup, name)
    decision = sup.fault('a', 'exit', '', 1.0)
    assert [x for x in decision.actions if x[0] == 'spawn'] == [('spawn', 'a'), ('spawn', 'b'), ('spawn', 'd')]
    assert sup['c'].state == State.STOPPED


def test_no_sequence_of_faults_operator_commands_and_spawn_failures_breaks_the_state_machine():
    """Random sequences (seeded) over services with dependencies: every decision is carried out as the
    manager would, and no call ever meets a state it does not expect."""
    import random
    rng = random.Random(7)
    c = config('  tg: {command: x, critical: true}\n  pub: {command: y, on_failure: alert}\n'
               '  c4g: {command: z, terminate_with: [tg], restart_with: [pub], restart_limit: 2, restart_window: 5}\n'
               '  oms: {command: w, on_failure: terminate}\n'
               '  slow: {command: v, restart_delay: 0.3, restart_with: [pub], terminate_with: [oms]}\n')
    for _ in range(30):
        sup = Supervisor(c)
        now = 0.0
        for name in sup.services:
            sup[name].spawned(now)
        for _ in range(200):
            now += rng.uniform(0.0, 0.5)
            name = rng.choice(list(sup.services))
            s = sup[name]
            move = rng.choice(('heard', 'error', 'exit', 'check', 'start', 'stop', 'restart', 'spawn_failed', 'clear'))
            before = {n: other.state for n, other in sup.services.items()}
            actions = []
            if move == 'heard':
                s.heard(now, 'ok')
            elif move == 'error':
                s.heard(now, 'error', 'x')
            elif move in ('exit', 'check'):
                sample = ALIVE._replace(alive=False, exit_code=1) if move == 'exit' else ALIVE
                decision = sup.check(name, sample, now, GB) if s.state in (State.STARTING, State.RUNNING) else None
                actions = decision.actions if decision else []
            elif move in ('start', 'stop', 'restart'):
                actions = getattr(sup, move)(name, now)[1]
            elif move == 'spawn_failed' and s.state in (State.STOPPED, State.RESTARTING):
                actions = sup.spawn_failed(name, now, 'no such file').actions
            elif move == 'clear':
                sup.clear_safe_state(now)
            actions += sup.due(now)          # held restarts, as the manager's loop spawns them
            spawned = set()
            for verb, target in actions:     # as the manager carries them out
                if verb == 'spawn':
                    sup[target].spawned(now)
                    spawned.add(target)
                else:   # never a spawn, then a kill of the same service in one plan (left with no process)
                    assert target not in spawned, (move, name, actions)
            # a critical service a fault or an operator's stop or restart stopped is the safe state
            if move in ('exit', 'check', 'stop', 'restart'):
                for other in sup.services.values():
                    if other.config['critical'] and other.state in (State.STOPPED, State.FAILED) \
                            and before[other.name] not in (State.STOPPED, State.FAILED):
                        assert sup.safe_state is not None, (move, name, actions)
        for s in sup.services.values():
            assert all((old, new) in EDGES for _, old, new, _ in s.history)


# -- state restoration -----------------------------------------------------------------------------
def in_range(state):
    return None if 0 <= state.get('position', -1) <= 10 else 'position %r outside 0 .. 10' % state.get('position')


def test_a_saved_state_is_restored_after_its_checks(tmp_path):
    store = StateStore(str(tmp_path / 'a.json'), in_range)
    assert store.load() == (None, 'no saved state')
    store.save({'position': 4.5, 'tool': 'gripper'})
    assert store.load() == ({'position': 4.5, 'tool': 'gripper'}, None)


@pytest.mark.parametrize('corrupt,why', [
    (lambda text: text.replace('4.5', '4.6'), 'checksum mismatch'),
    (lambda text: text[:len(text) // 2], 'not a state record'),
    (lambda text: '', 'not a state record'),
])
def test_a_corrupt_state_falls_back_to_a_clean_start_saying_why(tmp_path, corrupt, why):
    path = tmp_path / 'a.json'
    store = StateStore(str(path), in_range)
    store.save({'position': 4.5})
    path.write_text(corrupt(path.read_text()))
    state, reason = store.load()
    assert state is None and why in reason


def test_a_state_out_of_range_is_not_restored(tmp_path):
    store = StateStore(str(tmp_path / 'a.json'), in_range)
    store.save({'position': 42})
    assert store.load() == (None, 'saved state out of range: position 42 outside 0 .. 10')


def test_the_manager_tells_a_service_where_its_state_is_and_whether_to_restore_it(tmp_path):
    store, restore = from_environment('/default', environ={'AFT_STATE_FILE': str(tmp_path / 's.json'),
                                                           'AFT_RESTORE_STATE': '1'})
    assert store.path == str(tmp_path / 's.json') and restore
    store, restore = from_environment('/default', environ={})
    assert store.path == '/default' and not restore


def test_saving_replaces_the_file_whole(tmp_path):
    store = StateStore(str(tmp_path / 'a.json'))
    for i in range(20):
        store.save({'i': i})
    assert json.loads(json.loads((tmp_path / 'a.json').read_text())['state']) == {'i': 19}
    assert [p.name for p in tmp_path.iterdir()] == ['a.json']   # no temporary file left


def test_a_held_restart_holds_the_dependants_too_and_spawns_them_with_it():
    sup = Supervisor(config('  c4g: {command: z, restart_with: [pub], restart_delay: 0.5}\n'
                            '  pub: {command: y}\n'))
    running(sup, 'c4g')
    running(sup, 'pub')
    decision = sup.check('c4g', ALIVE._replace(alive=False, exit_code=1), 1.0, GB)
    assert decision.actions == [('kill', 'c4g'), ('kill', 'pub')]        # nothing spawned yet
    assert sup['pub'].state == State.RESTARTING and sup.due(1.4) == []
    assert sup.due(1.5) == [('spawn', 'c4g'), ('spawn', 'pub')]


# -- review of stop 39 -----------------------------------------------------------------------------
def test_an_operators_restart_or_stop_that_leaves_a_critical_service_down_is_the_safe_state():
    """`servicectl restart c4g` (the README's example) terminates the trajectory generator, which must
    not run without it, and leaves it stopped: it was down with no safe state, shown like a deliberate stop."""
    c = config('  tg: {command: x, critical: true}\n  c4g: {command: y, terminate_with: [tg]}\n')
    sup = Supervisor(c)
    running(sup, 'tg')
    running(sup, 'c4g')
    ok, actions, message = sup.restart('c4g', 1.0)
    assert ok and actions[:2] == [('kill', 'tg'), ('kill', 'c4g')] and sup['tg'].state == State.STOPPED
    assert sup.safe_state == "tg (critical) terminated by an operator's restart of c4g" and 'safe state' in message
    sup = Supervisor(c)
    running(sup, 'tg')
    running(sup, 'c4g')
    ok, actions, _ = sup.stop('c4g', 1.0)
    assert ok and ('kill', 'tg') in actions and sup['tg'].state == State.STOPPED and sup.safe_state
    sup = Supervisor(c)
    running(sup, 'tg')
    assert sup.stop('tg', 1.0)[0] and sup.safe_state == 'tg (critical) stopped by an operator (with tg)'


def test_what_must_not_run_without_a_terminated_service_is_terminated_transitively():
    sup = Supervisor(config('  a: {command: x, on_failure: terminate, terminate_with: [b]}\n'
                            '  b: {command: y, terminate_with: [c]}\n  c: {command: z}\n'))
    for name in 'abc':
        running(sup, name)
    decision = sup.fault('a', 'exit', '', 1.0)
    assert [t for verb, t in decision.actions if verb == 'kill'] == ['b', 'c', 'a']   # c ran on without b before
    assert all(sup[n].state == State.STOPPED for n in 'abc')


def test_an_alerted_error_hides_no_later_hang_nor_limit():
    sup = Supervisor(config('  a: {command: x, on_failure: alert, heartbeat_timeout: 0.1, memory_limit: 100MB}\n'))
    running(sup, 'a')
    sup['a'].heard(0.02, 'error', 'sensor lost')
    assert sup.check('a', ALIVE, 0.05, GB).kind == 'reported_error'
    # It hangs: no beat since 0.02 s. Before, the alerted error hid the timeout for ever.
    assert sup.check('a', ALIVE, 1.0, GB).kind == 'heartbeat_timeout'
    assert sup.check('a', ALIVE._replace(rss=200e6), 2.0, GB).kind == 'memory_limit'
    assert sup['a'].errors == {'reported_error': 1, 'heartbeat_timeout': 1, 'memory_limit': 1}
    assert sup.check('a', ALIVE._replace(rss=200e6), 3.0, GB) is None   # each alerted once while it lasts
    sup['a'].heard(3.1, 'ok')
    assert sup.check('a', ALIVE, 3.15, GB) is None and not sup['a'].alerted


def test_a_manager_started_again_keeps_the_safe_state_and_the_services_left_down():
    """Who watches the watcher: a manager killed and started again under the same name lifted the safe
    state and restarted a critical service whose restart limit was exhausted, with nothing said."""
    c = config('  a: {command: x, critical: true, restart_limit: 0}\n  b: {command: y}\n  d: {command: z}\n'
               '  e: {command: w, autostart: false}\n')
    sup = Supervisor(c)
    for name in 'abd':
        running(sup, name)
    sup.fault('a', 'exit', 'status 1', 1.0)
    sup.stop('b', 2.0)
    assert sup['a'].state == State.FAILED and sup.safe_state
    record = json.loads(json.dumps(sup.record()))          # as written to, and read from, its file
    assert set(record['down']) == {'a', 'b'}                # d runs; e was never started: not held
    again = Supervisor(c)
    assert again.restore(record, 0.0) == ['a', 'b']
    assert again.safe_state.startswith("held from the manager's previous run: a: restart limit exhausted")
    assert 'down in the manager\'s previous run' in again['a'].reason
    assert not again.clear_safe_state(1.0)[0]               # a, critical, is down: start it first
    assert again.start('a', 1.0)[0]
    with pytest.raises(ServiceConfigError, match='not a mapping'):
        Supervisor(c).restore(['a'], 0.0)
    # Killed again before an operator did anything: still held, the reasons not nested.
    third = Supervisor(c)
    assert third.restore(json.loads(json.dumps(_after_restore(c, record))), 0.0) == ['a', 'b']
    assert third.safe_state.count('held from') == 1 and third['b'].reason.count('down in') == 1


def _after_restore(c, record):
    again = Supervisor(c)
    again.restore(record, 0.0)
    return again.record()


def test_a_transitive_terminate_with_that_would_kill_what_a_restart_starts_is_refused():
    with pytest.raises(ServiceConfigError, match='would start and stop b at once.*through'):
        config('  a: {command: x, restart_with: [b, d]}\n  b: {command: y}\n  d: {command: z, terminate_with: [e]}\n'
               '  e: {command: w, terminate_with: [b]}\n')
