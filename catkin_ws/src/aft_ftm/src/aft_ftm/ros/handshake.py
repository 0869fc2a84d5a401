"""Bounded TCPROS handshakes: a connection that never completes its header cannot wedge a node.

rospy reads an inbound connection's handshake header in its TCPROS server's one accept thread,
blocking and without a timeout (``rospy.impl.tcpros_base.TCPServer.run`` ->
``TCPROSHandler._tcp_server_callback`` -> ``rosgraph.network.read_ros_handshake_header``). A client
that connects and never sends a whole header (a frozen or dead client, a half-open connection from a
powered-off host, or bytes that are no TCPROS at all) stops that thread for good: no subscriber and
no service client can connect to the node any more, and their calls hang.

It happens in plain ROS 1, found by the campaign: a node restarted on the port a dead node's
XML-RPC API had used gets the master's HTTP call meant for the dead node; "POST" read as a header
length is 1.4 GB, and the read waits for ever. The relaunched witness was wedged that way, and every
call to it hung (scripts/campaign, 1000 faults, seed 2026, fault 348).

:func:`bound_handshakes` bounds that read to HANDSHAKE_TIMEOUT seconds (the socket's own timeout,
if shorter, is kept, and restored after the header): past it rospy logs the connection as failed,
closes it and accepts the next. ``run_node`` calls it before ``init_node``.
"""
import socket

HANDSHAKE_TIMEOUT = 10.0   # s: a header is a few hundred bytes; rospy answers in milliseconds


def bounded(read, timeout):
    """read_ros_handshake_header bounded to timeout seconds per header."""
    def read_bounded(sock, buffer, buff_size):
        previous = sock.gettimeout()
        if previous is None or previous > timeout:
            sock.settimeout(timeout)
        try:
            return read(sock, buffer, buff_size)
        except socket.timeout:
            raise socket.timeout('no complete TCPROS handshake header within %.1f s' % timeout)
        finally:
            sock.settimeout(previous)
    read_bounded.bounded_to = timeout
    return read_bounded


def bound_handshakes(timeout=HANDSHAKE_TIMEOUT):
    """Bound rospy's handshake reads (idempotent). Returns the timeout in force."""
    import rospy.impl.tcpros_base as base
    current = getattr(base.read_ros_handshake_header, 'bounded_to', None)
    if current is None:
        base.read_ros_handshake_header = bounded(base.read_ros_handshake_header, timeout)
        current = timeout
    return current
