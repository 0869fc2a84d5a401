"""Priority on the network for the crash detectors' heartbeats.

A heartbeat shares its link with the data. Behind a saturated rate limit it waited with the
checkpoints and the state transfers, was dropped past the limit's latency, and was resent by TCP only
after its retransmission timeout (200 ms, doubled each time): sent on time, the master's beats
reached the slave 501 ms late, and a 500 ms detector fenced a healthy site (a clean-clone CI, session
50). Each connection of a detector's heartbeat topics (both ways: the beats, and the
acknowledgments the receiver sends back) is marked low delay (IP TOS 0x10; Linux also gives such a
socket the interactive priority): the emulated hosts' rate limits serve it first
(:func:`aft_ftm.hosts.plan_rate`), as a network with QoS would.
"""
import socket
import weakref

from ..hosts import URGENT_TOS


class Marker(object):
    """Marks the sockets of rospy Publishers' and Subscribers' connections urgent, each once."""

    def __init__(self):
        # connection -> the socket marked (a connection made again, e.g. after a failed TLS handshake,
        # keeps its object and gets a new socket: marked again)
        self.marked = weakref.WeakKeyDictionary()
        self.failures = 0   # sockets that refused the mark (closed meanwhile)

    def mark(self, *handles):
        """Mark the sockets of these rospy handles' connections not marked yet; returns how many were
        marked now. Never raises (it runs in the heartbeat loop)."""
        count = 0
        for handle in handles:
            impl = getattr(handle, 'impl', None)
            for conn in list(getattr(impl, 'connections', None) or ()):
                sock = getattr(conn, 'socket', None)
                if sock is None:
                    continue   # not connected yet: marked at a later look
                try:
                    if self.marked.get(conn) is sock:
                        continue
                    self.marked[conn] = sock
                except TypeError:   # an object without weak references: never remembered, marked each look
                    pass
                try:
                    sock.setsockopt(socket.IPPROTO_IP, socket.IP_TOS, URGENT_TOS)
                    count += 1
                except (OSError, ValueError):   # closed meanwhile (ValueError: a closed SSL socket)
                    self.failures += 1
        return count
