"""A&D's After (aft_ftm.ros.ad_nodes.AdAfterNode) without a master: its ports faked, its pairing and
sweep real. A reply whose request never comes is answered "outcome unknown", never dropped: the
Protocol runs one request at a time and waited for it for good (review of session 36)."""
import threading
import time

import rospy
from aft_msgs.msg import Reply

from aft_ftm import assertions
from aft_ftm.ros import ad_nodes
from fakes import FakePorts


def test_a_reply_whose_request_never_comes_is_answered_outcome_unknown_with_an_alarm(monkeypatch):
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))
    node = ad_nodes.AdAfterNode.__new__(ad_nodes.AdAfterNode)
    node.ports, node.lock, node.checks = FakePorts(), threading.Lock(), []
    node.pairing = assertions.Pairing(wait=0.05, max_requests=10)
    reply = Reply(id=7, origin='/client/proxy', client='c', attempt=1, status=Reply.OK, payload=b'x')
    assert node.handle(reply) is None            # parked: its request has not come
    node._sweep(None)
    assert node.ports.sent == []                 # not yet past request_wait
    time.sleep(0.06)
    node._sweep(None)
    kinds = [(port, getattr(msg, 'kind', None)) for port, msg in node.ports.sent]
    assert kinds == [('alarms', 'unchecked_reply'), ('out', None)], kinds
    answer = node.ports.sent[1][1]
    assert (answer.id, answer.origin, answer.attempt, answer.status) == (7, '/client/proxy', 1, Reply.ERROR)
    assert answer.error.startswith('outcome unknown') and answer.payload == b''
    node._sweep(None)
    assert len(node.ports.sent) == 2             # answered once


def _after(checks):
    node = ad_nodes.AdAfterNode.__new__(ad_nodes.AdAfterNode)
    node.ports, node.lock, node.checks = FakePorts(), threading.Lock(), checks
    node.pairing = assertions.Pairing(wait=5.0, max_requests=10)
    node.run = ad_nodes.BoundedRun(0, lambda *a: None)    # ~assertion_timeout 0: unbounded, in this thread
    return node


def _withdrawn(node, balance):
    """A withdraw of 100 the server executed (balance then ``balance``), its request and reply through After."""
    from aft_msgs.msg import Request
    from aft_msgs.srv import AccountRequest, AccountResponse
    from aft_ftm.ros.envelope import serialize
    node._on_request(Request(id=1, origin='/p', service_type='aft_msgs/Account',
                             payload=serialize(AccountRequest(op='withdraw', amount=100))))
    return node.handle(Reply(id=1, origin='/p', status=Reply.OK,
                             payload=serialize(AccountResponse(balance=balance, count=1))))


def test_a_reply_assertion_violated_says_the_request_executed_not_that_nothing_changed(monkeypatch):
    """Review of session 48: the refusal read as the server's error, which the Proxy's clients (and the
    campaign's history checker) take for "nothing changed", and may retry: the withdraw applied twice."""
    from aft_examples import bank
    from aft_examples.history import classify_error
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))
    node = _after([('aft_examples.bank:balance_never_negative', bank.balance_never_negative)])
    answer = _withdrawn(node, -50)
    assert answer.status == Reply.ERROR and 'balance_never_negative violated' in answer.error
    assert classify_error('service [/account] responded with an error: ' + answer.error) == 'indeterminate'
    assert [getattr(m, 'kind', None) for _, m in node.ports.sent] == ['assertion_violated']


def test_an_assertion_that_exits_is_a_violation_not_a_reply_dropped(monkeypatch):
    """Review of session 48: with ~assertion_timeout 0, sys.exit() (or KeyboardInterrupt) in a user's
    assertion escaped the check; the reply was neither passed nor refused, and the Protocol waited for good."""
    import sys
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))

    def exits(request, response):
        sys.exit('the library gave up')

    def interrupted(request, response):
        raise KeyboardInterrupt()
    for check in (exits, interrupted):
        node = _after([('user:check', check)])
        answer = _withdrawn(node, 50)
        assert answer is not None and answer.status == Reply.ERROR, check
        assert 'raised %s' % ('SystemExit' if check is exits else 'KeyboardInterrupt') in answer.error
