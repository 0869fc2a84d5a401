"""The demo application: errors in the request stream are visible in the replies. No ROS."""
import random
import time

import pytest

from aft_examples.bank import Account, InsufficientFunds, ReplyChecker, StateLayout, account_state, operation
from aft_ftm.delta import crc, rebuild
from aft_ftm.errors import StateError


def run(ops):
    account = Account()
    return [account.apply(op, amount) for op, amount in ops], account


def test_reply_reflects_every_operation_in_order():
    replies, account = run([('deposit', 10), ('withdraw', 3)])
    assert replies[-1][:2] == (7, 2)
    # Same operations in another order: same balance, different hash chain.
    other, _ = run([('deposit', 10), ('deposit', 0), ('withdraw', 3)][::2])
    assert other[-1] == replies[-1]
    swapped, _ = run([('deposit', 3), ('deposit', 10)])
    straight, _ = run([('deposit', 10), ('deposit', 3)])
    assert swapped[-1][:2] == straight[-1][:2] and swapped[-1][2] != straight[-1][2]


def test_application_errors_change_nothing():
    account = Account()
    with pytest.raises(InsufficientFunds):
        account.apply('withdraw', 1)
    with pytest.raises(ValueError):
        account.apply('steal', 1)
    assert account.snapshot() == Account().snapshot()


def test_demo_workload_never_overdraws():
    account = Account()
    for i in range(2000):
        account.apply(*operation(i))


def test_state_round_trip():
    _, account = run([('deposit', 5)])
    copy = Account()
    copy.set_state(account.get_state())
    assert copy.snapshot() == account.snapshot()


@pytest.mark.parametrize('data,error', [
    (b'not json', 'not valid JSON'),
    (b'\xff\xfe', 'not valid JSON'),
    (b'[1, 2]', 'exactly balance, count, digest'),
    (b'{"balance": 1, "count": 1}', 'exactly balance, count, digest'),
    (b'{"balance": -1, "count": 1, "digest": "0000000000000000"}', 'balance must be an integer >= 0'),
    (b'{"balance": 1, "count": "1", "digest": "0000000000000000"}', 'count must be an integer >= 0'),
    (b'{"balance": 1, "count": 1, "digest": "short"}', 'digest must be 16'),
])
def test_corrupt_state_is_refused_and_changes_nothing(data, error):
    _, account = run([('deposit', 5)])
    before = account.snapshot()
    with pytest.raises(StateError, match=error):
        account.set_state(data)
    assert account.snapshot() == before


@pytest.mark.parametrize('server_ops,verdict', [
    ([0, 1, 2], 'correct'),
    ([0, 2], 'lost'),            # request 1 never applied
    ([0, 1, 1, 2], 'duplicated'),
    ([1, 0, 2], 'reordered'),
])
def test_checker_classifies_what_happened_to_the_request_stream(server_ops, verdict):
    server = Account()
    got = None
    for i in server_ops:
        got = server.apply(*operation(i))
    checker = ReplyChecker()
    expected = None
    for i in range(3):
        expected = checker.expect(*operation(i))
    assert checker.check(expected, got) == (verdict == 'correct')
    summary = checker.summary()
    assert summary[verdict] >= 1
    assert sum(summary.values()) == summary[verdict]
    assert checker.model.snapshot() == server.snapshot()    # resynchronised on the server's answer


@pytest.mark.parametrize('ballast', [0, 3000])
def test_the_servers_changes_since_any_version_it_named_rebuild_its_state(ballast):
    """The bank server's own state changes (StateLayout.since), from random versions it named, some
    forgotten: runs that rebuild exactly its state now, with its CRC, or the whole state."""
    seed = int(time.time())
    rng = random.Random(seed)
    layout, account = StateLayout(ballast, 'inc1'), Account()
    named = {}   # version -> the whole state at it
    for step in range(300):
        for _ in range(rng.randint(0, 3)):
            try:
                account.apply(*operation(rng.randrange(1000)))
            except InsufficientFunds:
                continue   # refused: the state did not change
            layout.changed()
        since = rng.choice(sorted(named) + ['', 'other:1']) if named else ''
        changes = layout.since(since, account.get_state())
        now = layout.state(account.get_state())
        named[changes.version] = now
        if changes.state is not None:
            assert changes.state == now
            assert since not in list(named)[-StateLayout.KNOWN:] or since == changes.version, \
                'seed %d, step %d: the whole state for a version it knows' % (seed, step)
            continue
        assert rebuild(named[since], changes.runs) == now, 'seed %d, step %d' % (seed, step)
        assert (changes.size, changes.crc) == (len(now), crc(now))
        assert sum(len(d) for _, _, d in changes.runs) < 200   # the account, never the ballast
    assert layout.account(layout.state(account.get_state())) == account.get_state()
    assert account_state(layout.state(account.get_state())) == account.get_state()


def test_a_state_of_another_ballast_is_refused_by_its_length():
    layout = StateLayout(100, 'inc1')
    with pytest.raises(StateError, match='ballast of 99 bytes, expected 100'):
        layout.account(b'\xa5' * 99 + b'\0' + Account().get_state())
    with pytest.raises(StateError, match='ballast of 0 bytes, expected 100'):
        layout.account(Account().get_state())


def test_a_slow_fault_still_has_calls_after_it():
    """drive_through_fault (the failover benchmarks and tests): however long the fault takes to land
    (a loaded machine stopping a site), some calls are sent after it, so the outage is measured.
    Seeded: the fault's length and the point it is injected at vary."""
    from aft_examples.ros.bank_nodes import drive_through_fault
    from aft_examples.stats import longest_wait
    seed = random.randrange(1 << 30)
    rng = random.Random(seed)
    for _ in range(5):
        account, checker = Account(), ReplyChecker()
        slow = rng.uniform(0.02, 0.1)

        def fault():
            time.sleep(slow)     # far longer than every remaining call together
            return 1, time.time()
        count, after = 40, rng.randint(1, 30)   # (10 or more left: the tail is whole)
        records, injected = drive_through_fault(lambda op, amount: account.apply(op, amount), count, checker,
                                                after, fault, rng)
        assert len(records) == count and all(ok for *_, ok in records), 'seed %d' % seed
        sent_after = [r for r in records if r[1] >= injected['wall']]
        assert len(sent_after) >= 10, 'seed %d: %d calls sent after the fault' % (seed, len(sent_after))
        assert longest_wait(records, injected['wall']) is not None, 'seed %d' % seed
    with pytest.raises(ValueError, match='fault_after=41'):
        drive_through_fault(lambda op, amount: None, 40, ReplyChecker(), 41, fault, rng)


def test_a_fault_that_refuses_to_run_is_named_and_every_call_still_made():
    """A fault that raises (bench_pbr's, when a false suspicion changed the pair before it) is not injected:
    the calls go on, and what it raised is raised once they are made (not a thread's traceback)."""
    from aft_examples.ros.bank_nodes import drive_through_fault
    account, checker = Account(), ReplyChecker()

    def refused():
        raise LookupError('the pair changed')
    with pytest.raises(LookupError, match='the pair changed'):
        drive_through_fault(lambda op, amount: account.apply(op, amount), 30, checker, 5, refused, random.Random(1))
    assert checker.correct == 30


def test_a_failed_calls_text_stays_off_rosout(monkeypatch, capsys):
    """/rosout is in clear: the kind of a failed call goes there, its text (what SEC sealed on the wire,
    a server's error about the account) only to the client's own stderr."""
    import rospy
    from aft_examples.ros import bank_nodes
    logged = []
    monkeypatch.setattr(rospy, 'logerr', lambda fmt, *args: logged.append(fmt % args))
    calls = iter([rospy.ServiceException('balance 1234 below 5000 for account alice')])

    def call(op, amount):
        raise next(calls)
    records = bank_nodes.drive(call, 1, ReplyChecker())
    assert [ok for *_, ok in records] == [False]
    assert logged == ['request 0 failed (ServiceException; its text on the client\'s stderr)']
    assert 'balance 1234 below 5000 for account alice' in capsys.readouterr().err
