"""The demo application: errors in the request stream are visible in the replies. No ROS."""
import pytest

from aft_examples.bank import Account, InsufficientFunds, ReplyChecker, operation
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
