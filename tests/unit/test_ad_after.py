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
