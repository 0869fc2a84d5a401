"""The Adaptation Engine's LeaseKeeper with fake service connections (no ROS master): each held node
is renewed by a thread of its own, on the connection opened before the pause; a node hanging in
its answer delays no other; a refusal is reported as lost; stop() ends a thread waiting for a hung
node's answer at once."""
import socket
import threading
import time

import pytest

from aft_ftm.ros import adaptation_engine
from aft_ftm.ros.adaptation_engine import LeaseKeeper

LEASE = 0.2   # renewed every 0.05 s


class FakeNodes(object):
    """What each node answers to its ~suspend service: 'ok', 'refuse' or 'hang' (until stopped)."""

    def __init__(self):
        self.mode = {}
        self.renewals = {}        # node -> times renewed
        self.created = []         # (node, thread name) of each connection opened
        self.lock = threading.Lock()

    def proxy_class(self):
        nodes = self

        class Proxy(object):
            def __init__(self, name, _cls, persistent=False):
                assert persistent
                self.node = name[:-len('/suspend')]
                self.sock, self._peer = socket.socketpair()
                self.transport = type('Transport', (), {'socket': self.sock})()
                self.closed = False
                with nodes.lock:
                    nodes.created.append((self.node, threading.current_thread().name))

            def __call__(self, probe=False, renew=False, lease=0.0, owner=""):
                mode = nodes.mode.get(self.node, 'ok')
                if probe:
                    return type('Answer', (), {'success': True, 'message': 'CLOSED'})()
                if mode == 'hang':
                    if not self.sock.recv(1):   # as rospy waits for the answer: until cut
                        raise OSError('connection cut')
                with nodes.lock:
                    nodes.renewals[self.node] = nodes.renewals.get(self.node, 0) + 1
                if mode == 'refuse':
                    return type('Answer', (), {'success': False, 'message': 'not suspended (OPEN)'})()
                return type('Answer', (), {'success': True, 'message': 'lease renewed'})()

            def close(self):
                self.closed = True
                self.sock.close()
                self._peer.close()
        return Proxy


@pytest.fixture
def nodes(monkeypatch):
    fake = FakeNodes()
    monkeypatch.setattr(adaptation_engine.rospy, 'ServiceProxy', fake.proxy_class())
    return fake


def wait(predicate, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, 'not within %.1f s' % timeout
        time.sleep(0.01)


def test_each_held_node_is_renewed_on_the_connection_opened_before_the_pause(nodes):
    log = []
    keeper = LeaseKeeper(LEASE, log.append)
    for node in ('/a/protocol', '/b/protocol'):
        keeper.connect(node)
    opened = list(nodes.created)
    for node in ('/a/protocol', '/b/protocol'):
        keeper.hold(node)
    try:
        wait(lambda: min(nodes.renewals.get(n, 0) for n in ('/a/protocol', '/b/protocol')) >= 3)
    finally:
        keeper.stop()
    # No connection opened in the pause: a renewal needs no ROS master.
    assert nodes.created == opened
    assert keeper.lost() == {}
    assert log == []


def test_a_node_hanging_in_its_answer_delays_no_other_and_stop_cuts_it(nodes):
    nodes.mode['/a/protocol'] = 'hang'
    keeper = LeaseKeeper(LEASE, lambda text: None)
    for node in ('/a/protocol', '/b/protocol'):
        keeper.connect(node)
        keeper.hold(node)
    wait(lambda: nodes.renewals.get('/b/protocol', 0) >= 5)   # 5 periods while /a hangs
    assert nodes.renewals.get('/a/protocol', 0) == 0
    start = time.monotonic()
    keeper.stop()
    assert time.monotonic() - start < 2.0   # not the 5 s join bound: the hung call was cut
    assert not [t for t in threading.enumerate() if t.name.startswith('lease_keeper')]


def test_a_refused_renewal_is_lost_and_renewed_no_more_while_a_released_node_is_not(nodes):
    nodes.mode['/a/protocol'] = 'refuse'
    log = []
    keeper = LeaseKeeper(LEASE, log.append)
    keeper.hold('/a/protocol')    # not connected before: its first renewal opens the connection
    keeper.hold('/b/protocol')
    try:
        wait(lambda: '/a/protocol' in keeper.lost())
        keeper.release('/b/protocol')
        renewed = nodes.renewals.get('/a/protocol', 0)
        time.sleep(4 * LEASE)
        assert nodes.renewals.get('/a/protocol', 0) == renewed == 1
        assert list(keeper.lost()) == ['/a/protocol']   # /b was released, not lost
        assert 'not suspended (OPEN)' in keeper.lost()['/a/protocol']
        assert any('/a/protocol is no longer suspended' in line for line in log)
        # Held again (a later suspension of the same node): renewed again, by a new thread.
        nodes.mode['/b/protocol'] = 'ok'
        before = nodes.renewals.get('/b/protocol', 0)
        keeper.hold('/b/protocol')
        wait(lambda: nodes.renewals.get('/b/protocol', 0) >= before + 2)
    finally:
        keeper.stop()
