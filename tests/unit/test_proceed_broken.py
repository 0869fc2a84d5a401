"""Proceed outside a replica when its connection to the server breaks: a request that was written is
never called again nor told "not executed" (the server may have applied it); one never written is
sent once the server is back. No ROS master: ProceedNode._call on a stand-in node."""
import types

import pytest

from aft_examples.history import classify_error
from aft_ftm.recovery import OnHang

bpa = pytest.importorskip('aft_ftm.ros.bpa_nodes')
rospy = pytest.importorskip('rospy')
from aft_ftm.ros.deadline import Deadline  # noqa: E402

RECEIVE = "transport error completing service call: unable to receive data from sender, check sender's logs"
CONNECT = 'unable to connect to service: [Errno 111] Connection refused'


class Server(object):
    """Applies each request it receives; the first call fails with ``first_error`` (after applying
    it unless the error says the request was never written)."""

    def __init__(self, first_error):
        self.first_error, self.applied = first_error, []

    def __call__(self, request):
        error, self.first_error = self.first_error, None
        if error is None or not bpa.unsent(error):
            self.applied.append(request)
        if error is not None:
            raise rospy.ServiceException(error)
        return 'ok'

    def fresh(self):
        return self


@pytest.fixture
def node(monkeypatch):
    alarms = []
    monkeypatch.setattr(bpa, 'alarm', lambda ports, mechanism, kind, detail, request=None: alarms.append(kind))
    monkeypatch.setattr(rospy, 'wait_for_service', lambda name, timeout=None: None)   # the server is back

    def make(server):
        n = types.SimpleNamespace(site='', server_name='/server', server_timeout=5.0, calling_since=None, ports=None,
                                  _deadline=Deadline('server-call'), _proxies={'t/T': server}, alarms=alarms,
                                  hang=types.SimpleNamespace(on_hang=lambda: OnHang.WAIT, why_wait=lambda: ''))
        n._proxy = lambda type_name: n._proxies[type_name]
        return n
    return make


def test_a_request_written_before_the_connection_broke_is_an_unknown_outcome_not_a_second_call(node):
    """Review, stop 38: it was called again once the server was back (applied twice), or answered
    "not executed" (false); the documented server_unavailable alarm was never raised."""
    server = Server(RECEIVE)
    n = node(server)
    with pytest.raises(rospy.ServiceException) as raised:
        bpa.ProceedNode._call(n, types.SimpleNamespace(origin='/proxy', id=42, service_type='t/T'), 'move')
    assert server.applied == ['move']   # once
    assert classify_error('service [/account] responded with an error: %s' % raised.value) == 'indeterminate'
    assert n.alarms == ['server_unavailable']


def test_a_request_never_written_is_sent_once_the_server_is_back(node):
    server = Server(CONNECT)
    n = node(server)
    assert bpa.ProceedNode._call(n, types.SimpleNamespace(origin='/proxy', id=43, service_type='t/T'), 'move') == 'ok'
    assert server.applied == ['move'] and n.alarms == []


@pytest.mark.parametrize('text', [
    'unable to connect to service: [Errno 111] Connection refused',
    'service /server unavailable: no provider',
    'service /server: the master cannot be reached to find it (Connection refused)',
])
def test_a_call_that_never_left_is_told_not_executed_after_a_wait_never_unknown(text):
    """Review of stop 38: these said "outcome unknown" for calls that never reached a server."""
    assert bpa.unsent(text)
    assert not bpa.unsent(RECEIVE)


def test_a_persistent_connection_its_server_closed_is_opened_again_before_a_request_is_written():
    """A server restarted between two calls closed the old connection: a request written there was
    lost, and its failure ("unable to receive data") told nothing of whether it ran."""
    import socket
    from aft_ftm.ros.persistent_service import _closed_by_peer
    listener = socket.socket()
    listener.bind(('127.0.0.1', 0))
    listener.listen(1)
    client = socket.create_connection(listener.getsockname())
    server, _ = listener.accept()
    try:
        assert not _closed_by_peer(client)        # open, nothing to read
        server.sendall(b'x')
        assert not _closed_by_peer(client)        # something to read: open (nothing taken)
        assert client.recv(1) == b'x'
        server.close()
        for _ in range(100):                      # bounded: the FIN arrives at once on the loopback
            if _closed_by_peer(client):
                break
            import time
            time.sleep(0.01)
        assert _closed_by_peer(client)
    finally:
        client.close()
        listener.close()


def test_a_request_of_another_type_than_the_server_s_is_answered_not_executed_never_a_fail_stop(node):
    """Review of session 36: a request naming another loadable type (std_srvs/Empty decodes from any
    payload) made Proceed open a connection the server refused, read as the server gone: the site
    fail-stopped, then the backup with the same request. It is answered "not executed" instead."""
    import threading
    from aft_msgs.msg import Reply, Request
    from aft_msgs.srv import Account
    server = Server(None)
    n = node(server)
    n.site, n.failed, n._lock = 'master', None, threading.Lock()
    n.server_type = ('aft_msgs/Account', Account._md5sum)
    n._call = lambda request, app_request: bpa.ProceedNode._call(n, request, app_request)
    stray = Request(id=9, origin='/proxy', client='c', attempt=1, service_type='std_srvs/Empty', payload=b'\x01\x02')
    reply = bpa.ProceedNode.handle(n, stray)
    assert reply.status == Reply.ERROR and reply.error.startswith('not executed: the request is a std_srvs/Empty')
    assert 'aft_msgs/Account' in reply.error and n.alarms == ['wrong_type']
    assert server.applied == [] and not n.failed
