"""A&D's Before and After wired together without a master, a bank server between them: a second copy
of a request (the same origin, id and attempt: a publisher heard on two connections across a rebind, a
message published again on pro2bfr, a Protocol started again) is never executed twice. It gets what a
copy gets from TR's Before: the first copy's answer again, or nothing while the first is in progress
(its answer then answers both). Its nodes are built by their own constructors, their parameters faked."""
import collections
import threading

import pytest
import rospy
from aft_msgs.msg import Reply, Request
from aft_msgs.srv import AccountRequest, AccountResponse

from aft_examples import bank
from aft_ftm.ros import ad_nodes, bpa_nodes
from aft_ftm.ros import ports as ros_ports
from aft_ftm.ros.envelope import deserialize, serialize


class Wire(object):
    """A node's ports: Before's ``out`` goes to the server (queued: it executes when run() says),
    ``to_after`` to After's requests; what reaches the Protocol (Before's ``errors``, After's ``out``)
    is kept in order, and so are the alarms."""

    def __init__(self, graph, node):
        self.graph, self.node = graph, node

    def publish(self, port, msg):
        g = self.graph
        if port == 'alarms':
            g.alarms.append(msg.kind)
        elif (self.node, port) == ('before', 'out'):
            g.to_server.append(msg)
        elif (self.node, port) == ('before', 'to_after'):
            g.after._on_request(msg)
        elif (self.node, port) in (('before', 'errors'), ('after', 'out')):
            g.protocol.append(msg)
        else:
            raise AssertionError('%s published on %s' % (self.node, port))


class Graph(object):
    def __init__(self, monkeypatch, request_assertions=(), reply_assertions=()):
        values = {'request_assertions': list(request_assertions), 'reply_assertions': list(reply_assertions),
                  'assertion_timeout': 0.0}

        def param(name, convert, default=None, required=False):
            return values.get(name, default)
        for module in (ad_nodes, bpa_nodes, ros_ports):
            monkeypatch.setattr(module, 'param', param)
        monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))
        self.alarms, self.protocol, self.to_server = [], [], collections.deque()
        self.balance = 100   # the server's state: each withdraw applied (overdrawn too: a reply assertion's case)
        self.executed = []   # (origin, id, attempt) of every execution by the server
        self.before, self.after = ad_nodes.AdBeforeNode(), ad_nodes.AdAfterNode()
        self.before.ports, self.after.ports = Wire(self, 'before'), Wire(self, 'after')

    def send(self, rid, amount=10, attempt=0):
        """The Protocol sends a withdraw (or a copy of one) to Before."""
        self.before._on_input(Request(id=rid, origin='/proxy', client='c', attempt=attempt,
                                      service_type='aft_msgs/Account',
                                      payload=serialize(AccountRequest(op='withdraw', amount=amount))))

    def run(self):
        """The server executes what Before passed on; its replies go to After."""
        while self.to_server:
            request = self.to_server.popleft()
            self.executed.append((request.origin, request.id, request.attempt))
            self.balance -= deserialize(AccountRequest, request.payload).amount
            self.after._on_input(Reply(id=request.id, origin=request.origin, client=request.client,
                                       attempt=request.attempt, status=Reply.OK,
                                       payload=serialize(AccountResponse(balance=self.balance,
                                                                         count=len(self.executed)))))

    def answers(self):
        return [(a.id, a.status, bytes(a.payload), a.error) for a in self.protocol]


@pytest.fixture
def graph(monkeypatch):
    return Graph(monkeypatch, request_assertions=['aft_examples.bank:amount_within_limit'],
                 reply_assertions=['aft_examples.bank:balance_never_negative'])


def test_a_second_copy_of_a_request_is_never_executed_again(graph):
    """A copy heard before the server executed the first (mid-flight) gets no answer of its own (the first's
    answers it); one heard after the first was answered gets that answer again. The server applies the
    withdraw once; each copy is alarmed ``duplicate_request``."""
    graph.send(1)
    graph.send(1)                 # a copy while the first is still to be executed
    graph.run()
    assert graph.executed == [('/proxy', 1, 0)] and graph.balance == 90
    first = graph.answers()
    assert len(first) == 1 and first[0][1] == Reply.OK
    graph.send(1)                 # a copy after the first was answered (a Protocol started again lost it)
    graph.run()
    assert graph.executed == [('/proxy', 1, 0)] and graph.balance == 90
    assert graph.answers() == first * 2
    assert graph.alarms == ['duplicate_request'] * 2


def test_another_attempt_of_a_request_is_not_a_copy(graph):
    """TR around A&D executes a request again under a new attempt number: each attempt executes once."""
    graph.send(2, attempt=0)
    graph.send(2, attempt=1)
    graph.send(2, attempt=1)      # a copy of the second attempt
    graph.run()
    assert graph.executed == [('/proxy', 2, 0), ('/proxy', 2, 1)] and graph.balance == 80
    assert [(a.id, a.attempt) for a in graph.protocol] == [(2, 0), (2, 1)]
    assert graph.alarms == ['duplicate_request']


def test_a_copy_of_a_refused_request_gets_the_refusal_again_never_an_execution(graph):
    graph.send(3, amount=bank.LIMIT + 1)     # request assertion violated: refused, not executed
    graph.run()
    refusal = graph.answers()
    assert len(refusal) == 1 and refusal[0][1] == Reply.ERROR and 'amount_within_limit' in refusal[0][3]
    graph.send(3, amount=bank.LIMIT + 1)
    graph.run()
    assert graph.executed == [] and graph.answers() == refusal * 2
    assert graph.alarms == ['assertion_violated', 'duplicate_request']


def test_a_copy_of_a_request_whose_reply_assertion_failed_gets_that_answer_again(graph):
    graph.send(4, amount=150)                # executed; its reply (balance -50) is withheld
    graph.run()
    withheld = graph.answers()
    assert len(withheld) == 1 and withheld[0][1] == Reply.ERROR and 'balance_never_negative' in withheld[0][3]
    graph.send(4, amount=150)
    graph.run()
    assert graph.executed == [('/proxy', 4, 0)] and graph.balance == -50
    assert graph.answers() == withheld * 2


def test_a_copy_heard_while_its_first_is_checked_is_neither_checked_nor_executed(monkeypatch):
    """Two copies heard on two connections come on two threads: the second, heard while the first's
    request assertion runs, is not passed on (the first's outcome answers it), whether the first then
    passes or is refused."""
    for passes in (True, False):
        graph = Graph(monkeypatch, request_assertions=['aft_examples.bank:amount_within_limit'])
        entered, go, calls = threading.Event(), threading.Event(), []

        def slow(request):
            calls.append(request.amount)
            if len(calls) == 1:   # the first copy's check waits; a second one checked is the failure
                entered.set()
                go.wait(10)
            return passes or 'refused'
        graph.before.checks = [('user:slow', slow)]
        first = threading.Thread(target=graph.send, args=(5,))
        first.start()
        assert entered.wait(10)
        graph.send(5)                        # the copy, while the first is checked
        go.set()
        first.join(10)
        graph.run()
        assert calls == [10], passes         # the copy was not checked
        assert graph.executed == ([('/proxy', 5, 0)] if passes else []), passes
        assert len(graph.protocol) == 1, (passes, graph.answers())
        assert graph.alarms.count('duplicate_request') == 1, (passes, graph.alarms)


def test_a_reply_heard_twice_is_answered_once_and_its_request_s_copy_gets_the_true_answer(graph):
    """A copy of the server's reply, once its request was answered, waited for a request that had come
    already; past ~request_wait it was answered again, "outcome unknown", which a later copy of the
    request would then have been given."""
    graph.send(6)
    request = graph.to_server[0]
    graph.run()
    first = graph.answers()
    graph.after.pairing.wait = 0.0   # the sweep hands back at once whatever waits
    graph.after._on_input(Reply(id=request.id, origin=request.origin, attempt=request.attempt, status=Reply.OK,
                                payload=graph.protocol[0].payload))
    graph.after._sweep(None)
    assert graph.answers() == first and graph.alarms == []
    graph.send(6)
    assert graph.answers() == first * 2 and graph.executed == [('/proxy', 6, 0)]
