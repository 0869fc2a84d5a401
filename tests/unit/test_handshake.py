"""Bounded TCPROS handshakes (aft_ftm.ros.handshake): a connection that sends no whole header
cannot hold a node's TCPROS server for ever. No ROS master."""
import io
import socket
import struct
import time

import pytest
from rosgraph.network import read_ros_handshake_header

from aft_ftm.ros.handshake import bound_handshakes, bounded


def header(fields):
    body = b''.join(struct.pack('<I', len(f)) + f for f in (('%s=%s' % kv).encode() for kv in fields.items()))
    return struct.pack('<I', len(body)) + body


def test_an_http_call_on_a_tcpros_port_is_given_up_after_the_bound_and_the_socket_keeps_its_timeout():
    server, client = socket.socketpair()
    try:
        # The master's XML-RPC call meant for a dead node: "POST" is a 1.4 GB header length.
        client.sendall(b'POST /RPC2 HTTP/1.1\r\nHost: vm\r\n\r\n')
        read = bounded(read_ros_handshake_header, 0.3)
        t0 = time.monotonic()
        with pytest.raises(socket.timeout, match='no complete TCPROS handshake header within 0.3 s'):
            read(server, io.BytesIO(), 4096)
        assert 0.25 < time.monotonic() - t0 < 3.0
        assert server.gettimeout() is None          # blocking again, as rospy left it
    finally:
        server.close()
        client.close()


def test_a_whole_header_is_read_as_before_and_a_shorter_timeout_is_kept():
    server, client = socket.socketpair()
    try:
        client.sendall(header({'topic': '/aft/alarms', 'callerid': '/x'}))
        server.settimeout(0.1)
        got = bounded(read_ros_handshake_header, 10.0)(server, io.BytesIO(), 4096)
        assert got['topic'] == '/aft/alarms' and server.gettimeout() == 0.1
    finally:
        server.close()
        client.close()


def test_rospy_reads_its_headers_bounded_once_patched_and_patching_twice_changes_nothing():
    import rospy.impl.tcpros_base as base
    original = base.read_ros_handshake_header
    try:
        assert bound_handshakes(5.0) == 5.0
        patched = base.read_ros_handshake_header
        assert patched is not original and patched.bounded_to == 5.0
        assert bound_handshakes(1.0) == 5.0 and base.read_ros_handshake_header is patched
    finally:
        base.read_ros_handshake_header = original
