"""Publisher connections that never block the publishing thread, at no cost while the subscriber reads.

rospy writes a message to each subscriber of a publisher without a queue in the publishing thread
(``sendall``). When one subscriber stops reading (its host lost power: no FIN, no RST; its process is
frozen), that write blocks once the socket's buffers fill, and every other subscriber waits with it.
rospy's own queue (``queue_size``) avoids that with a thread per connection, at the price of a
thread hand-off on every message (PBR's median latency rose from 1.6 to 1.8 ms with the Protocol's
replies queued) and of silently dropping the oldest message when full.

:class:`SpilloverConnection` wraps one rospy connection:
- while nothing is waiting, a message is written at once with a non-blocking send, in the
  publishing thread, as rospy would (no hand-off);
- what the socket cannot take now (a partial send, a full buffer) spills into a buffer that a
  thread of the connection's own drains in order; later messages go behind it, so the subscriber
  sees them in order; once drained, writes are direct again;
- past ``max_bytes`` waiting, the connection is given up (rospy closes it and drops the subscriber;
  an FTM subscriber connects again, its Proxy re-sends what it misses): never a silent drop of
  single messages, and a warning names the subscriber.
A TLS connection (an ``ssl.SSLSocket`` cannot send with MSG_DONTWAIT) is written as before; the
kernel's limit on unacknowledged data (aft_ftm.ros.handshake.unacknowledged_limit) bounds it.
"""
import collections
import socket
import ssl
import threading

MAX_BYTES = 16 << 20   # bytes waiting for one subscriber before it is given up


class SpilloverConnection(object):
    """A rospy publisher connection (a TCPROSTransport) whose writes never block (module docstring).
    Everything but write_data and close is the wrapped connection's."""

    def __init__(self, connection, max_bytes=MAX_BYTES, warn=None):
        self._connection = connection
        self._max = max_bytes
        self._warn = warn or (lambda text: None)
        self._lock = threading.Condition()
        self._pending = collections.deque()
        self._pending_bytes = 0
        self._error = None
        self._closed = False
        self._thread = None
        self.spilled = 0   # messages that went through the buffer

    def __getattr__(self, name):
        if name.startswith('__'):
            raise AttributeError(name)
        return getattr(self._connection, name)

    def set_cleanup_callback(self, callback):
        """rospy's topic removes a closed connection through this callback: it gets this wrapper (the
        one in its list, found by identity), and the wrapper knows its connection is closed."""
        def closed(_connection):
            self._closing()
            callback(self)
        self._connection.set_cleanup_callback(closed)

    @property
    def cleanup_cb(self):
        return self._connection.cleanup_cb

    @property
    def pending_bytes(self):
        with self._lock:
            return self._pending_bytes

    def write_data(self, data):
        from rospy.exceptions import TransportTerminated
        sock = self._connection.socket
        if isinstance(sock, ssl.SSLSocket) or sock is None:
            return self._connection.write_data(data)
        with self._lock:
            if self._error is not None:
                raise self._error
            if self._closed or self._connection.done:
                raise TransportTerminated('connection closed')
            if not self._pending:   # (the chunk being drained stays first until it is sent)
                try:
                    sent = sock.send(data, socket.MSG_DONTWAIT)
                except (BlockingIOError, InterruptedError):
                    sent = 0
                except OSError as e:
                    self._error = TransportTerminated('write to %s failed: %s' % (self._connection.endpoint_id, e))
                    raise self._error
                if sent == len(data):
                    self._count(len(data), 1)
                    return True
                self._count(sent, 0)
                data = data[sent:]
            self._pending.append(data)
            self._pending_bytes += len(data)
            self.spilled += 1
            if self._pending_bytes > self._max:
                self._error = TransportTerminated(
                    'subscriber %s reads nothing: %d bytes wait for it (bound %d); given up'
                    % (self._connection.endpoint_id, self._pending_bytes, self._max))
                self._pending.clear()
                self._pending_bytes = 0
                self._lock.notify_all()
                self._warn(str(self._error))
                raise self._error
            if self._thread is None:
                self._thread = threading.Thread(target=self._drain, daemon=True,
                                                name='spillover-%s' % self._connection.endpoint_id)
                self._thread.start()
            self._lock.notify_all()
        return True

    def _count(self, size, messages):
        self._connection.stat_bytes += size
        self._connection.stat_num_msg += messages

    def _drain(self):
        while True:
            with self._lock:
                while not self._pending and not self._closed and self._error is None:
                    self._lock.wait()
                if self._closed or self._error is not None:
                    return
                chunk = self._pending[0]
            try:
                self._connection.socket.sendall(chunk)   # blocking, in order (bounded by the kernel's limit)
                failed = None
            except (OSError, AttributeError) as e:   # (AttributeError: rospy set the socket to None on close)
                failed = e
            with self._lock:
                if failed is None:
                    if self._pending and self._pending[0] is chunk:
                        self._pending.popleft()
                        self._pending_bytes -= len(chunk)
                        self._count(len(chunk), 1)
                    self._lock.notify_all()
                    continue
                from rospy.exceptions import TransportTerminated
                lost = (len(self._pending), self._pending_bytes)
                self._error = TransportTerminated('write to %s failed: %s' % (self._connection.endpoint_id, failed))
                self._pending.clear()
                self._pending_bytes = 0
                closed = self._closed
            if not closed:   # never silent: said, and the connection closed (rospy drops the subscriber)
                self._warn('%s; %d messages (%d bytes) waiting for it are not sent: the connection is closed'
                           % (self._error, lost[0], lost[1]))
                self.close()
            return

    def _closing(self):
        with self._lock:
            self._closed = True
            self._pending.clear()
            self._pending_bytes = 0
            self._lock.notify_all()

    def close(self):
        self._closing()
        return self._connection.close()


def spill_over(publisher, max_bytes=MAX_BYTES, warn=None):
    """Make every connection a rospy.Publisher adds from now on a SpilloverConnection (its
    implementation is shared by the process's publishers of that topic). A publisher with rospy's own
    queue is left as it is. Returns the publisher."""
    impl = publisher.impl
    if getattr(impl, 'spills_over', False) or impl.queue_size is not None:
        return publisher
    add = impl.add_connection

    def add_connection(c):
        return add(SpilloverConnection(c, max_bytes, warn))
    with impl.c_lock:
        impl.add_connection = add_connection
        impl.spills_over = True
        # A subscriber may have connected between the publisher's registration and now.
        wrapped = []
        for c in impl.connections:
            if not isinstance(c, SpilloverConnection):
                c = SpilloverConnection(c, max_bytes, warn)
                c.set_cleanup_callback(impl.remove_connection)
            wrapped.append(c)
        impl.connections = wrapped
    return publisher
