"""The adaptation transaction without a master: its edges, its decisions carried out on a fake
system, rollback order, interrupts at random steps (seeded), lost leases, failing undos."""
import itertools
import os
import random

import pytest

from aft_ftm import adaptation
from aft_ftm.transaction import EDGES, TERMINAL, Action, Outcome, State, Transaction, TransactionError
from adaptation_scripts import COMPOSE_PROMOTING as COMPOSE

SEED = int(os.environ.get('AFT_SEED', random.SystemRandom().randrange(2 ** 32)))


class FakeSystem(object):
    """What an adaptation changes, as plain sets and dicts: steps done on it, and undone."""

    def __init__(self):
        self.running = {'/%s/%s' % (s, n) for s in ('master', 'slave')
                        for n in ('protocol', 'proceed', 'before', 'after', 'recovery')}
        self.suspended = set()
        self.bindings = {('/master/proceed', 'inp'): '/master/bfr2prd', ('/slave/proceed', 'inp'): '/slave/bfr2prd'}
        self.promotes = {'/master/recovery': ('/master/before', '/master/after'),
                         '/slave/recovery': ('/slave/before', '/slave/after')}
        self.pids = itertools.count(100)

    def snapshot(self):
        return (frozenset(self.running), frozenset(self.suspended), dict(self.bindings), dict(self.promotes))

    def do(self, step):
        if step.action == 'suspend':
            self.suspended.add(step.target)
            return 0
        if step.action == 'resume':
            self.suspended.discard(step.target)
            return 0
        if step.action == 'launch':
            ns = dict(step.detail.args)['ns']
            self.running |= {ns + '/protocol', ns + '/after'}
            return ns
        if step.action == 'wait_launched':
            return 2
        if step.action == 'rebind':
            bind = step.detail
            previous = self.bindings.pop((bind.node, bind.port), '')
            if bind.activate:
                self.bindings[bind.node, bind.port] = bind.topic
            return previous
        if step.action == 'promote':
            previous = self.promotes[step.target]
            self.promotes[step.target] = tuple(step.detail.nodes)
            return list(previous)
        if step.action == 'kill':
            self.running.remove(step.target)
            return {'pid': next(self.pids)}
        raise ValueError(step.action)

    def undo(self, step):
        if step.action == 'resume':
            self.suspended.discard(step.target)
        elif step.action == 'stop_launch':
            self.running -= {step.detail + '/protocol', step.detail + '/after'}
        elif step.action == 'respawn':
            self.running.add(step.target)
        elif step.action == 'restore_binding':
            bind, previous = step.detail
            self.bindings.pop((bind.node, bind.port), None)
            if previous:
                self.bindings[bind.node, bind.port] = previous
        elif step.action == 'restore_promote':
            self.promotes[step.target] = tuple(step.detail)
        else:
            raise ValueError(step.action)
        return 'undone'


class Clock(object):
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        self.t += 0.001
        return self.t


def drive(tx, system, clock, fail=None, interrupt_before=None, interrupt_during=None, lose_before=None,
          undo_fails=()):
    """Carry out tx's decisions on system, as the engine does. fail: (action, target) of a step
    that fails; interrupt_before / lose_before: the number of groups run before an interrupt or a
    lost lease is seen; interrupt_during: (action, target) of a step that fails interrupted.
    Returns [(kind, step)] of what was carried out, in order."""
    log, groups_run, interrupted = [], 0, ''
    tx.start(clock())
    while True:
        if interrupt_before is not None and groups_run >= interrupt_before:
            interrupted = 'SIGINT'
        lost = {'/master/protocol': 'lease ran out'} if lose_before is not None and groups_run >= lose_before else {}
        decision = tx.next(clock(), interrupted, lost)
        if decision.action is Action.END:
            return log
        if decision.action is Action.UNDO:
            step = decision.steps[0]
            log.append(('undo', step))
            if (step.action, step.target) in undo_fails:
                tx.undone(step, False, 'no answer', clock())
            else:
                tx.undone(step, True, system.undo(step), clock())
            continue
        outcomes = []
        for step in decision.steps:
            started = clock()
            log.append((decision.action.value, step))
            if (step.action, step.target) == fail:
                outcomes.append(Outcome(step, started, 'refused', None))
            elif (step.action, step.target) == interrupt_during:
                interrupted = 'SIGTERM'
                outcomes.append(Outcome(step, started, 'interrupted (SIGTERM)', None))
            else:
                outcomes.append(Outcome(step, started, None, system.do(step)))
        groups_run += 1
        tx.ran(outcomes, clock(), interrupted)


def new(mode='prepared', overrides=None):
    script = adaptation.load(COMPOSE, overrides)
    clock = Clock()
    tx = Transaction(script.name, clock())
    tx.validated(adaptation.plan(script, mode), clock())
    return tx, clock


def states(tx):
    return [tx.history[0][1]] + [to for _, _, to, _ in tx.history]


def ran(log):
    return [(s.action, s.target) for kind, s in log if kind in ('run', 'clean')]


# -- the edges ------------------------------------------------------------------------------------
@pytest.mark.parametrize('source,target', list(itertools.product(State, State)),
                         ids=lambda s: s.name)
def test_only_the_edges_of_the_table_are_allowed(source, target):
    tx = Transaction('x', 0.0)
    tx.state = source
    if (source, target) in EDGES:
        tx._change(target, 1.0, 'test')
        assert tx.state is target and tx.history == [(1.0, source, target, 'test')]
    else:
        with pytest.raises(TransactionError, match='%s -> %s is not allowed' % (source.name, target.name)):
            tx._change(target, 1.0, 'test')
        assert tx.state is source and tx.history == []


def test_every_edge_has_a_reason_and_no_edge_leaves_an_end_state():
    assert all(isinstance(reason, str) and reason for reason in EDGES.values())
    assert not [edge for edge in EDGES if edge[0] in TERMINAL]
    reachable = {State.VALIDATING}
    for _ in State:
        reachable |= {b for a, b in EDGES if a in reachable}
    assert reachable == set(State)


def test_a_refused_script_ends_there_and_cannot_run():
    tx = Transaction('x', 0.0)
    tx.refused('unknown node /master/nobody', 1.0)
    assert tx.state is State.REFUSED and not tx.ok and not tx.rolled_back
    assert tx.next(2.0).action is Action.END
    with pytest.raises(TransactionError):
        tx.start(2.0)


def test_decisions_are_reported_on_one_at_a_time():
    tx, clock = new()
    with pytest.raises(TransactionError):   # not started
        tx.next(clock())
    tx.start(clock())
    with pytest.raises(TransactionError):
        tx.ran([], clock())
    decision = tx.next(clock())
    assert decision.action is Action.RUN
    with pytest.raises(TransactionError, match='not reported yet'):
        tx.next(clock())
    with pytest.raises(TransactionError, match='handed out'):
        tx.ran([Outcome(adaptation.Step('kill', '/x', None), 0.0, None, None)], clock())
    with pytest.raises(TransactionError):
        tx.undone(decision.steps[0], True, '', clock())
    tx.ran([Outcome(s, clock(), None, None) for s in decision.steps], clock())
    assert tx.index == 1


# -- runs -----------------------------------------------------------------------------------------
def test_the_prepared_order_runs_every_step_then_cleans_up_after_the_pause():
    tx, clock = new('prepared')
    system = FakeSystem()
    log = drive(tx, system, clock)
    assert ran(log) == [(s.action, s.target) for s in tx.steps]
    assert [kind for kind, s in log if s.action == 'kill'] == ['clean', 'clean']
    assert states(tx) == [State.VALIDATING, State.VALIDATED, State.RUNNING, State.CLEANING_UP, State.DONE]
    assert tx.ok and not tx.rolled_back and tx.error == '' and 'rollback' not in tx.summary()
    assert system.suspended == set() and '/master/tr/protocol' in system.running
    assert '/master/proceed' not in system.running
    # The pause: from the first suspension to the end of the last resume, not the cleanup.
    suspend_started = tx.pause_start
    assert 0 < suspend_started < tx.pause_end < tx.since
    assert tx.summary()['pause_s'] == pytest.approx(tx.pause_end - suspend_started)


def test_the_paper_order_has_no_cleanup():
    tx, clock = new('paper')
    drive(tx, FakeSystem(), clock)
    assert states(tx) == [State.VALIDATING, State.VALIDATED, State.RUNNING, State.DONE]


def test_a_failing_step_rolls_back_in_reverse_order_and_leaves_the_system_as_before():
    tx, clock = new('prepared', {'site': 'master'})
    system = FakeSystem()
    before = system.snapshot()
    log = drive(tx, system, clock, fail=('promote', '/master/recovery'))
    assert tx.state is State.ROLLED_BACK and tx.rolled_back and not tx.ok
    assert tx.error == 'step promote /master/recovery failed: refused'
    undone = [(s.action, s.target) for kind, s in log if kind == 'undo']
    assert undone == [('restore_binding', '/master/tr/protocol'), ('restore_binding', '/master/proceed'),
                      ('resume', '/master/protocol'), ('stop_launch', 'aft_ftm/mechanism.launch')]
    assert system.snapshot() == before
    assert [r['action'] for r in tx.summary()['rollback']] == [a for a, _ in undone]
    assert all(r['ok'] for r in tx.summary()['rollback'])
    # Clients waited until the resume, not until the launch was stopped.
    stop_launch_at = [t for t, _, to, _ in tx.history if to is State.ROLLING_BACK][0]
    assert tx.pause_start < stop_launch_at < tx.pause_end < tx.since


def test_a_failed_suspension_is_resumed_by_the_rollback():
    tx, clock = new('paper', {'site': 'master'})
    system = FakeSystem()
    log = drive(tx, system, clock, fail=('suspend', '/master/protocol'))
    assert [(k, s.action, s.target) for k, s in log] == [('run', 'suspend', '/master/protocol'),
                                                         ('undo', 'resume', '/master/protocol')]
    assert tx.state is State.ROLLED_BACK


def test_a_failing_cleanup_step_is_reported_never_rolled_back():
    tx, clock = new('prepared', {'site': 'master'})
    system = FakeSystem()
    log = drive(tx, system, clock, fail=('kill', '/master/proceed'))
    assert tx.state is State.DONE and tx.ok and not [k for k, _ in log if k == 'undo']
    assert tx.cleanup_errors == ['kill /master/proceed: refused']
    assert '/master/tr/protocol' in system.running


def test_a_lost_suspension_rolls_back_before_the_next_group():
    tx, clock = new('paper', {'site': 'master'})
    system = FakeSystem()
    before = system.snapshot()
    log = drive(tx, system, clock, lose_before=2)
    assert ran(log) == [('suspend', '/master/protocol'), ('kill', '/master/proceed')]
    assert tx.error == 'suspension lost: /master/protocol: lease ran out before step launch aft_ftm/mechanism.launch'
    assert tx.interrupted == '' and tx.state is State.ROLLED_BACK
    assert system.snapshot() == before


def test_a_step_failing_because_of_an_interrupt_is_reported_as_interrupted():
    tx, clock = new('paper', {'site': 'master'})
    drive(tx, FakeSystem(), clock, interrupt_during=('wait_launched', '1 launch file(s)'))
    assert tx.error == 'interrupted (SIGTERM) during step wait_launched 1 launch file(s)'
    assert tx.summary()['interrupted'] == 'SIGTERM'


@pytest.mark.parametrize('mode', adaptation.MODES)
def test_an_interrupt_before_any_group_rolls_back_what_was_done_and_stops_there(mode):
    rng = random.Random(SEED)
    for trial in range(50):
        tx, clock = new(mode)
        system = FakeSystem()
        before = system.snapshot()
        k = rng.randrange(len(tx.groups) + 1)
        why = 'seed %d (AFT_SEED=%d to repeat), trial %d, interrupt before group %d of %d' % (
            SEED, SEED, trial, k, len(tx.groups))
        log = drive(tx, system, clock, interrupt_before=k)
        assert ran(log) == [(s.action, s.target) for g in tx.groups[:k] for s in g], why
        if k < tx.cleanup_from:
            assert tx.state is State.ROLLED_BACK, why
            assert tx.error.startswith('interrupted (SIGINT) before step %s' % tx.groups[k][0].action), why
            assert system.snapshot() == before, why
            undone = [s for kind, s in log if kind == 'undo']
            assert undone == adaptation.undo_plan(tx.done), why
            assert [s for s, _ in tx.done] == [s for g in tx.groups[:k] for s in g], why
        elif k < len(tx.groups):   # in the cleanup: the adaptation stands, the rest is left undone
            assert tx.state is State.DONE and tx.interrupted == 'SIGINT', why
            assert tx.cleanup_errors and all(e.endswith('not done (interrupted)') for e in tx.cleanup_errors), why
        else:                      # after the last step: nothing to stop
            assert tx.state is State.DONE and tx.interrupted == '' and tx.cleanup_errors == [], why


def test_a_failing_undo_ends_failed_with_an_alarm_and_every_other_undo_is_still_tried():
    tx, clock = new('paper', {'site': 'master'})
    system = FakeSystem()
    log = drive(tx, system, clock, fail=('rebind', '/master/tr/protocol'),
                undo_fails={('respawn', '/master/proceed')})
    assert tx.state is State.FAILED and tx.rolled_back and not tx.ok
    undone = [(s.action, s.target) for kind, s in log if kind == 'undo']
    assert undone == [('respawn', '/master/proceed'), ('resume', '/master/protocol'),
                      ('stop_launch', 'aft_ftm/mechanism.launch')]
    assert system.suspended == set() and '/master/tr/protocol' not in system.running
    assert '/master/proceed' not in system.running   # what could not be undone
    summary = tx.summary()
    assert summary['state'] == 'FAILED'
    assert [r['ok'] for r in summary['rollback']] == [False, True, True]
    assert 'respawn /master/proceed (no answer)' in summary['alarm']
    assert 'step rebind /master/tr/protocol failed' in summary['alarm']


def test_only_a_failed_rollback_raises_an_alarm():
    for fail in (None, ('rebind', '/master/tr/protocol')):
        tx, clock = new('paper', {'site': 'master'})
        drive(tx, FakeSystem(), clock, fail=fail)
        assert tx.alarm == '' and tx.summary()['alarm'] == ''
