"""A service call made in the caller's thread with a deadline (PersistentService.call_within, through
Deadline): the answer, the server's error answer, a late answer, a late answer in parts, a server
that reads nothing, a connection that breaks. The server is a fake TCPROS service on a socket pair
(the handshake done): it reads each request and answers when and how the test says. No ROS master."""
import socket
import struct
import threading
import time

import pytest
import rospy
from aft_msgs.srv import SetState, SetStateResponse
from rospy.impl.tcpros_base import TCPROSTransport
from rospy.impl.tcpros_service import TCPROSServiceClient

from aft_ftm.ros.deadline import CallPending, CallTimeout, Deadline
from aft_ftm.ros.persistent_service import PersistentService


class FakeServer(object):
    """The server's end of the connection: requests read whole, answers written as told."""

    def __init__(self, sock):
        self.sock = sock
        self.requests = []

    def read_request(self, timeout=5.0):
        self.sock.settimeout(timeout)
        size = struct.unpack('<I', self._read(4))[0]
        request = SetState._request_class()
        request.deserialize(self._read(size))
        self.requests.append(request)
        return request

    def _read(self, n):
        data = b''
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise EOFError('the client closed the connection')
            data += chunk
        return data

    def answer_bytes(self, success=True, message=''):
        body = _serialize(SetStateResponse(success=success, message=message))
        return b'\x01' + struct.pack('<I', len(body)) + body

    def answer(self, **kwargs):
        self.sock.sendall(self.answer_bytes(**kwargs))

    def error(self, text):
        data = text.encode()
        self.sock.sendall(b'\x00' + struct.pack('<I', len(data)) + data)


def _serialize(msg):
    import io
    buff = io.BytesIO()
    msg.serialize(buff)
    return buff.getvalue()


@pytest.fixture
def pair():
    client_sock, server_sock = socket.socketpair()
    proxy = PersistentService('/site/server/set_state', SetState)
    transport = TCPROSTransport(TCPROSServiceClient(proxy.resolved_name, SetState), proxy.resolved_name)
    transport.set_socket(client_sock, 'fake')
    transport.header = {}
    proxy.transport = transport
    server = FakeServer(server_sock)
    yield proxy, server
    for s in (client_sock, server_sock):
        s.close()


def serve(server, before=0.0, **answer):
    def run():
        server.read_request()
        time.sleep(before)
        server.answer(**answer)
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_an_answer_within_the_deadline_is_returned_and_the_connection_kept(pair):
    proxy, server = pair
    deadline = Deadline('state', exclusive=True)
    for i in range(3):
        serve(server, message='applied %d' % i)
        reply = deadline.call(proxy, 2.0, b'S%d' % i)
        assert (reply.success, reply.message) == (True, 'applied %d' % i)
    assert [bytes(r.state) for r in server.requests] == [b'S0', b'S1', b'S2']
    assert proxy.connected
    assert deadline._executor is None, 'the calls went through a worker thread'


def test_the_servers_error_answer_is_raised_as_rospy_raises_it_and_the_connection_kept(pair):
    proxy, server = pair

    def run():
        server.read_request()
        server.error('the state is corrupt')
    threading.Thread(target=run, daemon=True).start()
    with pytest.raises(rospy.ServiceException, match='responded with an error: .*the state is corrupt'):
        Deadline('state').call(proxy, 2.0, b'bad')
    assert proxy.connected
    serve(server)
    assert Deadline('state').call(proxy, 2.0, b'good').success


def test_a_late_answer_lands_in_the_future_and_an_exclusive_deadline_waits_for_it(pair):
    proxy, server = pair
    deadline = Deadline('state', exclusive=True)
    release = threading.Event()

    def run():
        server.read_request()
        release.wait(5.0)
        server.answer(message='late')
    threading.Thread(target=run, daemon=True).start()
    started = time.monotonic()
    with pytest.raises(CallTimeout) as late:
        deadline.call(proxy, 0.1, b'S1')
    assert 0.09 <= time.monotonic() - started < 1.0
    assert not proxy.connected, 'the late answer owns the old connection: the next call opens another'
    with pytest.raises(CallPending):
        deadline.call(proxy, 1.0, b'S2')
    release.set()
    assert late.value.future.result(5.0).message == 'late'
    assert [bytes(r.state) for r in server.requests] == [b'S1']


def test_an_answer_cut_by_the_deadline_is_read_whole_by_the_late_reader(pair):
    proxy, server = pair
    whole = server.answer_bytes(message='x' * 5000)
    release = threading.Event()

    def run():
        server.read_request()
        server.sock.sendall(whole[:7])      # the ok byte, the length and a little of the body
        release.wait(5.0)
        server.sock.sendall(whole[7:])
    threading.Thread(target=run, daemon=True).start()
    with pytest.raises(CallTimeout) as late:
        Deadline('state').call(proxy, 0.1, b'S1')
    release.set()
    assert late.value.future.result(5.0).message == 'x' * 5000


def test_a_request_a_stopped_server_does_not_read_is_sent_late_and_may_still_land(pair):
    """A request larger than the socket buffers, to a server that reads nothing yet: the send is bounded
    by the deadline, the rest goes late (as a worker thread would have sent it), and an exclusive
    deadline makes no other call until the server has read it and answered."""
    proxy, server = pair
    deadline = Deadline('state', exclusive=True)
    big = b'\x07' * (16 * 1024 * 1024)   # far more than the socket buffers hold
    resume = threading.Event()

    def run():
        resume.wait(10.0)
        request = server.read_request(timeout=10.0)
        server.answer(message='%d bytes' % len(request.state))
    threading.Thread(target=run, daemon=True).start()
    started = time.monotonic()
    with pytest.raises(CallTimeout) as late:
        deadline.call(proxy, 0.2, big)
    assert time.monotonic() - started < 3.0
    assert not late.value.future.done() and not proxy.connected
    with pytest.raises(CallPending):
        deadline.call(proxy, 1.0, b'S2')
    resume.set()
    assert late.value.future.result(10.0).message == '%d bytes' % len(big)
    assert bytes(server.requests[0].state) == big


def test_a_malformed_answer_is_a_transport_error_and_the_connection_is_not_used_again(pair):
    proxy, server = pair

    def run():
        server.read_request()
        server.sock.sendall(b'\x01' + struct.pack('<I', 3) + b'\xff\xff\xff')   # a string length past the end
    threading.Thread(target=run, daemon=True).start()
    with pytest.raises(rospy.ServiceException, match='transport error'):
        Deadline('state').call(proxy, 2.0, b'S1')
    assert not proxy.connected


def test_an_error_answer_cut_by_the_deadline_does_not_block_and_lands_in_the_future(pair):
    proxy, server = pair
    text = b'the state is refused ' * 50
    whole = b'\x00' + struct.pack('<I', len(text)) + text
    release = threading.Event()

    def run():
        server.read_request()
        server.sock.sendall(whole[:9])   # rospy would block reading the rest of the error message
        release.wait(5.0)
        server.sock.sendall(whole[9:])
    threading.Thread(target=run, daemon=True).start()
    started = time.monotonic()
    with pytest.raises(CallTimeout) as late:
        Deadline('state').call(proxy, 0.1, b'S1')
    assert time.monotonic() - started < 1.0
    release.set()
    with pytest.raises(rospy.ServiceException, match='responded with an error'):
        late.value.future.result(5.0)


def test_a_connection_the_server_closes_is_a_service_error_and_is_closed_here(pair):
    proxy, server = pair

    def run():
        server.read_request()
        server.sock.shutdown(socket.SHUT_RDWR)
    threading.Thread(target=run, daemon=True).start()
    with pytest.raises(rospy.ServiceException, match='transport error'):
        Deadline('state').call(proxy, 2.0, b'S1')
    assert not proxy.connected


def test_a_tls_connection_is_called_through_the_worker_thread(pair):
    """TLS (aft_ftm.ros.tls_transport) keeps decrypted bytes where poll does not see them: such a
    connection is never called in the caller's thread."""
    import ssl
    proxy, _ = pair
    assert proxy.can_call_within
    plain = socket.socket()
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    tls = context.wrap_socket(plain, do_handshake_on_connect=False)
    try:
        proxy.transport.socket = tls
        assert proxy.connected and not proxy.can_call_within
        deadline = Deadline('state')
        # The unconnected socket fails, on the worker; rospy's broken pipe (TransportTerminated, no
        # ROSException: it escaped every caller) is a service error, and the connection is closed.
        with pytest.raises(rospy.ServiceException, match='transport error'):
            deadline.call(proxy, 2.0, b'S1')
        assert deadline._executor is not None and not proxy.connected
    finally:
        tls.close()
