"""The gate that suspends a node: quiescence first, then every held message delivered in order."""
import threading
import time

import pytest

from aft_ftm.suspension import Gate, GateState, SuspendError


class Node(object):
    """A node with an input port and a result port; a request is "inside" until its result comes."""

    def __init__(self):
        self.handled = []
        self.inside = set()
        self.gate = Gate({'inp': self.on_input, 'results': self.on_result})

    def on_input(self, msg):
        self.handled.append(msg)
        self.inside.add(msg)

    def on_result(self, msg):
        self.inside.discard(msg)

    def quiescent(self):
        return not self.inside


def test_an_open_gate_hands_messages_on_at_once():
    node = Node()
    node.gate.deliver('inp', 1)
    assert node.handled == [1]


def test_suspension_waits_until_nothing_is_inside_while_results_still_flow():
    node = Node()
    node.gate.deliver('inp', 1)            # request 1 is executing
    closed = []
    thread = threading.Thread(target=lambda: closed.append(node.gate.close(['inp'], node.quiescent, 5.0)))
    thread.start()
    while node.gate.state == GateState.OPEN:   # the suspension has begun
        time.sleep(0.001)
    node.gate.deliver('inp', 2)            # arrives while suspending: held
    assert node.handled == [1] and thread.is_alive()
    node.gate.deliver('results', 1)        # not held: what is inside can finish
    thread.join(5)
    assert closed == [1] and node.gate.state == GateState.CLOSED


def test_held_messages_are_delivered_in_arrival_order_on_resume_and_none_is_lost():
    node = Node()
    node.gate.close(['inp'], node.quiescent, 1.0)
    for i in range(1000):
        node.gate.deliver('inp', i)
    assert node.handled == [] and node.gate.held == 1000
    assert node.gate.open() == 1000
    assert node.handled == list(range(1000)) and node.gate.state == GateState.OPEN
    node.gate.deliver('inp', 1000)
    assert node.handled[-1] == 1000


def test_a_message_arriving_during_the_delivery_of_held_ones_does_not_overtake_them():
    node = Node()
    node.gate.close(['inp'], node.quiescent, 1.0)
    node.gate.deliver('inp', 0)
    node.gate.deliver('inp', 1)
    original = node.on_input

    def slow_first(msg):
        original(msg)
        if msg == 0:
            node.gate.deliver('inp', 2)   # arrives while 1 is still held
    node.gate._callbacks['inp'] = slow_first
    node.gate.open()
    assert node.handled == [0, 1, 2]


def test_a_component_not_quiescent_in_time_is_resumed_and_the_suspension_refused():
    node = Node()
    node.gate.deliver('inp', 1)            # never gets a result
    with pytest.raises(SuspendError, match='not quiescent within 0.050 s'):
        node.gate.close(['inp'], node.quiescent, 0.05)
    assert node.gate.state == GateState.OPEN
    node.gate.deliver('inp', 2)
    assert node.handled == [1, 2]


def test_suspending_twice_is_harmless_and_resuming_a_running_node_delivers_nothing():
    node = Node()
    assert node.gate.open() == 0
    node.gate.close(['inp'], node.quiescent, 1.0)
    node.gate.deliver('inp', 1)
    assert node.gate.close(['inp'], node.quiescent, 1.0) == 1
    assert node.gate.open() == 1


def test_a_failing_handler_does_not_keep_the_other_held_messages_back():
    errors = []
    handled = []

    def handler(msg):
        if msg == 1:
            raise ValueError('bad message')
        handled.append(msg)
    gate = Gate({'inp': handler}, log_error=errors.append)
    gate.close(['inp'], lambda: True, 1.0)
    for i in range(3):
        gate.deliver('inp', i)
    assert gate.open() == 3
    assert handled == [0, 2] and 'bad message' in errors[0]
