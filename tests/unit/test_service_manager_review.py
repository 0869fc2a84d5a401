"""The service manager's fixes of the review of session 34, each failing on the code before it: one
manager of a name at a time and a shutdown that removes only its own files, a restart limit a back-off cannot make unreachable, a spawn failure retried as a fault,
memory judged while starting, and configurations and records refused naming the problem. No master."""
import errno
import os
import sys
import threading

import pytest

from aft_service_manager import channel
from aft_service_manager.services import Sample, ServiceConfigError, State, Supervisor, parse_config

ALIVE = Sample(alive=True, exit_code=None, stopped=False, cpu_percent=5.0, rss=50e6)
DEAD = ALIVE._replace(alive=False, exit_code=1)
GB = 1e9


def config(services, manager=''):
    return parse_config((('manager:\n' + manager) if manager else '') + 'services:\n' + services, source='test.yaml')


def running(sup, name, now=0.0):
    sup[name].spawned(now)
    sup[name].heard(now + 0.01, 'ok')
    assert sup[name].state == State.RUNNING


# -- 1: two managers of one name -------------------------------------------------------------------
def _new_manager(tmp_path, monkeypatch, made):
    """ServiceManagerNode() as run_node builds it, its parameters and process trees faked (no master)."""
    from aft_service_manager.ros import service_manager_node as node_module
    path = tmp_path / 'services.yaml'
    path.write_text('manager: {state_dir: %s, kill_timeout: 0.1}\nservices:\n  a: {command: x}\n' % (tmp_path / 'state'))
    monkeypatch.setattr(node_module, 'param', lambda name, convert, default=None, required=False:
                        str(path) if name == 'config' else default)
    monkeypatch.setattr(node_module.tree, 'make', lambda owner: made.append(owner) or object())
    monkeypatch.setattr(node_module, 'LOCK_WAIT', 0.2, raising=False)
    return node_module.ServiceManagerNode()


def test_a_second_manager_of_the_same_name_refuses_to_start_naming_the_first(tmp_path, monkeypatch):
    from aft_ftm.errors import ConfigError
    made = []
    first = _new_manager(tmp_path, monkeypatch, made)
    try:
        with pytest.raises(ConfigError, match='another service manager of this name \\(pid %d\\)' % os.getpid()):
            _new_manager(tmp_path, monkeypatch, made)
        assert len(made) == 1                       # the second touched none of the first's trees
    finally:
        os.close(first.name_lock)
    os.close(_new_manager(tmp_path, monkeypatch, made).name_lock)   # the first gone: a manager starts


class _Trees(object):
    def __init__(self, leftovers):
        self.left, self.killed = leftovers, []

    def leftovers(self):
        return list(self.left)

    def kill(self, handle, timeout):
        self.killed.append(handle)

    def close(self, timeout):
        pass


def test_a_shutdown_after_a_successor_started_leaves_the_successor_s_files_and_trees(tmp_path):
    """A mis-sequenced shutdown (the successor already wrote its pid file and record, and made its
    trees) removed the successor's files and killed its services."""
    from aft_service_manager import trust
    from aft_service_manager.ros.service_manager_node import ServiceManagerNode
    node = ServiceManagerNode.__new__(ServiceManagerNode)
    node.unacted, node.counted, node.already_counted = {}, set(), set()   # (the set-up's lost instances)
    node.lock, node.children, node.spares, node.stopping = threading.RLock(), {}, {}, {}
    node.config = {'manager': {'kill_timeout': 0.1}}
    node.wake_r, node.wake_w = os.pipe()
    node.local, node.safe_pub = None, None
    node.supervisor = Supervisor(config('  a: {command: x}\n'))
    node.supervisor._escalate('a: restart limit exhausted', 0.0)   # held: still the successor's record stays
    node.pid_file, node.record_file = str(tmp_path / 'm.pids'), str(tmp_path / 'm.record')
    node.own = {node.pid_file: trust.write_private_json(node.pid_file, {}),
                node.record_file: trust.write_private_json(node.record_file, {})}
    node.own_trees = ['mine-1']
    node.tree = _Trees(['mine-1', 'successor-2'])
    for path in (node.pid_file, node.record_file):   # the successor's, written since
        trust.write_private_json(path, {'successor': True})
    node.shutdown()
    assert os.path.exists(node.pid_file) and trust.read_private_json(node.record_file) == {'successor': True}
    assert node.tree.killed == ['mine-1']
    os.close(node.wake_r)
    os.close(node.wake_w)


def test_a_manager_s_socket_closed_after_its_successor_bound_its_own_leaves_it(tmp_path):
    path = channel.socket_path(str(tmp_path), 'manager_x')
    old = channel.ManagerSocket(path)
    new = channel.ManagerSocket(path)   # the successor's (it removed the old file)
    old.close()
    assert os.path.exists(path)
    new.close()
    assert not os.path.exists(path)


# -- 3: the restart limit with a back-off ---------------------------------------------------------
def test_a_back_off_never_makes_the_restart_limit_unreachable():
    """restart_delay 25 s capped at 25 s spaced the faults beyond 60 s / 3: a service failing at once
    after each start looped for ever (144 faults an hour), never FAILED, no safe state."""
    sup = Supervisor(config('  a: {command: x, critical: true, restart_delay: 25, restart_delay_max: 25}\n'))
    now, faults = 0.0, 0
    while sup['a'].state != State.FAILED and faults < 20:
        running(sup, 'a', now)
        decision = sup.check('a', DEAD, now + 0.5, GB)
        faults += 1
        if sup['a'].state == State.RESTARTING:
            now = sup.next_due()
            assert sup.due(now) == [('spawn', 'a')]
    assert sup['a'].state == State.FAILED and faults == 4
    assert 'restart limit exhausted' in decision.escalate and sup.safe_state


def test_restarts_far_apart_in_the_service_s_own_time_still_leave_the_window():
    sup = Supervisor(config('  a: {command: x, restart_limit: 1, restart_window: 5, restart_delay: 25, '
                            'restart_delay_max: 25, stable_after: 100}\n'))
    now = 0.0
    for _ in range(3):   # each runs 10 s: beyond the window, whatever the holds
        running(sup, 'a', now)
        assert sup.check('a', DEAD, now + 10.0, GB).escalate is None
        now = sup.next_due()
        sup.due(now)


# -- 4: a spawn that fails -------------------------------------------------------------------------
def test_a_transient_spawn_failure_is_retried_after_a_delay_and_the_service_runs():
    sup = Supervisor(config('  a: {command: x}\n'))
    decision = sup.spawn_failed('a', 0.0, '[Errno 11] Resource temporarily unavailable')
    assert decision.kind == 'spawn' and decision.escalate is None and ('spawn', 'a') not in decision.actions
    assert sup['a'].state == State.RESTARTING and sup.next_due() >= 1.0
    assert sup.due(sup.next_due()) == [('spawn', 'a')]
    running(sup, 'a', 1.0)
    assert sup['a'].errors['spawn'] == 1


def test_a_spawn_failing_for_good_exhausts_the_limit_and_escalates_a_service_that_is_not_critical():
    sup = Supervisor(config('  a: {command: x, restart_limit: 2}\n'))
    now, decision = 0.0, None
    for _ in range(3):
        decision = sup.spawn_failed('a', now, 'no such file')
        if sup['a'].state == State.RESTARTING:
            now = sup.next_due()
            sup.due(now)
    assert sup['a'].state == State.FAILED and 'restart limit exhausted after spawn' in decision.escalate
    assert sup.safe_state == decision.escalate


def test_the_manager_reports_a_spawn_failure_as_a_fault_and_holds_its_retry(tmp_path):
    from aft_service_manager.ros.service_manager_node import ServiceManagerNode
    node = ServiceManagerNode.__new__(ServiceManagerNode)
    node.unacted, node.counted, node.already_counted = {}, set(), set()   # (the set-up's lost instances)
    node.config = config('  a: {command: x}\n', '  state_dir: %s\n' % tmp_path)
    node.supervisor, node.closing, node.children, node.spares = Supervisor(node.config), False, {}, {}
    node.published_safe, node.published_also, node.recorded = None, 0, node.supervisor.record()
    node.record_file, node.own = str(tmp_path / 'm.record'), {}
    events = []
    node._event = lambda event, name, detail, now, **extra: events.append(dict(extra, event=event, service=name))

    def eagain(name, spare):
        raise OSError(errno.EAGAIN, 'Resource temporarily unavailable')
    node._start_process = eagain
    node._spawn('a', 5.0)
    assert [(e['event'], e.get('kind')) for e in events] == [('fault', 'spawn')]
    assert node.supervisor['a'].state == State.RESTARTING and node.supervisor.next_due() >= 6.0
    # Recorded at once, for a manager started again: the fault counts against its restart limit too.
    from aft_service_manager import trust
    assert trust.read_private_json(node.record_file)['counts']['a']['errors'] == {'spawn': 1}


# -- 6: memory while starting ----------------------------------------------------------------------
def test_memory_over_its_limit_is_a_fault_while_the_service_starts():
    sup = Supervisor(config('  a: {command: x, heartbeat_timeout: 0.1, start_timeout: 30, memory_limit: 100MB}\n'))
    sup['a'].spawned(0.0)
    decision = sup.check('a', ALIVE._replace(rss=2 * GB), 0.5, GB)
    assert decision is not None and decision.kind == 'memory_limit' and sup['a'].state == State.RESTARTING


def test_memory_alerted_while_starting_leaves_the_service_starting_and_alerted_once():
    sup = Supervisor(config('  a: {command: x, heartbeat_timeout: 0.1, on_failure: alert, memory_limit: 100MB}\n'))
    sup['a'].spawned(0.0)
    fat = ALIVE._replace(rss=2 * GB)
    assert sup.check('a', fat, 0.5, GB).actions == [('alert', 'a')] and sup['a'].state == State.STARTING
    assert sup.check('a', fat, 0.6, GB) is None
    assert sup.check('a', fat, 6.0, GB).kind == 'start_timeout'   # still judged by its start timeout


# -- 7, 9, 10: configurations ------------------------------------------------------------------------
@pytest.mark.parametrize('services,message', [
    ('  a: {command: x, start_grace: 10, start_timeout: 5}\n', 'start_grace 10 s exceeds start_timeout 5 s'),
    ('  a: {command: x, memory_limit: %d}\n' % 10 ** 400, 'services.a.memory_limit must be a finite number'),
    ('  a: {command: x, heartbeat_timeout: %d}\n' % 10 ** 400, 'services.a.heartbeat_timeout must be a finite'),
    ('  a: {command: x, memory_limit: %sMB}\n' % ('9' * 400), 'services.a.memory_limit must be a finite number'),
    ("  a: {command: ['']}\n", 'the program \\(its first argument\\) is empty'),
    ('  a: {command: x, warm_spare: true}\n', 'warm_spare needs spare_args'),
    ('  a: {command: \'sh -c "echo hi\'}\n', 'cannot be split into arguments'),
])
def test_a_configuration_the_review_found_accepted_is_refused_naming_the_problem(services, message):
    with pytest.raises(ServiceConfigError, match=message):
        config(services)


def test_a_command_string_is_split_as_a_shell_would():
    c = config('  a: {command: \'sh -c "echo hi"\', program: "logger \'a failed\'", on_failure: run}\n')
    assert c['services']['a']['command'] == ['sh', '-c', 'echo hi']
    assert c['services']['a']['program'] == ['logger', 'a failed']
    # with heartbeats, start_grace is not used: any value is accepted
    config('  a: {command: x, heartbeat_timeout: 0.1, start_grace: 10, start_timeout: 5}\n')


# -- 11: a malformed record ------------------------------------------------------------------------
@pytest.mark.parametrize('record', [{'safe_state': 1}, {'down': {'a': {'reason': 5}}}, {'down': {'a': 'x'}},
                                    {'safe_state': ['x'], 'down': {}}])
def test_a_malformed_record_is_refused_and_changes_nothing(record):
    sup = Supervisor(config('  a: {command: x}\n'))
    with pytest.raises(ServiceConfigError, match='record is malformed'):
        sup.restore(record, 0.0)
    assert sup.safe_state is None and not sup['a'].held_down


def test_a_manager_whose_record_is_malformed_starts_in_the_safe_state(tmp_path):
    from aft_service_manager import trust
    from aft_service_manager.ros.service_manager_node import ServiceManagerNode
    node = ServiceManagerNode.__new__(ServiceManagerNode)
    node.unacted, node.counted, node.already_counted = {}, set(), set()   # (the set-up's lost instances)
    node.supervisor = Supervisor(config('  a: {command: x}\n'))
    node.record_file, node.own = str(tmp_path / 'm.record'), {}
    trust.write_private_json(node.record_file, {'safe_state': 1, 'down': {}})
    assert node._restore() == []
    assert 'record of the manager\'s previous run is not usable' in node.supervisor.safe_state


# -- 12: held spawns in dependency order -----------------------------------------------------------
def test_held_spawns_come_in_dependency_order_whatever_the_config_order():
    sup = Supervisor(config('  dep: {command: y}\n  base: {command: x, restart_with: [dep], restart_delay: 3}\n'))
    running(sup, 'dep')
    running(sup, 'base')
    sup.check('base', DEAD, 0.5, GB)
    assert sup.due(3.5) == [('spawn', 'base'), ('spawn', 'dep')]


if __name__ == '__main__':
    sys.exit(pytest.main([__file__, '-q']))


# -- review of session 36 ----------------------------------------------------------------------------
def test_a_dependant_is_never_spawned_before_the_service_it_is_restarted_with():
    """Its spawn failing (retried after a hold), or its back-off longer than the dependant's own: the
    dependant was spawned first, ran against nothing, and was not restarted after it."""
    import random
    seed = random.randrange(1 << 16)
    rng = random.Random(seed)
    sup = Supervisor(config('  a: {command: x, restart_with: [b]}\n  b: {command: y}\n'))
    running(sup, 'a')
    running(sup, 'b')
    now = rng.uniform(1.0, 5.0)
    decision = sup.fault('a', 'exit', 'status 1', now)
    assert decision.actions == [('kill', 'a'), ('spawn', 'a'), ('kill', 'b'), ('spawn', 'b')], (seed, decision.actions)
    # The caller carries them out in order: a's spawn fails (retried after at least SPAWN_RETRY).
    sup.spawn_failed('a', now, 'EAGAIN')
    assert sup['a'].state == State.RESTARTING and sup['a'].spawn_at >= now + 1.0, seed
    assert not sup.may_spawn('b', now) and sup['b'].spawn_at == sup['a'].spawn_at, seed
    assert sup.due(sup['a'].spawn_at) == [('spawn', 'a'), ('spawn', 'b')], seed   # then a before b
    sup['a'].spawned(sup['a'].spawn_at or now + 1.0)
    assert sup.may_spawn('b', now + 1.0), seed                       # a is starting: b may go
    # b in a back-off of its own, shorter than a's: held until a's is due.
    sup2 = Supervisor(config('  a: {command: x, restart_with: [b], restart_delay: 3.0}\n'
                             '  b: {command: y, restart_delay: 0.1}\n'))
    running(sup2, 'a')
    running(sup2, 'b')
    sup2['b'].consecutive = 1
    sup2.fault('b', 'exit', 'status 1', 10.0)
    sup2['a'].consecutive = 1
    sup2.fault('a', 'exit', 'status 1', 10.01)
    b_due = sup2['b'].spawn_at
    assert b_due is not None and b_due < sup2['a'].spawn_at, (seed, b_due, sup2['a'].spawn_at)
    assert sup2.due(b_due) == [('spawn', 'b')] and not sup2.may_spawn('b', b_due), seed
    assert sup2.due(sup2['a'].spawn_at) == [('spawn', 'a'), ('spawn', 'b')], seed


def test_an_alerted_error_while_starting_is_alerted_once_not_at_every_wake():
    sup = Supervisor(config('  a: {command: x, heartbeat_timeout: 0.1, on_failure: alert, start_timeout: 5}\n'))
    sup['a'].spawned(0.0)
    sup['a'].heard(0.1, 'error', 'calibration failed')
    assert sup.check('a', ALIVE, 0.2, GB).actions == [('alert', 'a')] and sup['a'].state == State.STARTING
    assert all(sup.check('a', ALIVE, t, GB) is None for t in (0.21, 0.3, 1.0, 4.9))
    assert sum(sup['a'].errors.values()) == 1
    assert sup.check('a', ALIVE, 5.1, GB).kind == 'start_timeout'


def test_a_second_reason_for_the_safe_state_is_kept_and_said_when_it_is_cleared():
    sup = Supervisor(config('  a: {command: x, restart_limit: 1}\n  b: {command: y, restart_limit: 1}\n'))
    running(sup, 'a')
    running(sup, 'b')
    for name in ('a', 'b'):
        sup.fault(name, 'exit', 'status 1', 1.0)
        running(sup, name, 2.0)
        sup.fault(name, 'exit', 'status 1', 3.0)   # the limit exhausted: safe state
    assert sup.safe_state.startswith('a: restart limit exhausted') and sup.also_unsafe == [
        'b: restart limit exhausted after exit'], (sup.safe_state, sup.also_unsafe)
    ok, message = sup.clear_safe_state(4.0)
    assert ok and 'a: restart limit' in message and 'b: restart limit' in message, message
    assert sup.safe_state is None and sup.also_unsafe == []


def test_a_service_down_after_a_fault_is_degraded_an_operator_s_stop_is_not():
    sup = Supervisor(config('  a: {command: x, on_failure: terminate}\n  b: {command: y}\n  c: {command: z}\n'))
    for name in 'abc':
        running(sup, name)
    sup.fault('a', 'exit', 'status 1', 1.0)
    sup.stop('b', 1.0)
    assert list(sup.degraded()) == ['a'] and 'terminate' in sup.degraded()['a'], sup.degraded()


# -- review of session 36: counts kept across the manager's own restarts ---------------------------
@pytest.mark.parametrize('seed', [int(os.environ.get('AFT_SEED', 0)) or s for s in range(3901, 3921)])
def test_a_manager_started_again_keeps_each_service_s_restart_allowance_errors_and_back_off(seed):
    """A service that fails at every start, its manager killed and started again after some of its
    faults (drawn from the seed: a manager crashing with its service, or killed by it). Before, each
    new manager gave the service a fresh restart allowance, fresh error counts and no back-off: a
    crash loop never reached FAILED and never the safe state. Now it is FAILED at the same fault as
    under one manager, with the same counts and the same back-off delays."""
    import json
    import random
    rng = random.Random(seed)
    c = config('  a: {command: x, critical: true, restart_limit: %d, restart_window: 60, restart_delay: 0.5, '
               'restart_delay_factor: 2, restart_delay_max: 4, stable_after: 100}\n' % rng.randint(1, 5))
    runs = [rng.uniform(0.1, 2.0) for _ in range(12)]   # how long each start runs before it fails

    def crash_loop(kill_after):
        sup, now, delays = Supervisor(c), 1000.0, []
        for fault, run in enumerate(runs):
            running(sup, 'a', now)
            now += run
            sup.check('a', DEAD, now, GB)
            if sup['a'].state == State.FAILED:
                return fault + 1, dict(sup['a'].errors), delays, sup.safe_state
            delays.append(round(sup.next_due() - now, 6))
            now = sup.next_due()
            assert sup.due(now) == [('spawn', 'a')], 'seed %d' % seed
            if fault in kill_after:   # the manager dies; the next one reads its record (as a file would hold it)
                record = json.loads(json.dumps(sup.record()))
                sup = Supervisor(c)
                assert sup.restore(record, now) == [], 'seed %d: nothing was down' % seed
        return None, dict(sup['a'].errors), delays, sup.safe_state

    alone = crash_loop(kill_after=())
    killed = crash_loop(kill_after={f for f in range(12) if rng.random() < 0.6} | {0})
    assert alone[0] == c['services']['a']['restart_limit'] + 1 and alone[3], 'seed %d: %r' % (seed, alone)
    assert killed == alone, 'seed %d: one manager %r, managers started again %r' % (seed, alone, killed)


@pytest.mark.parametrize('counts', [[], {'a': 3}, {'a': {'errors': {'exit': -1}}}, {'a': {'errors': {'exit': True}}},
                                    {'a': {'restarts': ['soon']}}, {'a': {'restarts': [float('nan')]}},
                                    {'a': {'consecutive': 1.5}}, {'a': {'errors': []}}])
def test_a_record_with_malformed_counts_is_refused_and_changes_nothing(counts):
    sup = Supervisor(config('  a: {command: x}\n'))
    with pytest.raises(ServiceConfigError, match='record is malformed.*counts'):
        sup.restore({'safe_state': None, 'down': {}, 'counts': counts}, 0.0)
    assert sup['a'].errors == {} and not sup['a'].restarts and sup['a'].consecutive == 0 and sup.safe_state is None


def test_restarts_recorded_on_a_clock_since_started_again_count_as_now():
    """A record from before a reboot holds times ahead of the new monotonic clock: they count as
    restarts of now, within the window, never forgotten early."""
    sup = Supervisor(config('  a: {command: x, restart_limit: 1, restart_window: 60}\n'))
    sup.restore({'safe_state': None, 'down': {}, 'counts': {'a': {'errors': {'exit': 1}, 'restarts': [5e6]}}}, 10.0)
    running(sup, 'a', 10.0)
    assert sup.check('a', DEAD, 69.0, GB).escalate and sup['a'].state == State.FAILED


def _failed_twice(c):
    """A supervisor whose service a (restart_limit 1) failed twice: FAILED."""
    sup = Supervisor(c)
    for t in (0.0, 2.0):
        running(sup, 'a', t)
        sup.check('a', DEAD, t + 1.0, GB)
        if sup['a'].state == State.RESTARTING:
            sup.due(sup.next_due())
    return sup


def test_a_service_failed_in_the_previous_run_gets_a_fresh_allowance_when_an_operator_starts_it():
    """Review of session 38: restored as held down (STOPPED) with its restarts, it was not FAILED, so
    an operator's start kept them, and its first fault failed it again (the safe state, if critical),
    where one manager would have restarted it."""
    import json
    c = config('  a: {command: x, critical: true, restart_limit: 1, restart_window: 60}\n')
    sup = _failed_twice(c)
    assert sup['a'].state == State.FAILED and sup.safe_state
    record = json.loads(json.dumps(sup.record()))
    for _ in range(2):   # the manager started again twice before an operator comes
        again = Supervisor(c)
        assert again.restore(record, 5.0) == ['a']
        record = json.loads(json.dumps(again.record()))
    assert again.start('a', 6.0)[0] and not again['a'].restarts
    assert again.clear_safe_state(6.5)[0] is False   # (a is not running yet)
    running(again, 'a', 6.0)
    assert again.clear_safe_state(6.5)[0]
    assert again.check('a', DEAD, 7.0, GB).escalate is None and again['a'].state == State.RESTARTING


def test_counts_beyond_a_float_or_a_fault_run_past_any_delay_are_refused_or_capped():
    sup = Supervisor(config('  a: {command: x}\n'))
    for counts in ({'a': {'restarts': [-10 ** 400]}}, {'a': {'consecutive': 10 ** 9}}):
        with pytest.raises(ServiceConfigError, match='counts'):
            sup.restore({'counts': counts}, 0.0)
    slow = Supervisor(config('  a: {command: x, restart_delay: 1, restart_delay_factor: 10, restart_delay_max: 30}\n'))
    slow['a'].consecutive = 10 ** 6   # (a float overflow raised in fault(), the service stuck in ERROR)
    assert slow['a'].restart_delay() == 30


def test_a_service_failed_in_the_previous_run_is_restarted_only_by_a_start_and_only_once_renewed():
    """Review of session 38: `restart` of it was accepted (one manager refuses a FAILED one's: start
    it instead) without renewing its allowance; and the flag outlived its spawn, so a later stop
    and start of a service that had not failed since renewed it wrongly."""
    import json
    c = config('  a: {command: x, restart_limit: 1, restart_window: 60}\n')
    sup = _failed_twice(c)
    again = Supervisor(c)
    again.restore(json.loads(json.dumps(sup.record())), 5.0)
    ok, _, why = again.restart('a', 5.5)
    assert not ok and 'start it instead' in why
    assert again.start('a', 6.0)[0]
    running(again, 'a', 6.0)
    again.check('a', DEAD, 7.0, GB)                    # one restart within the renewed allowance
    again.due(again.next_due())
    running(again, 'a', 8.0)
    again.stop('a', 9.0)
    assert again.start('a', 9.5)[0] and len(again['a'].restarts) == 1   # not renewed again


def test_a_long_run_of_faults_is_recorded_capped_and_taken_back():
    import json
    sup = Supervisor(config('  a: {command: x, on_failure: alert}\n'))
    sup['a'].consecutive = 5 * 10 ** 6
    record = json.loads(json.dumps(sup.record()))
    again = Supervisor(config('  a: {command: x, on_failure: alert}\n'))
    again.restore(record, 0.0)
    assert again['a'].consecutive == 10 ** 6
