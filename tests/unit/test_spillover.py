"""Publisher connections whose writes never block (aft_ftm.ros.spillover), over real TCP sockets on the
loopback. No ROS master."""
import random
import socket
import struct
import threading
import time

import pytest
from rospy.exceptions import TransportTerminated

from aft_ftm.ros.spillover import SpilloverConnection


class FakeTransport(object):
    """What SpilloverConnection uses of a rospy TCPROSTransport."""

    def __init__(self, sock):
        self.socket = sock
        self.done = False
        self.endpoint_id = '/proxy2'
        self.stat_bytes = self.stat_num_msg = 0
        self.closed = 0
        self.cleanup_cb = None

    def set_cleanup_callback(self, callback):
        self.cleanup_cb = callback

    def write_data(self, data):
        self.socket.sendall(data)

    def close(self):   # as TCPROSTransport.close: once, then the cleanup callback with itself
        if self.done:
            return
        self.closed += 1
        self.done = True
        self.socket.close()
        if self.cleanup_cb:
            self.cleanup_cb(self)


@pytest.fixture
def pair():
    server = socket.socket()
    server.bind(('127.0.0.1', 0))
    server.listen(1)
    reader = socket.create_connection(server.getsockname())
    writer, _ = server.accept()
    server.close()
    yield writer, reader
    for s in (writer, reader):
        s.close()


def message(index, size):
    body = struct.pack('<II', index, size) + bytes([index % 251]) * size
    return struct.pack('<I', len(body)) + body


def read_messages(sock, count, timeout=20.0):
    """The (index, size) of count messages, checking each body."""
    sock.settimeout(timeout)
    buffer, out = b'', []
    while len(out) < count:
        chunk = sock.recv(1 << 16)
        assert chunk, 'connection closed after %d messages' % len(out)
        buffer += chunk
        while len(buffer) >= 4 and len(buffer) >= 4 + struct.unpack('<I', buffer[:4])[0]:
            length = struct.unpack('<I', buffer[:4])[0]
            body, buffer = buffer[4:4 + length], buffer[4 + length:]
            index, size = struct.unpack('<II', body[:8])
            assert body[8:] == bytes([index % 251]) * size, 'message %d altered' % index
            out.append((index, size))
    return out


def test_while_the_subscriber_reads_every_write_goes_at_once_in_the_callers_thread(pair):
    writer, reader = pair
    conn = SpilloverConnection(FakeTransport(writer))
    for i in range(200):
        assert conn.write_data(message(i, 100))
    assert read_messages(reader, 200) == [(i, 100) for i in range(200)]
    assert conn.spilled == 0 and conn.pending_bytes == 0
    assert (conn.stat_num_msg, conn.stat_bytes) == (200, 200 * len(message(0, 100)))   # rospy's statistics


def test_a_subscriber_that_reads_nothing_blocks_no_write_and_later_gets_everything_in_order(pair):
    """A dead or frozen subscriber: 8 MB, far beyond the sockets' buffers, written without blocking."""
    writer, reader = pair
    conn = SpilloverConnection(FakeTransport(writer))
    started = time.monotonic()
    for i in range(2000):
        conn.write_data(message(i, 4096))
    assert time.monotonic() - started < 2.0, 'the writes waited for the subscriber'
    assert conn.spilled > 0 and conn.pending_bytes > 0
    assert read_messages(reader, 2000) == [(i, 4096) for i in range(2000)]
    deadline = time.monotonic() + 5
    while conn.pending_bytes and time.monotonic() < deadline:
        time.sleep(0.01)
    assert conn.pending_bytes == 0
    conn.write_data(message(2000, 10))   # drained: direct again
    assert read_messages(reader, 1) == [(2000, 10)]


def test_past_its_bound_the_subscriber_is_given_up_with_a_warning_never_a_silent_drop(pair):
    writer, _reader = pair
    warned = []
    conn = SpilloverConnection(FakeTransport(writer), max_bytes=200000, warn=warned.append)
    with pytest.raises(TransportTerminated, match='/proxy2 reads nothing'):
        for i in range(10000):
            conn.write_data(message(i, 1000))
    assert len(warned) == 1 and '/proxy2' in warned[0]
    with pytest.raises(TransportTerminated):   # and for good: rospy closes it and drops the subscriber
        conn.write_data(message(0, 1))
    conn.close()
    assert conn._connection.closed == 1


def test_random_sizes_and_reader_pauses_deliver_the_stream_written(pair):
    """Seeded: messages of 1 B to 64 KB written while the reader pauses at random; the reader gets
    exactly what was written, in order."""
    seed = random.randrange(1 << 30)
    rng = random.Random(seed)
    writer, reader = pair
    conn = SpilloverConnection(FakeTransport(writer))
    sizes = [rng.choice((1, 100, 1000, 20000, 65536)) for _ in range(600)]
    written = b''.join(message(i, size) for i, size in enumerate(sizes))
    got = []

    def read():
        reader.settimeout(20)
        while sum(map(len, got)) < len(written):
            if rng.random() < 0.05:
                time.sleep(rng.uniform(0, 0.02))
            chunk = reader.recv(rng.choice((100, 4096, 1 << 16)))
            if not chunk:
                return
            got.append(chunk)
    thread = threading.Thread(target=read)
    thread.start()
    for i, size in enumerate(sizes):
        conn.write_data(message(i, size))
    thread.join(30)
    assert b''.join(got) == written, 'seed %d' % seed


def test_rospy_removes_the_wrapper_itself_when_its_connection_closes(pair):
    """rospy's topic keeps the wrapper in its list and removes a closed connection by what its cleanup
    callback is given: the wrapper, which stops taking writes."""
    writer, _reader = pair
    conn = SpilloverConnection(FakeTransport(writer))
    removed = []
    conn.set_cleanup_callback(removed.append)
    conn._connection.close()   # closed underneath (rospy's own write_data does so on a broken pipe)
    assert removed == [conn]
    with pytest.raises(TransportTerminated):
        conn.write_data(message(0, 1))


def test_a_drain_that_fails_says_what_it_did_not_send_and_closes_the_connection(pair):
    """The subscriber's host gone: the kernel aborts the connection (TCP_USER_TIMEOUT) under the drain.
    What waited is not sent; that is said, and the connection is closed so that rospy drops it."""
    writer, reader = pair
    warned, removed = [], []
    conn = SpilloverConnection(FakeTransport(writer), warn=warned.append)
    conn.set_cleanup_callback(removed.append)
    for i in range(3000):   # far beyond the buffers: the drain thread has work
        conn.write_data(message(i, 4096))
    reader.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack('ii', 1, 0))
    reader.close()   # a reset: the drain's sendall fails
    deadline = time.monotonic() + 10
    while not removed and time.monotonic() < deadline:
        time.sleep(0.01)
    assert removed == [conn] and conn._connection.closed == 1
    assert len(warned) == 1 and 'are not sent' in warned[0] and '/proxy2' in warned[0], warned
    with pytest.raises(TransportTerminated):
        conn.write_data(message(0, 1))
