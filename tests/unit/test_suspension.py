"""The gate that suspends a node: quiescence first, then every held message delivered in order;
a suspension's lease, and the bound of its buffer."""
import collections
import threading
import time

import pytest
from fakes import FakeClock

from aft_ftm.suspension import GATE_EDGES, Event, Gate, GateState, SuspendError, approx_size


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


# -- leases -------------------------------------------------------------------------------------

class LeasedNode(Node):
    """A Node whose gate tells what it ends on its own, on a fake clock."""

    def __init__(self, max_bytes=None, size=None):
        super(LeasedNode, self).__init__()
        self.clock = FakeClock(100.0)
        self.events = []
        self.gate = Gate({'inp': self.on_input, 'results': self.on_result}, max_bytes=max_bytes,
                         size=size or (lambda msg: 10), on_self_resume=lambda e, d: self.events.append((e, d)))

    def suspend(self, lease):
        return self.gate.close(['inp'], self.quiescent, 1.0, clock=lambda: self.clock.now, lease=lease)


def test_a_suspension_whose_lease_runs_out_resumes_by_itself_delivering_what_it_held():
    node = LeasedNode()
    node.suspend(lease=2.0)
    for i in range(3):
        node.gate.deliver('inp', i)
    assert node.gate.lease_left(node.clock.now) == 2.0
    assert node.gate.expire(node.clock.advance(1.999)) is None     # still within the lease
    assert node.handled == [] and node.gate.state == GateState.CLOSED
    assert node.gate.expire(node.clock.advance(0.001)) == 3
    assert node.handled == [0, 1, 2] and node.gate.state == GateState.OPEN
    assert [e for e, _ in node.events] == [Event.LEASE_EXPIRED]
    assert 'lease of 2 s expired' in node.events[0][1] and '3 held messages delivered' in node.events[0][1]
    assert node.gate.self_resumed == 1
    node.gate.deliver('inp', 3)                                      # running again: handled at once
    assert node.handled == [0, 1, 2, 3]


def test_a_renewal_extends_the_lease_and_changes_nothing_else():
    node = LeasedNode()
    node.suspend(lease=2.0)
    node.gate.deliver('inp', 1)
    assert node.gate.renew(2.0, node.clock.advance(1.5)) == 1       # from now on: 2 s more
    assert node.gate.expire(node.clock.advance(1.9)) is None        # 3.4 s after the suspension
    assert node.gate.state == GateState.CLOSED and node.handled == [] and node.gate.held == 1
    assert node.gate.expire(node.clock.advance(0.1)) == 1
    assert node.handled == [1]


def test_resumed_before_its_lease_runs_out_nothing_expires_later():
    node = LeasedNode()
    node.suspend(lease=2.0)
    node.gate.deliver('inp', 1)
    assert node.gate.open() == 1
    assert node.gate.lease_left(node.clock.now) is None
    assert node.gate.expire(node.clock.advance(10.0)) is None
    assert node.events == [] and node.gate.self_resumed == 0


def test_renewing_a_node_that_resumed_by_itself_is_refused_saying_why():
    node = LeasedNode()
    node.suspend(lease=1.0)
    node.gate.expire(node.clock.advance(1.0))
    with pytest.raises(SuspendError, match='not suspended .OPEN.*lease expired'):
        node.gate.renew(1.0, node.clock.now)
    assert node.gate.state == GateState.OPEN


def test_without_a_lease_a_suspension_lasts_until_resumed():
    node = LeasedNode()
    node.suspend(lease=None)
    assert node.gate.lease_left(node.clock.now) is None
    assert node.gate.expire(node.clock.advance(1e6)) is None
    assert node.gate.state == GateState.CLOSED


def test_suspending_a_suspended_node_sets_its_lease_anew():
    node = LeasedNode()
    node.suspend(lease=1.0)
    node.clock.advance(0.9)
    node.suspend(lease=5.0)
    assert node.gate.lease_left(node.clock.now) == 5.0


# -- the bound of the held buffer ---------------------------------------------------------------

def payload_size(msg):
    return len(msg.payload)


Message = collections.namedtuple('Message', 'id payload')   # stands in for aft_msgs/Request (hashable)


def message(i, size):
    return Message(i, b'x' * size)


def test_the_message_that_would_overflow_the_buffer_ends_the_suspension_and_none_is_dropped():
    node = LeasedNode(max_bytes=100, size=payload_size)
    node.suspend(lease=10.0)
    msgs = [message(i, 30) for i in range(4)]
    for msg in msgs[:3]:
        node.gate.deliver('inp', msg)                 # 90 bytes: held
    assert node.handled == [] and node.gate.held_bytes == 90
    node.gate.deliver('inp', msgs[3])                 # 120 > 100: the gate gives up
    assert node.handled == msgs                       # all of them, in arrival order, the last one last
    assert node.gate.state == GateState.OPEN and node.gate.held == 0 and node.gate.held_bytes == 0
    assert [e for e, _ in node.events] == [Event.BUFFER_FULL]
    assert 'over the bound of 100 bytes' in node.events[0][1] and '4 held messages delivered' in node.events[0][1]
    with pytest.raises(SuspendError, match='buffer full'):   # the engine's renewal learns it
        node.gate.renew(10.0, node.clock.now)
    node.gate.deliver('inp', message(4, 1000))        # not suspended: no bound applies
    assert len(node.handled) == 5


def test_a_single_message_larger_than_the_bound_is_delivered_not_dropped():
    node = LeasedNode(max_bytes=100, size=payload_size)
    node.suspend(lease=10.0)
    big = message(0, 101)
    node.gate.deliver('inp', big)
    assert node.handled == [big] and node.gate.state == GateState.OPEN


def test_a_buffer_filling_up_before_quiescence_gives_the_suspension_up():
    node = LeasedNode(max_bytes=50, size=payload_size)
    node.gate.deliver('inp', message(0, 1))            # executing: not quiescent
    errors = []

    def suspend():
        try:
            node.gate.close(['inp'], node.quiescent, 5.0, lease=10.0)
        except SuspendError as e:
            errors.append(str(e))
    thread = threading.Thread(target=suspend)
    thread.start()
    while node.gate.state != GateState.CLOSING:
        time.sleep(0.001)
    node.gate.deliver('inp', message(1, 40))
    node.gate.deliver('inp', message(2, 40))           # 80 > 50
    thread.join(5)
    assert errors and 'buffer full before quiescence' in errors[0]
    assert [m.id for m in node.handled] == [0, 1, 2] and node.gate.state == GateState.OPEN


def test_the_default_size_of_a_message_counts_its_payload_fields_and_nested_messages():
    class Header(object):
        __slots__ = ('seq', 'frame_id')

        def __init__(self):
            self.seq, self.frame_id = 1, 'base'

    class Request(object):   # as genpy declares one: its fields are its __slots__
        __slots__ = ('id', 'origin', 'payload', 'header', 'ranges')

        def __init__(self, payload, ranges=()):
            self.id, self.origin, self.payload, self.header, self.ranges = 7, '/proxy', payload, Header(), list(ranges)
    small, large = approx_size(Request(b'')), approx_size(Request(b'\0' * 10 ** 6))
    assert large - small == 10 ** 6
    assert 0 < small < 100
    assert approx_size(Request(b'', ranges=[0.5] * 1000)) - small == 8000


# -- every state change is an edge of GATE_EDGES -------------------------------------------------

def edges_of(scenario):
    """The (state, event) edges a scenario takes, on a gate of its own."""
    taken = []
    node = LeasedNode(max_bytes=25, size=lambda msg: 10)
    change = node.gate._change

    def record(event):
        taken.append((node.gate.state, event))
        return change(event)
    node.gate._change = record
    scenario(node)
    return taken


def resume_while_suspending(node):
    node.gate.deliver('inp', 1)               # not quiescent: the suspension waits
    thread = threading.Thread(target=lambda: pytest.raises(SuspendError, node.suspend, 10.0))
    thread.start()
    while node.gate.state != GateState.CLOSING:
        time.sleep(0.001)
    node.gate.open()
    thread.join(5)


def overflow_while_suspending(node):
    node.gate.deliver('inp', 1)
    thread = threading.Thread(target=lambda: pytest.raises(SuspendError, node.suspend, 10.0))
    thread.start()
    while node.gate.state != GateState.CLOSING:
        time.sleep(0.001)
    for i in range(3):
        node.gate.deliver('inp', 10 + i)
    thread.join(5)


def not_quiescent_in_time(node):
    node.gate.deliver('inp', 1)
    with pytest.raises(SuspendError):
        node.gate.close(['inp'], node.quiescent, 0.01)


def lease_runs_out(node):
    node.suspend(1.0)
    node.gate.expire(node.clock.advance(1.0))


def overflow_while_suspended(node):
    node.suspend(1.0)
    for i in range(3):
        node.gate.deliver('inp', i)


O, CG, C, OG = GateState.OPEN, GateState.CLOSING, GateState.CLOSED, GateState.OPENING
SCENARIOS = [
    (lambda node: (node.suspend(1.0), node.gate.open()),
     [(O, Event.SUSPEND), (CG, Event.QUIESCENT), (C, Event.RESUME), (OG, Event.DELIVERED)]),
    (not_quiescent_in_time, [(O, Event.SUSPEND), (CG, Event.TIMEOUT), (OG, Event.DELIVERED)]),
    (resume_while_suspending, [(O, Event.SUSPEND), (CG, Event.RESUME), (OG, Event.DELIVERED)]),
    (overflow_while_suspending, [(O, Event.SUSPEND), (CG, Event.BUFFER_FULL), (OG, Event.DELIVERED)]),
    (lease_runs_out, [(O, Event.SUSPEND), (CG, Event.QUIESCENT), (C, Event.LEASE_EXPIRED), (OG, Event.DELIVERED)]),
    (overflow_while_suspended, [(O, Event.SUSPEND), (CG, Event.QUIESCENT), (C, Event.BUFFER_FULL),
                                (OG, Event.DELIVERED)]),
]


@pytest.mark.parametrize('scenario,expected', SCENARIOS)
def test_each_way_through_a_suspension_takes_the_edges_of_the_table(scenario, expected):
    assert edges_of(scenario) == expected


def test_the_edges_table_has_a_reason_for_every_change_and_no_edge_unused():
    taken = {edge for _, expected in SCENARIOS for edge in expected}
    assert taken == set(GATE_EDGES)
    assert all(isinstance(to, GateState) and reason for to, reason in GATE_EDGES.values())
    # No edge out of OPEN but a suspension; nothing to expire nor overflow on a running node.
    gate = Gate({'inp': lambda msg: None})
    for event in (Event.LEASE_EXPIRED, Event.BUFFER_FULL, Event.RESUME, Event.DELIVERED):
        with pytest.raises(SuspendError, match='not allowed in state OPEN'):
            gate._change(event)
        assert gate.state == GateState.OPEN
