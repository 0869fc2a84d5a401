"""TR's Before and After wired together without a master: a repeat that cannot run (the saved state
refused by the server's state manager) is never told as "failed, nothing changed". No ROS master."""
import collections
import threading

import pytest

from aft_examples.history import classify_error
from aft_ftm.voting import TimeRedundancyVote

tr = pytest.importorskip('aft_ftm.ros.tr_nodes')
from aft_ftm.ros.deadline import Deadline  # noqa: E402
from aft_msgs.msg import Reply, Request  # noqa: E402
from aft_msgs.srv import GetStateResponse, Repeat, SetStateResponse  # noqa: E402


class Ports(object):
    def __init__(self):
        self.out = collections.deque()

    def publish(self, port, msg):
        if port == 'out':
            self.out.append(msg)


class Account(object):
    """Withdraws 10 per execution; the first execution's result is corrupted (a transient value fault)."""

    def __init__(self):
        self.balance, self.corrupt_next, self.refuse_restore = 100, True, False

    def get_state(self):
        return GetStateResponse(state=str(self.balance).encode())

    def set_state(self, state):
        if self.refuse_restore:
            return SetStateResponse(success=False, message='StateError: bad state')
        self.balance = int(bytes(state))
        return SetStateResponse(success=True, message='')

    def execute(self, request):
        self.balance -= 10
        payload = b'999' if self.corrupt_next else str(self.balance).encode()
        self.corrupt_next = False
        return Reply(id=request.id, origin=request.origin, attempt=request.attempt, payload=payload)


@pytest.fixture
def wired(monkeypatch):
    alarms = []
    monkeypatch.setattr(tr, 'alarm', lambda ports, mechanism, kind, detail, request=None: alarms.append(kind))
    server = Account()
    before = object.__new__(tr.TrBeforeNode)   # the node's state, without its ROS set-up
    before.__dict__.update(server_timeout=1.0, site='', get_state=server.get_state, set_state=server.set_state,
                           held={}, lock=threading.Lock(), _deadline=Deadline('c'), _restore_deadline=Deadline('r'),
                           pending_restore=None, capturing_since=None, failed=None, ports=Ports())
    after = object.__new__(tr.TrAfterNode)
    after.__dict__.update(voter=TimeRedundancyVote(3), site='', failed=None, masked=0, ports=Ports())
    after.repeat = lambda **kw: before._on_repeat(Repeat._request_class(**kw))

    def call(rid):
        answers, executions = [], collections.deque([before.handle(Request(id=rid, origin='/proxy'))])
        while executions:   # bounded: at most ~executions repeats are published
            answer = after.handle(server.execute(executions.popleft()))
            if answer is not None:
                answers.append(answer)
            executions.extend(before.ports.out)
            before.ports.out.clear()
        assert len(answers) == 1
        return answers[0]
    return server, before, after, call, alarms


def test_a_value_fault_is_masked_by_the_vote(wired):
    server, before, after, call, alarms = wired
    answer = call(1)
    assert answer.status == Reply.OK and bytes(answer.payload) == b'90' and server.balance == 90
    assert alarms == ['value_fault_masked'] and before.held == {} and after.voter.pending() == 0


def test_a_repeat_whose_state_cannot_be_restored_is_an_unknown_outcome_with_an_alarm(wired):
    """Review, stop 38: the client was told "time redundancy: cannot execute again" (an error: nothing
    changed) while the server held the unvoted execution; no alarm; the saved state and the votes
    stayed for ever (one whole server state per request)."""
    server, before, after, call, alarms = wired
    server.refuse_restore = True
    answer = call(2)
    assert answer.status == Reply.ERROR and server.balance == 90   # one execution applied
    assert classify_error('service [/account] responded with an error: ' + answer.error) == 'indeterminate'
    assert alarms == ['restore_failed'] and before.held == {} and after.voter.pending() == 0
