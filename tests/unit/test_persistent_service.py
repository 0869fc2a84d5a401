"""A service call made in the caller's thread with a deadline (PersistentService.call_within, through
Deadline): the answer, the server's error answer, a late answer, a late answer in parts, a server
that reads nothing, a connection that breaks. The server is a fake TCPROS service on a socket pair
(the handshake done): it reads each request and answers when and how the test says. No ROS master."""
import concurrent.futures
import re
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


# -- random schedules: several callers, every kind of answer, drawn from a printed seed -----------------

BEHAVIOURS = ('now', 'now', 'delay', 'parts', 'error', 'close', 'garbage')


class Reconnecting(PersistentService):
    """A PersistentService whose connect() opens a new socket pair served by a FakeServer thread (as a
    reconnection to the server would)."""

    def __init__(self, serve_connection):
        super(Reconnecting, self).__init__('/site/server/set_state', SetState)
        self.serve_connection = serve_connection
        self.sockets = []

    def connect(self):
        if self.transport is not None:
            return
        client_sock, server_sock = socket.socketpair()
        self.sockets += [client_sock, server_sock]
        transport = TCPROSTransport(TCPROSServiceClient(self.resolved_name, SetState), self.resolved_name)
        transport.set_socket(client_sock, 'fake')
        transport.header = {}
        threading.Thread(target=self.serve_connection, args=(server_sock,), daemon=True).start()
        self.transport = transport


class Schedule(object):
    """The server's side of a random schedule: each request (its state is its id) answered as its plan says.
    ``received``: the ids in the order the server read them; ``overlaps``: requests read while an earlier
    one could still take effect (with an exclusive Deadline there must be none)."""

    def __init__(self, plans):
        self.plans = plans
        self.lock = threading.Lock()
        self.received, self.outstanding, self.overlaps = [], set(), []

    def serve_connection(self, sock):
        server = FakeServer(sock)
        try:
            while True:
                try:
                    request = server.read_request(timeout=20.0)
                except (EOFError, OSError):
                    return
                i = int(bytes(request.state))
                with self.lock:
                    if self.outstanding:
                        self.overlaps.append((i, sorted(self.outstanding)))
                    self.received.append(i)
                    self.outstanding.add(i)
                if not self._act(server, i):
                    return
        finally:
            sock.close()

    def _act(self, server, i):
        """Carry out request i's plan; False once the connection is closed. Request i stops being able to
        take effect before its last byte is written (a set_state applies before it answers)."""
        behaviour, delay, split = self.plans[i][1:]
        done = lambda: self._finish(i)   # noqa: E731
        if behaviour in ('delay', 'close', 'garbage'):
            time.sleep(delay)
        if behaviour in ('now', 'delay'):
            done()
            server.answer(message='ok %d' % i)
        elif behaviour == 'parts':
            whole = server.answer_bytes(message='ok %d ' % i + 'x' * 3000)
            server.sock.sendall(whole[:split])
            time.sleep(delay)
            done()
            server.sock.sendall(whole[split:])
        elif behaviour == 'error':
            done()
            server.error('refused %d' % i)
        elif behaviour == 'close':
            done()
            server.sock.shutdown(socket.SHUT_RDWR)
            return False
        else:   # garbage: a string length past the end of the answer
            done()
            server.sock.sendall(b'\x01' + struct.pack('<I', 3) + b'\xff\xff\xff')
            return False
        return True

    def _finish(self, i):
        with self.lock:
            self.outstanding.discard(i)


def _draw_plans(rng, callers, calls):
    """{id: (caller, behaviour, delay, split)}; ids are numbered per caller."""
    plans = {}
    for c in range(callers):
        for k in range(calls):
            plans[c * 1000 + k] = (c, rng.choice(BEHAVIOURS), rng.uniform(0.0, 0.25), rng.randint(1, 400))
    return plans


def _expected(plan, outcome):
    """Whether a call's outcome (kind, text) fits its plan: its own answer, its own error, or the transport
    error of a connection closed or garbled under it."""
    behaviour = plan[1]
    kind, text = outcome
    if kind == 'answer':
        return behaviour in ('now', 'delay', 'parts') and text.split(' ')[:2] == ['ok', str(plan[-1])]
    if kind == 'error':
        return behaviour == 'error' and re.search(r'refused %d\b' % plan[-1], text) is not None
    if kind == 'transport':
        return behaviour in ('close', 'garbage')
    return False


def _outcome(e):
    text = str(e)
    if isinstance(e, rospy.ServiceException) and 'responded with an error' in text:
        return 'error', text
    if isinstance(e, rospy.ServiceException) and 'transport error' in text:
        return 'transport', text
    return 'other', '%s: %s' % (type(e).__name__, text)


@pytest.mark.parametrize('callers,exclusive', [(1, True), (3, True), (3, False)])
def test_random_schedules_every_caller_gets_its_own_answer_or_a_named_timeout(callers, exclusive):
    """Callers in several threads share one Deadline and one connection; the server answers at once,
    late, in parts, with an error, closes the connection or garbles the answer, at random. Every call
    ends within its timeout (plus slack) with its own answer, its own error, a transport error where the
    server broke the connection, or a CallTimeout: its future then gets the call's own outcome, or says
    it was never sent (and the server never saw it). With an exclusive Deadline the server never reads a
    request while an earlier one may still take effect."""
    import os
    import random
    base = int(os.environ.get('AFT_SEED', int(time.time()) % 100000))
    for seed in range(base, base + 3):
        rng = random.Random(seed)
        calls = 12
        plans = _draw_plans(rng, callers, calls)
        timeouts = {i: rng.uniform(0.03, 0.15) for i in plans}
        schedule = Schedule(plans)
        proxy = Reconnecting(schedule.serve_connection)
        proxy.connect()
        deadline = Deadline('state', exclusive=exclusive)
        outcomes, problems = {}, []

        def caller(c):
            for k in range(calls):
                i = c * 1000 + k
                started = time.monotonic()
                try:
                    reply = deadline.call(proxy, timeouts[i], str(i).encode())
                    outcomes[i] = ('answer', reply.message)
                except CallPending as e:
                    outcomes[i] = ('pending', e)
                except CallTimeout as e:
                    outcomes[i] = ('timeout', e.future)
                except Exception as e:   # every other error must be the call's own (checked below)
                    outcomes[i] = _outcome(e)
                took = time.monotonic() - started
                if took > timeouts[i] + 1.0:
                    problems.append('call %d took %.3f s against a timeout of %.3f s' % (i, took, timeouts[i]))
        threads = [threading.Thread(target=caller, args=(c,), daemon=True) for c in range(callers)]
        try:
            for t in threads:
                t.start()
            for t in threads:
                t.join(60.0)
            assert not any(t.is_alive() for t in threads), 'seed %d: a caller did not finish in 60 s' % seed
            for i in sorted(plans):
                kind, value = outcomes[i]
                plan = plans[i] + (i,)
                if kind == 'pending':
                    if i in schedule.received:
                        problems.append('call %d: CallPending, yet the server read it' % i)
                    continue
                if kind == 'timeout':
                    try:
                        result = value.result(10.0)
                        kind, value = 'answer', result.message
                    except CallTimeout:   # not sent: another call kept the connection
                        if i in schedule.received:
                            problems.append('call %d: not sent, yet the server read it' % i)
                        continue
                    except concurrent.futures.TimeoutError:
                        problems.append('call %d: its late outcome never came (plan %s)' % (i, plan[1:4]))
                        continue
                    except Exception as e:
                        kind, value = _outcome(e)
                if not _expected(plan, (kind, value)):
                    problems.append('call %d (plan %s, %.3f s delay): got %s %r' % (i, plan[1], plan[2], kind,
                                                                                   str(value)[:120]))
            if exclusive and schedule.overlaps:
                problems.append('requests read while earlier ones could still take effect: %s' % schedule.overlaps)
            assert not problems, 'seed %d (AFT_SEED=%d replays it): %s' % (seed, seed, problems)
        finally:
            proxy.reset()
            for s in proxy.sockets:
                s.close()
