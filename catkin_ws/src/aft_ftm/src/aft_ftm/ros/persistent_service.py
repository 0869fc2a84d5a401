"""Service calls that need no ROS master once set up.

A rospy ServiceProxy asks the master for the service's address (``lookupService``) every time it
opens a connection, and a persistent one opens its connection at its first call. A failover makes
first calls (a backup's Proceed calls its server for the first time, a promoted After its state
manager): with the master dead those calls fail. :class:`PersistentService` opens its connection
at set-up (:meth:`PersistentService.connect`) and remembers the address the master gave, so that a
reconnection (the connection broke) also works while the master cannot be reached, as long as the
service still runs where it did.

:meth:`PersistentService.call_within` makes a call on the open connection in the caller's own
thread, its answer awaited at most a timeout: a call that may hang costs no hand-over to a worker
thread (two thread switches, about 70 microseconds of each PBR state capture and server call here).
"""
import concurrent.futures
import io
import select
import socket
import ssl
import struct
import threading
import time

import rosgraph
import rospy
from rospy.exceptions import TransportException, TransportInitError
from rospy.impl.tcpros_base import TCPROSTransport, recv_buff
from rospy.msg import args_kwds_to_message, serialize_message


def _transport_error(e):
    """The ServiceException rospy raises for a broken or garbled connection."""
    return rospy.ServiceException('transport error completing service call: %s' % e)


def _whole_answer(b):
    """Whether the buffer holds a whole service answer: its ok byte, its length, and that many bytes."""
    n = b.tell()
    if n < 5:
        return False
    with b.getbuffer() as view:
        return n >= 5 + struct.unpack_from('<I', view, 1)[0]


class LateAnswer(Exception):
    """No answer within the timeout. ``future`` gets the late answer (or the call's error) from a thread
    that goes on with the call."""

    def __init__(self, future):
        super(LateAnswer, self).__init__('no answer within the timeout')
        self.future = future


class Busy(Exception):
    """Another call held the connection for the whole timeout: this one was not sent."""


class NotConnected(Exception):
    """The connection is not open (or is TLS) by the time this call has it: nothing was sent; the call is
    to be made with :meth:`PersistentService.call`, which opens one."""


def _closed_by_peer(sock):
    """Whether the peer closed (or reset) a connection that has nothing to read: a look, no byte taken.
    A TLS socket is not looked at (its records are not the bytes read)."""
    if isinstance(sock, ssl.SSLSocket):
        return False
    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b''
    except (BlockingIOError, InterruptedError):
        return False
    except OSError:
        return True


class PersistentService(rospy.ServiceProxy):
    """A persistent rospy.ServiceProxy that can connect without the master.

    ``connect()`` opens the connection now (the master is asked, once). Later connections ask the
    master too, and use the last address it gave when it cannot be reached (``master_misses`` counts
    them). Calls raise what rospy.ServiceProxy raises.
    """

    def __init__(self, name, service_class):
        super(PersistentService, self).__init__(name, service_class, persistent=True)
        self.master_misses = 0
        # One call at a time on the connection, whichever way it is made (a request written while
        # another call's answer is read would take that answer). A call that hangs keeps it: a caller
        # that gives up on it goes on with fresh().
        self._lock = threading.Lock()

    @property
    def connected(self):
        transport = self.transport
        return transport is not None and transport.socket is not None and not transport.done

    @property
    def can_call_within(self):
        """Whether :meth:`call_within` may be used now: the connection is open, and plain TCP (a TLS
        connection, aft_ftm.ros.tls_transport, buffers what it decrypted where poll does not see it;
        its calls go through a worker thread)."""
        return self.connected and not isinstance(self.transport.socket, ssl.SSLSocket)

    def call(self, *args, **kwds):
        """rospy.ServiceProxy.call; a connection that failed (anything but the service's own error
        answer) is closed, so that the next call opens a new one. A request rospy could not write (a
        broken pipe: its TransportTerminated is no ROSException) is a ServiceException here."""
        with self._lock:
            try:
                self.connect()
                return super(PersistentService, self).call(*args, **kwds)
            except (rospy.ServiceException, rospy.ROSException) as e:
                self._failed(e)
                raise
            except TransportException as e:
                self.reset()
                raise _transport_error(e)

    def call_within(self, timeout, *args, **kwds):
        """The call on the open connection, made in this thread, its answer awaited at most ``timeout``
        seconds (waiting for another call to be done with the connection included); returns or raises
        what :meth:`call` would. Past the timeout raises :class:`LateAnswer`: the connection is handed
        to a thread that finishes sending the request (a stopped server may not read it all yet) and
        reads the late answer into the exception's future; the next call opens a new connection.
        Nothing sent: :class:`Busy` (another call kept the connection for the whole timeout) or
        :class:`NotConnected` (``can_call_within`` is false once the connection is this call's)."""
        deadline = time.monotonic() + timeout
        if not self._lock.acquire(timeout=timeout):
            raise Busy('another call on %s did not return within %.3f s' % (self.resolved_name, timeout))
        try:
            if self.connected and _closed_by_peer(self.transport.socket):
                self.reset()   # its server closed it (restarted): the worker's way opens a new one
            if not self.can_call_within:
                raise NotConnected(self.resolved_name)
            return self._call_within(self.transport, deadline, args, kwds)
        finally:
            self._lock.release()

    def _call_within(self, transport, deadline, args, kwds):
        request = args_kwds_to_message(self.request_class, args, kwds)
        self.seq += 1
        buff = io.BytesIO()
        serialize_message(buff, self.seq, request)
        data = memoryview(buff.getvalue())
        try:
            sent = self._send(transport.socket, data, deadline)
            response = self._receive(transport, deadline) if sent == len(data) else None
        except rospy.ServiceException as e:
            self._failed(e)
            raise
        if response is not None:
            return response
        self.transport = None   # the late answer's now: the next call opens a new connection
        future = concurrent.futures.Future()

        def finish_late():
            try:
                if sent < len(data):
                    transport.socket.sendall(data[sent:])
                future.set_result(self._receive(transport, None))
            except rospy.ServiceException as e:   # the call's own error, as it would have been raised
                future.set_exception(e)
            except Exception as e:
                future.set_exception(_transport_error(e))
            finally:
                transport.close()
        threading.Thread(target=finish_late, name='late-' + self.resolved_name, daemon=True).start()
        raise LateAnswer(future)

    @staticmethod
    def _send(sock, data, deadline):
        """Send what the socket takes of data until deadline; the bytes sent (a server that reads
        nothing fills the buffers: the rest is sent late). ServiceException if the connection fails."""
        poller = select.poll()
        poller.register(sock, select.POLLOUT)
        sent = 0
        sock.setblocking(False)
        try:
            while sent < len(data):
                try:
                    sent += sock.send(data[sent:])
                except (BlockingIOError, InterruptedError):
                    left = deadline - time.monotonic()
                    if left <= 0 or not poller.poll(left * 1e3):
                        break
        except OSError as e:
            raise _transport_error(e)
        finally:
            sock.setblocking(True)
        return sent

    def _receive(self, transport, deadline):
        """The response read off the connection, as rospy reads it (raising the server's error answer as
        ServiceException); None if it is not whole by ``deadline`` (monotonic; None: no limit). rospy's
        reader is given only a whole answer (it would block reading the rest of an error message)."""
        sock, b, protocol, messages = transport.socket, transport.read_buff, transport.protocol, []
        poller = select.poll()
        poller.register(sock, select.POLLIN)
        try:
            while True:
                if _whole_answer(b):
                    protocol.read_messages(b, messages, sock)
                    if messages:
                        break
                if deadline is not None:
                    left = deadline - time.monotonic()
                    if left <= 0 or not poller.poll(left * 1e3):
                        return None
                recv_buff(sock, b, protocol.buff_size)
        except rospy.ServiceException:
            raise   # the server's error answer
        except Exception as e:   # a broken connection, a malformed answer (genpy's DeserializationError)
            raise _transport_error(e)
        if len(messages) > 1:
            raise rospy.ServiceException('service [%s] returned multiple responses: %s'
                                         % (self.resolved_name, len(messages)))
        messages[0]._connection_header = transport.header
        return messages[0]

    def _failed(self, e):
        """After a call that raised e: the connection is closed unless the server answered (its own error)."""
        if 'responded with an error' not in str(e):
            self.reset()

    def reset(self):
        """Close the connection (if open); the next call opens a new one."""
        transport, self.transport = self.transport, None
        if transport is not None:
            transport.close()

    def fresh(self):
        """A new PersistentService to the same service that knows its last address (to leave this one
        to a call that may never return)."""
        other = PersistentService(self.resolved_name, self.service_class)
        other.uri = self.uri
        return other

    def connect(self):
        """Open the persistent connection if it is not open, or if its server closed it (a server that
        restarted: a request written there would be lost, its failure telling nothing of whether it
        ran); raises rospy.ServiceException."""
        if self.transport is not None and self.transport.socket is not None \
                and _closed_by_peer(self.transport.socket):
            self.reset()
        if self.transport is not None:
            return
        uri = self._get_service_uri(None)
        host, port = rospy.core.parse_rosrpc_uri(uri)
        transport = TCPROSTransport(self.protocol, self.resolved_name)
        transport.buff_size = self.buff_size
        try:
            transport.connect(host, port, uri)
        except TransportInitError as e:
            raise rospy.ServiceException('unable to connect to service %s: %s' % (self.resolved_name, e))
        self.transport = transport

    def _get_service_uri(self, request):
        """The service's address from the master; the last one it gave if it cannot be reached."""
        try:
            uri = rosgraph.Master(rospy.get_name()).lookupService(self.resolved_name)
        except (socket.error, OSError) as e:   # the master is unreachable
            if self.uri is None:
                raise rospy.ServiceException('service %s: the master cannot be reached to find it (%s)'
                                             % (self.resolved_name, e))
            self.master_misses += 1
            return self.uri
        except rosgraph.MasterError as e:
            raise rospy.ServiceException('service %s unavailable: %s' % (self.resolved_name, e))
        self.uri = uri
        return uri


def open_service(name, service_class, timeout):
    """Wait for the service (asks the master), then open a PersistentService to it. Raises
    rospy.ROSException (not available within timeout) or rospy.ServiceException."""
    rospy.wait_for_service(name, timeout)
    proxy = PersistentService(name, service_class)
    proxy.connect()
    return proxy
