"""The campaign's history checker: linearizable histories pass, every injected violation is caught.
Seeded random histories; a failure prints its seed (replay: AFT_HISTORY_SEED=<seed>). No ROS."""
import os
import random

import pytest

from aft_examples.bank import Account, InsufficientFunds
from aft_examples.history import HistoryError, Op, check, percentile, read_history, unavailability, \
    unavailability_split

SEEDS = [int(os.environ['AFT_HISTORY_SEED'])] if 'AFT_HISTORY_SEED' in os.environ else range(200)
MUTATIONS = ('lost', 'duplicated', 'reordered', 'wrong_value', 'failed_but_executed', 'indeterminate_no_kill',
             'stale_reply', 'final_differs')


def simulate(rng, clients=3, per_client=25, mutation=None):
    """Random concurrent clients on one account. Each operation takes effect at a point inside its call
    (its linearization point). Returns (ops, final states, proxy kills, the mutation applied or None)."""
    plans = []
    for c in range(clients):
        t = rng.uniform(0, 0.01)
        for i in range(per_client):
            invoke = t
            point = invoke + rng.uniform(0.0005, 0.01)
            complete = point + rng.uniform(0.0005, 0.01)
            t = complete + rng.uniform(0, 0.005)
            op = ('withdraw', rng.randint(1, 15)) if rng.random() < 0.35 else ('deposit', rng.randint(1, 10))
            op += ('c%d:%d' % (c, i),)   # the campaign's tags: every operation unique
            fate = rng.random()
            outcome = 'not_executed' if fate < 0.05 else 'indeterminate' if fate < 0.1 else 'ok'
            plans.append(dict(client='c%d' % c, index=i, invoke=invoke, point=point, complete=complete, op=op,
                              outcome=outcome, executes=outcome == 'ok' or (outcome == 'indeterminate'
                                                                            and rng.random() < 0.5)))
    answered = [p for p in plans if p['outcome'] == 'ok']
    target = rng.choice(answered) if mutation else None
    if mutation == 'reordered':
        # Two answered operations, one completed before the other was invoked: swap their points.
        pairs = [(a, b) for a in answered for b in answered if a['complete'] < b['invoke']]
        a, b = rng.choice(pairs)
        a['point'], b['point'] = b['point'], a['point']
    if mutation == 'failed_but_executed':
        target = rng.choice([p for p in plans if p['outcome'] == 'not_executed'] or [None])
        if target is None:
            return None
        target['executes'] = True
    if mutation == 'indeterminate_no_kill':
        target = rng.choice([p for p in plans if p['outcome'] == 'indeterminate'] or [None])
        if target is None:
            return None
    account, previous = Account(), None
    applied = mutation in (None, 'indeterminate_no_kill', 'final_differs')
    for p in sorted(plans, key=lambda p: p['point']):
        p['reply'], p['error'] = None, ''
        if not p['executes']:
            continue
        before = account.snapshot()
        try:
            reply = account.apply(*p['op'])
        except InsufficientFunds as e:
            if p['outcome'] == 'ok':
                p['outcome'], p['error'] = 'error', str(e)
            continue
        if mutation == 'lost' and p is target:
            account = Account(*before)
            applied = True
        if mutation == 'duplicated' and p is target:
            try:
                account.apply(*p['op'])
            except InsufficientFunds:
                return None
            applied = True
        if mutation == 'stale_reply' and p is target and previous is not None:
            # A deposed primary answers from its own copy: one that missed the operation before.
            try:
                reply = Account(*previous).apply(*p['op'])
            except InsufficientFunds:
                return None
            applied = True
        previous = before
        p['reply'] = list(reply)
        if mutation == 'wrong_value' and p is target:
            p['reply'][0] += 1
            applied = True
    if mutation == 'reordered':   # both still executed (a withdrawal moved may be refused instead)
        applied = a['reply'] is not None and b['reply'] is not None
    if mutation == 'failed_but_executed':
        applied = target['reply'] is not None
    if not applied:
        return None
    kills = {}
    ops = []
    for p in plans:
        if p['outcome'] == 'indeterminate' and not (mutation == 'indeterminate_no_kill' and p is target):
            kills.setdefault(p['client'], []).append(rng.uniform(p['invoke'], p['complete']))
        if p['outcome'] == 'ok' and p['reply'] is None:
            p['outcome'] = 'not_executed'   # an unexecuted answered op is a client-side "not executed"
        ops.append(Op(p['client'], p['index'], p['invoke'], p['complete'], p['op'][0], p['op'][1], p['outcome'],
                      p['reply'], p['error'], p['op'][2]))
    final = account.snapshot()
    finals = [final]
    if mutation == 'final_differs':
        finals.append((final[0] + 1, final[1], final[2]))
    return ops, finals, kills, mutation


@pytest.mark.parametrize('seed', SEEDS)
def test_linearizable_histories_pass(seed):
    ops, finals, kills, _ = simulate(random.Random(seed))
    result = check(ops, finals, kills)
    assert result.ok, 'seed %d (AFT_HISTORY_SEED=%d): %s' % (seed, seed, result.violations[:3])
    assert result.counts['positions'] == finals[0][1]


@pytest.mark.parametrize('mutation', MUTATIONS)
def test_every_injected_violation_is_caught(mutation):
    tried = 0
    for seed in SEEDS:
        made = simulate(random.Random(seed), mutation=mutation)
        if made is None:
            continue
        ops, finals, kills, _ = made
        tried += 1
        result = check(ops, finals, kills)
        assert not result.ok, 'seed %d (AFT_HISTORY_SEED=%d): the %s history passed' % (seed, seed, mutation)
    assert tried >= min(20, len(SEEDS)) or len(SEEDS) == 1, 'only %d %s histories made' % (tried, mutation)


def op(client, index, invoke, complete, name, amount, outcome='ok', reply=None, error=''):
    return Op(client, index, invoke, complete, name, amount, outcome, reply, error)


def chain(*ops):
    account = Account()
    return [account.apply(*o) for o in ops]


def test_each_kind_is_named():
    r1, r2 = chain(('deposit', 5), ('deposit', 3))
    # Real time: b completed before a was invoked, yet a's reply places it first.
    a = op('a', 0, 2.0, 3.0, 'deposit', 5, reply=r1)
    b = op('b', 0, 0.0, 1.0, 'deposit', 3, reply=r2)
    assert [v.kind for v in check([a, b], [r2]).violations] == ['real_time']
    # Lost: answered, and not in the final state.
    assert 'lost' in [v.kind for v in check([a], [(0, 0, '0' * 16)]).violations]
    # A withdrawal refused while the balance always covered it.
    refused = op('b', 1, 1.5, 1.6, 'withdraw', 2, 'error', error='cannot withdraw 2 from a balance of 0')
    ok_a = op('a', 0, 0.0, 1.0, 'deposit', 5, reply=r1)
    assert [v.kind for v in check([ok_a, refused], [r1]).violations] == ['wrong_refusal']
    refused_early = op('b', 1, 0.0, 0.4, 'withdraw', 2, 'error', error='cannot withdraw 2 from a balance of 0')
    assert check([ok_a, refused_early], [r1]).ok


def test_indeterminate_and_unfinished_operations_fill_gaps_in_either_fate():
    r1, r2 = chain(('deposit', 5), ('deposit', 3))
    lost_call = op('a', 0, 0.0, 1.0, 'deposit', 5, 'indeterminate', error='transport error')
    b = op('b', 0, 0.5, 2.0, 'deposit', 3, reply=r2)
    assert check([lost_call, b], [r2], {'a': [0.5]}).ok
    # The same call never executed: fine too, if b's reply says so.
    alone = chain(('deposit', 3))[0]
    assert check([lost_call, op('b', 0, 0.5, 2.0, 'deposit', 3, reply=alone)], [alone], {'a': [0.5]}).ok
    unfinished = op('a', 1, 3.0, None, 'deposit', 5, 'unfinished')
    both = chain(('deposit', 3), ('deposit', 5))[1]
    assert check([op('b', 0, 0.5, 2.0, 'deposit', 3, reply=alone), unfinished], [both], killed_clients={'a'}).ok


def test_a_call_never_ended_needs_its_client_killed_in_it_at_the_end():
    """An unfinished call is an unknown outcome: acceptable only as the last call of a client the run
    killed at its end (a call hung past the stop), never for a client that was not killed, nor for an
    earlier call of a killed one."""
    r1, r2 = chain(('deposit', 5), ('deposit', 2))
    ok_a = op('a', 0, 0.0, 1.0, 'deposit', 5, reply=r1)
    hung = op('a', 1, 1.5, None, 'deposit', 2, 'unfinished')
    assert check([ok_a, hung], [r2], killed_clients={'a'}).ok
    result = check([ok_a, hung], [r2], end=100.0)
    assert [v.kind for v in result.violations] == ['unfinished_without_cause'], result.violations
    earlier = op('a', 0, 0.0, None, 'deposit', 5, 'unfinished')
    later = op('a', 1, 1.5, 2.0, 'deposit', 2, reply=chain(('deposit', 5), ('deposit', 2))[1])
    assert [v.kind for v in check([earlier, later], [r2], killed_clients={'a'}).violations] == \
        ['unfinished_without_cause']


def test_no_final_state_or_an_unreadable_one_is_a_violation_not_a_pass():
    """Only the final state shows an answered operation the servers lost after their answer: without
    it (the witness silent at the end, a server that cannot be read) the run is not a pass."""
    r1, r2 = chain(('deposit', 5), ('deposit', 3))
    a, b = op('a', 0, 0.0, 1.0, 'deposit', 5, reply=r1), op('b', 0, 1.5, 2.0, 'deposit', 3, reply=r2)
    assert [v.kind for v in check([a, b], [r1]).violations] == ['lost']     # the servers ended at r1: b lost
    assert [v.kind for v in check([a, b], []).violations] == ['final_state_unreadable']
    unreadable = ('unreadable: timed out', -1, '')
    assert [v.kind for v in check([a, b], [unreadable, r2]).violations] == ['final_state_unreadable']
    assert [v.kind for v in check([a, b], [unreadable, r1]).violations] == ['final_state_unreadable', 'lost']


def test_an_operation_tag_given_twice_is_refused():
    """Tags tell executions apart: a tag repeated (a client relaunched with its index from 0) would let
    an execution twice of one pass for an indeterminate other."""
    r1, r2 = chain(('deposit', 5, 'a:0'), ('deposit', 5, 'a:0'))
    x = Op('a', 0, 0.0, 1.0, 'deposit', 5, 'ok', r1, '', 'a:0')
    y = Op('a', 0, 2.0, 3.0, 'deposit', 5, 'indeterminate', None, 'transport error', 'a:0')
    with pytest.raises(HistoryError, match='tags given to more than one operation: a:0'):
        check([x, y], [r2], {'a': [2.5]})


def test_percentile_and_unavailability():
    assert percentile([], 50) is None
    assert percentile([1, 2, 3, 4], 50) == 2 and percentile(range(1, 101), 99) == 99
    r = chain(*[('deposit', 1)] * 4)
    ops = [op('a', 0, 0.0, 1.0, 'deposit', 1, reply=r[0]), op('a', 1, 1.0, 4.0, 'deposit', 1, reply=r[1]),
           op('a', 2, 4.0, 4.5, 'deposit', 1, reply=r[2])]
    assert unavailability(ops, 1.5, 10.0) == pytest.approx(2.5)
    assert unavailability(ops, 5.0, 10.0) == 0.0   # nothing pending: not unavailable
    # Clients idle after the fault: the wait counts from their first call, not from the fault.
    late = [op('a', 0, 3.0, 3.01, 'deposit', 1, reply=r[0]), op('a', 1, 3.01, 3.05, 'deposit', 1, reply=r[1])]
    assert unavailability(late, 1.0, 10.0) == pytest.approx(0.04)


def test_unavailability_split_tells_the_fault_from_its_repair():
    # A failover (answers stop 0.05 s, at the fault) then a re-join's pause (0.3 s, after the relaunch at 2.0).
    r = chain(*[('deposit', 1)] * 6)
    ops = [op('a', 0, 0.0, 0.95, 'deposit', 1, reply=r[0]), op('a', 1, 0.95, 1.05, 'deposit', 1, reply=r[1]),
           op('a', 2, 1.05, 1.1, 'deposit', 1, reply=r[2]), op('a', 3, 1.1, 2.6, 'deposit', 1, reply=r[3]),
           op('a', 4, 2.6, 2.7, 'deposit', 1, reply=r[4])]
    split = unavailability_split(ops, 1.0, 2.0, 3.0)
    assert split['unavailable'] == pytest.approx(1.5)          # 1.1 .. 2.6: the whole window's longest
    assert split['unavailable_fault'] == pytest.approx(0.9)    # 1.1 .. 2.0, cut at the relaunch
    assert split['unavailable_repair'] == pytest.approx(0.6)   # 2.0 .. 2.6
    assert unavailability_split(ops, 1.0, None, 3.0) == {'unavailable': pytest.approx(1.5),
                                                         'unavailable_fault': pytest.approx(1.5),
                                                         'unavailable_repair': 0.0}
    # A repair time outside the window (before the fault, or after the next one) is no repair of it.
    assert unavailability_split(ops, 1.0, 0.5, 3.0)['unavailable_repair'] == 0.0
    assert unavailability_split(ops, 1.0, 3.5, 3.0)['unavailable_fault'] == pytest.approx(1.5)


def test_bad_records_are_refused_by_name(tmp_path):
    with pytest.raises(HistoryError, match='outcome'):
        Op('a', 0, 0.0, 1.0, 'deposit', 1, 'maybe')
    with pytest.raises(HistoryError, match='ok without a reply'):
        Op('a', 0, 0.0, 1.0, 'deposit', 1, 'ok')
    path = tmp_path / 'h.jsonl'
    path.write_text('{"i": 0, "invoke": 1.0, "op": "deposit", "amount": 1}\n'
                    '{"i": 0, "complete": 1.5, "outcome": "ok", "reply": [1, 1, "x"]}\n'
                    '{"i": 1, "invoke": 2.0, "op": "deposit", "amount": 2}\n{"i": 1, "comp')
    ops = read_history(str(path), 'a')
    assert [(o.index, o.outcome) for o in ops] == [(0, 'ok'), (1, 'unfinished')]
    path.write_text('garbage\n')
    with pytest.raises(HistoryError, match='line 1'):
        read_history(str(path), 'a')


def test_a_tag_enters_the_chain_and_an_untagged_chain_is_unchanged():
    import hashlib
    untagged = Account().apply('deposit', 5)
    assert untagged[2] == hashlib.sha256(('0' * 16 + '|deposit:5').encode()).hexdigest()[:16]
    tagged = Account().apply('deposit', 5, 'c0:1')
    assert tagged[:2] == untagged[:2] and tagged[2] != untagged[2]


def test_a_refusal_sees_only_positions_reached_before_it_was_answered():
    """Review of the checker (session 33): the window of balances a refusal may have seen ended at the
    last operation invoked before the refusal completed, so a slow call overlapping it let a later,
    low balance (reached only after an operation invoked once the refusal was answered) excuse it."""
    acc = Account()
    ra, rb, rc = acc.apply('deposit', 10, 'a'), acc.apply('withdraw', 8, 'b'), acc.apply('deposit', 1, 'c')
    refusal = 'responded with an error: error processing request: cannot withdraw 5 from a balance of 2'
    ops = [Op('c1', 0, 0.0, 1.0, 'deposit', 10, 'ok', ra, tag='a'),
           Op('c2', 0, 2.0, 5.0, 'withdraw', 5, 'error', error=refusal, tag='r'),
           Op('c2', 1, 6.0, 7.0, 'withdraw', 8, 'ok', rb, tag='b'),      # invoked after the refusal came back
           Op('c3', 0, 3.0, 10.0, 'deposit', 1, 'ok', rc, tag='c')]      # slow, overlapping the refusal
    assert [v.kind for v in check(ops, [acc.snapshot()]).violations] == ['wrong_refusal']
    # The same refusal while b could have run (b invoked before it was answered): right.
    ops[2] = Op('c2', 1, 4.0, 7.0, 'withdraw', 8, 'ok', rb, tag='b')
    ops[1] = Op('c4', 0, 2.0, 5.0, 'withdraw', 5, 'error', error=refusal, tag='r')
    assert check(ops, [acc.snapshot()]).ok


def test_a_refusal_must_name_a_balance_the_account_held_inside_its_call():
    """A refusal naming a balance no position inside its call held is a wrong value (a deposed
    primary's, or a corrupted one), even when that balance happens to be below the amount."""
    r1 = chain(('deposit', 4))[0]
    a = op('a', 0, 0.0, 1.0, 'deposit', 4, reply=r1)
    wrong = op('b', 0, 2.0, 3.0, 'withdraw', 5, 'error', error='cannot withdraw 5 from a balance of 2')
    assert [v.kind for v in check([a, wrong], [r1]).violations] == ['wrong_refusal']
    right = op('b', 0, 2.0, 3.0, 'withdraw', 5, 'error', error='cannot withdraw 5 from a balance of 4')
    assert check([a, right], [r1]).ok


def test_a_call_in_flight_past_the_proxys_call_limit_is_hung_not_a_pass():
    """The run kills a client only after waiting longer than the Proxy's call limit: its call in
    flight then was never answered, not even "outcome unknown"."""
    r1, r2 = chain(('deposit', 4), ('deposit', 3))
    ok_a = op('a', 0, 0.0, 1.0, 'deposit', 4, reply=r1)
    hung = op('a', 1, 1.0, None, 'deposit', 3, 'unfinished')
    assert check([ok_a, hung], [r2], end=101.0, killed_clients={'a'}).ok   # no limit given: as before
    result = check([ok_a, hung], [r2], end=101.0, killed_clients={'a'}, call_limit=30.0)
    assert [v.kind for v in result.violations] == ['hung'], result.violations
    assert check([ok_a, hung], [r2], end=20.0, killed_clients={'a'}, call_limit=30.0).ok


def test_a_client_that_stopped_calling_before_it_was_told_to_is_named():
    """A client that died or gave up early leaves the faults after it without load: a history
    with no calls (or none near the stop) must not pass for an available service."""
    r1 = chain(('deposit', 4))[0]
    a = op('a', 0, 0.0, 1.0, 'deposit', 4, reply=r1)
    result = check([a], [r1], clients=['a', 'b'], stopped=50.0)
    assert sorted(v.detail.split()[0] for v in result.violations if v.kind == 'client_silent') == ['a', 'b']
    assert check([a], [r1], clients=['a'], stopped=3.0).ok
    in_flight = op('a', 1, 2.0, None, 'deposit', 1, 'unfinished')
    assert check([a, in_flight], [r1], clients=['a'], stopped=50.0, killed_clients={'a'}).ok


def test_a_proxy_kill_stamped_before_and_after_its_signal_covers_a_call_begun_between():
    r1 = chain(('deposit', 4))[0]
    cut = op('a', 0, 100.00005, 100.01, 'deposit', 4, 'indeterminate', error='transport error')
    assert [v.kind for v in check([cut], [r1], {'a': [100.0]}).violations] == ['indeterminate_without_cause']
    assert check([cut], [r1], {'a': [(100.0, 100.0002)]}).ok
