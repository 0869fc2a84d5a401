"""Bounded TCPROS handshakes: a connection that never completes its header cannot wedge a node.

rospy reads an inbound connection's handshake header in its TCPROS server's one accept thread,
blocking and without a timeout (``rospy.impl.tcpros_base.TCPServer.run`` ->
``TCPROSServer._tcp_server_callback`` -> ``rosgraph.network.read_ros_handshake_header``), and its
listen backlog is 5. A client that connects and never sends a whole header (a frozen or dead client,
a half-open connection from a powered-off host, or bytes that are no TCPROS at all) stops that
thread: the backlog fills, later connections are dropped at SYN and retried by the kernel after
1, 3, 7, 15 s, so no subscriber and no service client can connect to the node any more.

It happens in plain ROS 1, found by the campaign: a node restarted on the port a dead node's
XML-RPC API had used gets the master's HTTP call meant for the dead node; "POST" read as a header
length is 1.4 GB, and the read waits for ever. The relaunched witness was wedged that way, and every
call to it hung (scripts/campaign, 1000 faults, seed 2026, fault 348).

:func:`bound_handshakes` (``run_node`` calls it before ``init_node``) changes three things:
- each inbound connection is handled in a thread of its own, so the accept thread only accepts
  (rospy's own comment there: "leave threading decisions up to inbound_handler"); answering a
  subscriber and adding its connection stay one at a time (:func:`one_subscriber_at_a_time`);
- a header read waits at most HANDSHAKE_TIMEOUT seconds (the socket's own timeout, if shorter, is
  kept, and restored after the header);
- a header whose announced length is beyond MAX_HEADER_BYTES (an HTTP request, garbage) is refused
  at once, without waiting for bytes that will never come.
Past either bound rospy logs the inbound connection as failed and closes it.
"""
import select
import socket
import struct
import threading
import time

HANDSHAKE_TIMEOUT = 10.0   # s: a header is a few hundred bytes; rospy answers in milliseconds
# s: an inbound connection whose sent data stays unacknowledged this long is aborted by the kernel
# (TCP_USER_TIMEOUT), see unacknowledged_limit(). 0: the kernel's own (about 15 min of retransmissions).
USER_TIMEOUT = 10.0
MAX_USER_TIMEOUT = (2 ** 31 - 1) // 1000   # s: the socket option is a signed 32-bit count of ms
_LIMIT = {'ms': 0}
INBOUND_HOOKS = []   # hook(server, sock, client_addr) -> the socket to hand to rospy, or None (closed): TLS
MAX_HEADER_BYTES = 16 << 20   # a header carries a message definition: kilobytes; 'POST' reads as 1.4 GB


class HandshakeRefused(socket.error):
    """The connection announced a header no TCPROS peer sends."""


class _Deadlined(object):
    """A socket whose reads all end by one deadline: the timeout was per recv, and a peer sending a
    byte every few seconds held its thread and its buffer for as long as it liked (review of session
    36)."""

    def __init__(self, sock, deadline):
        self._sock, self._deadline = sock, deadline

    def recv(self, count, *flags):
        left = self._deadline - time.monotonic()
        if left <= 0:
            raise socket.timeout('the handshake\'s time is up')
        self._sock.settimeout(left)
        return self._sock.recv(count, *flags)

    def __getattr__(self, name):
        return getattr(self._sock, name)


def _announced_length(sock, deadline=None):
    """The header length in the first 4 bytes, peeked (left for the reader); None if the peer
    closed before sending them. A socket with a timeout is non-blocking underneath, where MSG_WAITALL
    returns what is there: peeked again until the 4 bytes are (one byte sent alone skipped the bound
    on the announced length; review of session 36), until ``deadline`` (socket.timeout past it)."""
    while True:
        first = sock.recv(4, socket.MSG_PEEK | socket.MSG_WAITALL)
        if len(first) >= 4:
            return struct.unpack('<I', first[:4])[0]
        if not first:
            return None
        if deadline is not None and time.monotonic() >= deadline:
            raise socket.timeout('fewer than 4 bytes of a header within the handshake\'s time')
        time.sleep(0.005)


def _read_exactly(sock, count):
    """count bytes, or fewer if the peer closes first."""
    data = b''
    while len(data) < count:
        chunk = sock.recv(count - len(data))
        if not chunk:
            break
        data += chunk
    return data


def bounded(read, timeout, max_bytes=MAX_HEADER_BYTES):
    """read_ros_handshake_header bounded to timeout seconds per header and max_bytes per header."""
    def read_bounded(sock, buffer, buff_size):
        previous = sock.gettimeout()
        deadline = time.monotonic() + (timeout if previous is None else min(previous, timeout))
        if previous is None or previous > timeout:
            sock.settimeout(timeout)
        try:
            if buffer.tell() == 0:   # nothing read yet: the length comes first
                if hasattr(sock, 'getpeercert'):
                    # A TLS socket cannot be peeked at: its 4 length bytes are read into the buffer,
                    # where the reader takes them as its own.
                    first = _read_exactly(_Deadlined(sock, deadline), 4)
                    buffer.write(first)
                    length = struct.unpack('<I', first)[0] if len(first) == 4 else None
                else:
                    length = _announced_length(sock, deadline)
                if length is not None and length > max_bytes:
                    raise HandshakeRefused('not a TCPROS handshake: a header of %d bytes announced (%r)'
                                           % (length, struct.pack('<I', length)))
            return read(_Deadlined(sock, deadline), buffer, buff_size)
        except socket.timeout:
            raise socket.timeout('no complete TCPROS handshake header within %.1f s' % timeout)
        finally:
            try:
                sock.settimeout(previous)
            except OSError:   # closed meanwhile (rospy closes a connection it gave up on)
                pass
    read_bounded.bounded_to = timeout
    return read_bounded


def peer_hung_up(sock):
    """True if the peer has closed (or reset) its end: an orderly EOF is waiting. Data or nothing
    yet: False. Never waits (rospy's sockets may carry a timeout, which recv would wait out) and
    consumes nothing. A TLS socket is peeked at below its TLS layer (records, not data, are left
    in place), unless TLS data is already buffered in it (then it is not hung up)."""
    tls_socket = hasattr(sock, 'getpeercert')
    if tls_socket and sock.pending():
        return False
    poller = select.poll()
    poller.register(sock, select.POLLIN | select.POLLPRI)
    if not poller.poll(0):
        return False
    try:
        receive = socket.socket.recv if tls_socket else type(sock).recv   # the kernel's socket, not TLS's
        return receive(sock, 1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b''
    except (BlockingIOError, InterruptedError, socket.timeout):
        return False
    except OSError:   # reset, or closed here meanwhile
        return True


def one_subscriber_at_a_time(handler, lock=None, log=None):
    """rospy's topic_connection_handler, made safe for connections handled in parallel threads.

    rospy answers a subscriber's header, then adds the connection and drops an older one from the
    same subscriber. A subscriber told of a publisher twice at once (two publisherUpdate calls) makes
    two transports; adding the second closes the first, before the second even connects, and it keeps
    the second. Handled out of order (the second's header read first), the publisher kept the first,
    the one the subscriber had closed, dropped the second, and that subscription was lost for good
    (the adapting campaign and CI: replacement nodes that never set up). So, under one lock (answer
    and add are not interleaved), a connection whose subscriber has already hung up is closed
    unanswered instead of replacing a live one: its FIN left before the live connection's SYN, so it
    is there to see. Header reads stay in parallel, and a stuck connection holds nobody."""
    lock = threading.Lock() if lock is None else lock

    def handle(sock, client_addr, header):
        with lock:
            if peer_hung_up(sock):
                if log is not None:
                    log('inbound connection from %s for %s closed by %s before it was answered: not added'
                        % (client_addr, header.get('topic'), header.get('callerid')))
                sock.close()
                return None
            return handler(sock, client_addr, header)
    handle.one_subscriber_at_a_time = True
    return handle


def _rospy_info(text):
    import rospy
    rospy.loginfo(text)


def threaded(callback):
    """callback(self, sock, addr) run in a daemon thread of its own per connection; the server's
    topic_connection_handler (set by rospy at init_node) wrapped by one_subscriber_at_a_time."""
    def handle(self, sock, client_addr):
        if _LIMIT['ms']:
            try:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, _LIMIT['ms'])
            except (OSError, AttributeError):   # not TCP (a test's socket pair), or not Linux
                pass
        topic_handler = getattr(self, 'topic_connection_handler', None)
        if topic_handler is not None and not getattr(topic_handler, 'one_subscriber_at_a_time', False):
            self.topic_connection_handler = one_subscriber_at_a_time(topic_handler, log=_rospy_info)   # accept thread: no race
        # At most MAX_HANDSHAKES at once: past that a new connection is closed unanswered (its peer
        # connects again; rospy's subscribers and service clients do), and a failure to start a thread
        # closes it too. Both once ended rospy's accept thread (it catches socket errors only), and the
        # node took no subscriber or service client any more, with a traceback on stderr alone (review
        # of session 36: a flood of connections that send nothing, or a byte at a time).
        if not _HANDSHAKES.acquire(blocking=False):
            _close_refused(sock, client_addr, 'more than %d connections are in their handshake' % MAX_HANDSHAKES)
            return
        try:
            threading.Thread(target=_handshake, args=(callback, self, sock, client_addr), daemon=True,
                             name='tcpros-inbound-%s:%s' % tuple(client_addr[:2])).start()
        except RuntimeError as e:   # no thread can be started now
            _HANDSHAKES.release()
            _close_refused(sock, client_addr, 'no thread for it: %s' % e)
    handle.threaded = True
    return handle


MAX_HANDSHAKES = 64   # inbound connections handled at once (each a thread until its header is read)
_HANDSHAKES = threading.BoundedSemaphore(MAX_HANDSHAKES)
_REFUSED = {'count': 0, 'told': 0.0}


def _close_refused(sock, client_addr, why):
    try:
        sock.close()
    except (OSError, AttributeError):
        pass
    _REFUSED['count'] += 1
    if time.monotonic() - _REFUSED['told'] >= 10.0:   # at most once every 10 s: a flood is one line
        _REFUSED['told'] = time.monotonic()
        import rospy
        rospy.logwarn('inbound connection from %s closed unanswered: %s (%d so far)' % (client_addr, why,
                                                                                     _REFUSED['count']))


def _handshake(callback, server, sock, client_addr):
    try:
        _with_hooks(callback, server, sock, client_addr)
    finally:
        _HANDSHAKES.release()


def _with_hooks(callback, server, sock, client_addr):
    for hook in list(INBOUND_HOOKS):
        sock = hook(server, sock, client_addr)
        if sock is None:
            return
    callback(server, sock, client_addr)


def unacknowledged_limit(seconds=USER_TIMEOUT):
    """Abort an inbound connection (a subscriber's, a service client's) whose data this node sent stays
    unacknowledged for ``seconds`` (TCP_USER_TIMEOUT; 0: the kernel's default). A host that lost power
    sends no FIN or RST: a synchronous rospy publisher's write to a subscriber on it blocks once about
    20 small messages fill the socket's buffers, and then waits for the kernel to give the connection
    up, about 15 minutes of retransmissions, holding whatever lock the publishing thread holds (an
    After's checkpoints to a dead backup host, alarms to a dead site's Recovery). With the limit it
    waits that long at most, then rospy drops the dead subscriber and goes on. A frozen subscriber
    whose receive buffer filled is aborted too once frozen that long (rospy then connects again, or
    the subscription keeper does), so the limit stays well above the freezes of the fault model (3 s).
    Applies to the connections accepted after the call: call it before init_node (run_node does).
    Raises ConfigError for a limit the kernel cannot take (below 0, or 2**31 ms and beyond)."""
    if not 0 <= seconds < MAX_USER_TIMEOUT:
        from ..errors import ConfigError
        raise ConfigError('AFT_TCP_USER_TIMEOUT=%r: expected seconds from 0 (the kernel\'s own) to below %d'
                          % (seconds, MAX_USER_TIMEOUT))
    _LIMIT['ms'] = int(round(seconds * 1000))
    return seconds


def bound_handshakes(timeout=HANDSHAKE_TIMEOUT):
    """Bound rospy's handshake reads and hand each inbound connection to its own thread
    (idempotent; before init_node). Returns the timeout in force."""
    import rospy.impl.tcpros_base as base
    current = getattr(base.read_ros_handshake_header, 'bounded_to', None)
    if current is None:
        base.read_ros_handshake_header = bounded(base.read_ros_handshake_header, timeout)
        current = timeout
    if not getattr(base.TCPROSServer._tcp_server_callback, 'threaded', False):
        base.TCPROSServer._tcp_server_callback = threaded(base.TCPROSServer._tcp_server_callback)
    return current
