"""The crash detectors' heartbeat connections marked low delay (IP TOS 0x10), which the emulated hosts'
rate limits serve first (aft_ftm.hosts.plan_rate): real sockets, no ROS."""
import socket
import types

import pytest

qos = pytest.importorskip('aft_ftm.ros.qos')
from aft_ftm.hosts import URGENT_TOS  # noqa: E402


class Connection(object):
    """A rospy transport: its socket (None until connected)."""

    def __init__(self, sock):
        self.socket = sock


def connected():
    """A listening socket and two client sockets connected to it."""
    server = socket.socket()
    server.bind(('127.0.0.1', 0))
    server.listen(2)
    return server, socket.create_connection(server.getsockname()), socket.create_connection(server.getsockname())


def handle(*socks):
    return types.SimpleNamespace(impl=types.SimpleNamespace(connections=[Connection(s) for s in socks]))


def test_each_connection_of_the_heartbeat_topics_is_marked_once_and_new_ones_later():
    server, first, second = connected()
    try:
        marker = qos.Marker()
        beats, peer = handle(first), handle(None)       # the subscriber not connected yet
        assert marker.mark(beats, peer) == 1
        assert first.getsockopt(socket.IPPROTO_IP, socket.IP_TOS) == URGENT_TOS
        assert marker.mark(beats, peer) == 0            # each once
        peer.impl.connections.append(Connection(second))
        assert marker.mark(beats, peer) == 1 and second.getsockopt(socket.IPPROTO_IP, socket.IP_TOS) == URGENT_TOS
    finally:
        for s in (first, second, server):
            s.close()


def test_a_closed_connection_or_a_handle_without_connections_changes_nothing():
    closed = socket.socket()
    closed.close()
    marker = qos.Marker()
    assert marker.mark(handle(closed), None, types.SimpleNamespace()) == 0 and marker.failures == 1


def test_a_connection_made_again_with_a_new_socket_is_marked_again():
    """rospy keeps a subscriber's connection object when it connects again (a failed TLS handshake sets
    its socket to None, then a new one): the new socket must be marked too (review of session 50)."""
    server, first, again = connected()
    try:
        marker = qos.Marker()
        peer = handle(first)
        assert marker.mark(peer) == 1
        peer.impl.connections[0].socket = None
        assert marker.mark(peer) == 0
        peer.impl.connections[0].socket = again
        assert marker.mark(peer) == 1 and again.getsockopt(socket.IPPROTO_IP, socket.IP_TOS) == URGENT_TOS
    finally:
        for s in (first, again, server):
            s.close()
