"""Bounded TCPROS handshakes (aft_ftm.ros.handshake): a connection that sends no whole header
cannot hold a node's TCPROS server for ever. No ROS master."""
import io
import socket
import struct
import threading
import time

import pytest
from rosgraph.network import read_ros_handshake_header

from aft_ftm.ros.handshake import HandshakeRefused, bound_handshakes, bounded, threaded


def header(fields):
    body = b''.join(struct.pack('<I', len(f)) + f for f in (('%s=%s' % kv).encode() for kv in fields.items()))
    return struct.pack('<I', len(body)) + body


def test_an_http_call_on_a_tcpros_port_is_refused_at_once_naming_what_it_announced():
    server, client = socket.socketpair()
    try:
        # The master's XML-RPC call meant for a dead node: "POST" is a 1.4 GB header length.
        client.sendall(b'POST /RPC2 HTTP/1.1\r\nHost: vm\r\n\r\n')
        read = bounded(read_ros_handshake_header, 30.0)
        t0 = time.monotonic()
        with pytest.raises(HandshakeRefused, match="1414745936 bytes announced .b'POST'"):
            read(server, io.BytesIO(), 4096)
        assert time.monotonic() - t0 < 5.0          # not the 30 s bound
        assert server.gettimeout() is None          # blocking again, as rospy left it
    finally:
        server.close()
        client.close()


def test_a_connection_that_sends_part_of_a_header_is_given_up_after_the_bound():
    server, client = socket.socketpair()
    try:
        whole = header({'topic': '/aft/alarms', 'callerid': '/x'})
        client.sendall(whole[:9])                   # a frozen client: length and part of a field
        read = bounded(read_ros_handshake_header, 0.3)
        t0 = time.monotonic()
        with pytest.raises(socket.timeout, match='no complete TCPROS handshake header within 0.3 s'):
            read(server, io.BytesIO(), 4096)
        assert 0.25 < time.monotonic() - t0 < 3.0
        assert server.gettimeout() is None
    finally:
        server.close()
        client.close()


def test_a_header_whose_length_arrives_in_pieces_is_read_whole():
    server, client = socket.socketpair()
    try:
        whole = header({'service': '/aft/witness/request', 'callerid': '/x'})
        client.sendall(whole[:2])
        threading.Timer(0.1, client.sendall, (whole[2:],)).start()
        got = bounded(read_ros_handshake_header, 5.0)(server, io.BytesIO(), 4096)
        assert got['service'] == '/aft/witness/request'
    finally:
        server.close()
        client.close()


def test_a_connection_stuck_in_its_handshake_does_not_hold_the_next_one():
    """Each inbound connection gets its own thread: the accept loop calls the handler and goes on."""
    release = threading.Event()
    handled = []

    def callback(_self, sock, addr):
        if addr[0] == 'stuck':
            release.wait(5.0)
        handled.append(addr)
    handle = threaded(callback)
    try:
        handle(None, None, ('stuck', 1))
        handle(None, None, ('next', 2))
        deadline = time.monotonic() + 5.0
        while ('next', 2) not in handled and time.monotonic() < deadline:
            time.sleep(0.01)
        assert handled == [('next', 2)]
    finally:
        release.set()


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


def test_rospy_reads_its_headers_bounded_in_a_thread_each_once_patched_and_patching_twice_changes_nothing():
    import rospy.impl.tcpros_base as base
    original = base.read_ros_handshake_header
    callback = base.TCPROSServer._tcp_server_callback
    try:
        assert bound_handshakes(5.0) == 5.0
        patched = base.read_ros_handshake_header
        handler = base.TCPROSServer._tcp_server_callback
        assert patched is not original and patched.bounded_to == 5.0 and handler.threaded
        assert bound_handshakes(1.0) == 5.0 and base.read_ros_handshake_header is patched
        assert base.TCPROSServer._tcp_server_callback is handler
    finally:
        base.read_ros_handshake_header = original
        base.TCPROSServer._tcp_server_callback = callback
