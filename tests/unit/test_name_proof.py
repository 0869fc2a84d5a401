"""Under TLS a node whose name another registration took at the ROS master gives way only to a node
that proves the name (aft_ftm.ros.tls_transport.name_proof): the master's XML-RPC API is open, so
anyone can register any name and have the master ask the real node to shut down. No ROS master here:
the new registration is a plain XML-RPC server answering requestTopic, in front of a TLS server
that answers a TCPROS subscription header, each made as the case needs."""
import io
import socket
import ssl
import threading
from xmlrpc.server import SimpleXMLRPCServer

import pytest
from rosgraph.network import encode_ros_handshake_header, read_ros_handshake_header

from aft_ftm import tls
from aft_ftm.ros import tls_transport

POLICY = {'plaintext': ['/rosout'],
          'parties': {'slave': {'nodes': ['/slave/*'], 'publish': ['/rosout']},
                      'client2': {'nodes': ['/client2*']},
                      'anyname': {'publish': ['/rosout']}}}   # certified, not bound to names


@pytest.fixture(scope='module')
def authority(tmp_path_factory):
    directory = str(tmp_path_factory.mktemp('tls'))
    tls.make_authority(directory)
    for party in ('slave', 'client2', 'anyname', 'checker'):
        tls.issue(directory, party)
    return directory


class Impostor(object):
    """A TCPROS endpoint (TLS with ``party``'s certificate, or in clear) answering a subscription as
    ``callerid``, behind an XML-RPC server whose requestTopic names it (or ``protocol``)."""

    def __init__(self, directory, party, callerid, protocol=None, answer=None):
        self.answer = answer or (lambda sock, header: {'callerid': self.callerid, 'type': '*', 'md5sum': '*'})
        self.listener = socket.socket()
        self.listener.bind(('127.0.0.1', 0))
        self.listener.listen(4)
        self.context = tls.contexts(directory, party)[0] if party else None
        self.callerid = callerid
        threading.Thread(target=self._serve, daemon=True).start()
        port = self.listener.getsockname()[1]
        self.xmlrpc = SimpleXMLRPCServer(('127.0.0.1', 0), logRequests=False, allow_none=True)
        answer = protocol if protocol is not None else ['TCPROS', '127.0.0.1', port]
        self.xmlrpc.register_function(lambda caller, topic, protocols: [1, 'ready', answer], 'requestTopic')
        threading.Thread(target=self.xmlrpc.serve_forever, daemon=True).start()
        self.uri = 'http://127.0.0.1:%d/' % self.xmlrpc.server_address[1]

    def _serve(self):
        while True:
            try:
                sock, _ = self.listener.accept()
            except OSError:
                return
            try:
                sock.settimeout(5.0)
                if self.context is not None:
                    sock = self.context.wrap_socket(sock, server_side=True)
                header = read_ros_handshake_header(sock, io.BytesIO(), 65536)
                sock.sendall(encode_ros_handshake_header(self.answer(sock, header)))
            except (OSError, ssl.SSLError, Exception):
                pass
            finally:
                sock.close()

    def close(self):
        self.listener.close()
        self.xmlrpc.shutdown()
        self.xmlrpc.server_close()


@pytest.fixture
def node(authority, monkeypatch):
    """This process as node /slave/protocol of party slave, under the policy."""
    server, client = tls.contexts(authority, 'slave')
    state = {'client': client, 'server': server, 'permissions': tls.Permissions.parse(POLICY),
             'revocations': tls.Revocations.of_directory(authority), 'party': 'slave'}
    monkeypatch.setattr(tls_transport, '_STATE', state)
    return authority


@pytest.mark.parametrize('party,callerid,proven,words', [
    ('slave', '/slave/protocol', True, None),                      # a new incarnation of the node
    ('slave', '/slave/after', False, "answers as '/slave/after'"),  # another node of the same party
    ('client2', '/slave/protocol', False, '(party client2) may not run a node named /slave/protocol'),
    ('anyname', '/slave/protocol', False, '(party anyname) may not run'),   # not bound to names: no proof
    (None, '/slave/protocol', False, 'no TLS handshake'),           # no certificate at all
])
def test_only_a_certified_node_bound_to_the_name_and_answering_as_it_proves_it(node, party, callerid, proven, words):
    impostor = Impostor(node, party, callerid)
    try:
        why = tls_transport.name_proof(impostor.uri, '/slave/protocol', timeout=1.0)
    finally:
        impostor.close()
    assert (why is None) == proven, why
    if words:
        assert words in why


@pytest.mark.parametrize('protocol,words', [
    ([], 'offers no TCPROS connection'),
    (['UDPROS', '127.0.0.1', 1], 'offers no TCPROS connection'),
    (['TCPROS', '127.0.0.1', 1], 'cannot be reached'),
])
def test_a_registration_without_a_usable_tcpros_server_proves_nothing(node, protocol, words):
    impostor = Impostor(node, 'slave', '/slave/protocol', protocol=protocol)
    try:
        why = tls_transport.name_proof(impostor.uri, '/slave/protocol', timeout=1.0)
    finally:
        impostor.close()
    assert why is not None and words in why, why


def test_an_xmlrpc_address_nobody_serves_proves_nothing(node):
    probe = socket.socket()
    probe.bind(('127.0.0.1', 0))
    port = probe.getsockname()[1]
    probe.close()
    why = tls_transport.name_proof('http://127.0.0.1:%d/' % port, '/slave/protocol', timeout=1.0)
    assert why is not None and 'does not answer' in why, why


def test_a_revoked_certificate_proves_nothing(node, monkeypatch):
    impostor = Impostor(node, 'slave', '/slave/protocol')
    monkeypatch.setattr(tls_transport, '_revoked', lambda certificate: 'certificate 1 of party slave is revoked')
    try:
        why = tls_transport.name_proof(impostor.uri, '/slave/protocol', timeout=1.0)
    finally:
        impostor.close()
    assert why == 'certificate 1 of party slave is revoked'


def test_a_registration_naming_this_nodes_own_tcpros_server_proves_nothing(node, monkeypatch):
    """An impostor's requestTopic may name the real node's own TCPROS server, which would answer as it."""
    impostor = Impostor(node, 'slave', '/slave/protocol')
    port = impostor.listener.getsockname()[1]
    monkeypatch.setattr(tls_transport, '_own_tcpros_address', lambda: ('localhost', port))
    try:
        why = tls_transport.name_proof(impostor.uri, '/slave/protocol', timeout=1.0)
    finally:
        impostor.close()
    assert why is not None and "this node's own TCPROS address" in why, why


def test_a_proof_that_comes_back_to_the_node_that_made_it_proves_nothing(node):
    """A relay (or another address of this host) can lead the proof back to this very node, which would
    answer as itself with its own certificate: the proof's subscription carries a nonce, and a node
    refuses a subscription carrying one of its own proofs under way."""
    handle = tls_transport._guard(lambda sock, addr, header: None, 'subscribe', 'topic')
    tls_transport._PROOFS.add('n0nce')
    try:
        refused = handle(None, ('127.0.0.1', 1), {'topic': '/rosout', 'callerid': '/slave/protocol',
                                                  tls_transport.PROOF_FIELD: 'n0nce'})
    finally:
        tls_transport._PROOFS.discard('n0nce')
    assert refused and 'reached the node that made it' in refused

    def own_guard(sock, header):   # this node's own server behind the impostor's address: its _guard answers
        why = handle(sock, ('127.0.0.1', 1), header)
        return {'error': why} if why else {'callerid': '/slave/protocol', 'type': '*', 'md5sum': '*'}
    back = Impostor(node, 'slave', '/slave/protocol', answer=own_guard)
    try:
        why = tls_transport.name_proof(back.uri, '/slave/protocol', timeout=2.0)
    finally:
        back.close()
    assert why is not None and 'reached the node that made it' in why, why
    assert not tls_transport._PROOFS   # the nonce is dropped once the proof ends


def test_a_proof_is_bounded_in_all_and_a_node_that_no_name_binds_gives_way(node, monkeypatch):
    """A registration whose API answers a byte at a time must not hold the node: the whole proof is
    awaited NAME_PROOF_TIMEOUT at most. And where the policy binds this node's party to no names,
    nobody can prove one: the node gives way, as plain rospy does (two such nodes would otherwise take
    the name from each other for ever)."""
    import time
    slow = SimpleXMLRPCServer(('127.0.0.1', 0), logRequests=False, allow_none=True)
    slow.register_function(lambda caller, topic, protocols: time.sleep(1.2) or [1, "late", []], 'requestTopic')
    threading.Thread(target=slow.serve_forever, daemon=True).start()
    monkeypatch.setattr(tls_transport, 'NAME_PROOF_TIMEOUT', 0.5)
    try:
        started = time.monotonic()
        why = tls_transport._proof_within('http://127.0.0.1:%d/' % slow.server_address[1], '/slave/protocol')
        assert why is not None and time.monotonic() - started < 1.5, why
    finally:
        slow.shutdown()
        slow.server_close()
    monkeypatch.setitem(tls_transport._STATE, 'party', 'anyname')   # bound to no names
    import rospy
    monkeypatch.setattr(rospy, 'get_name', lambda: '/slave/protocol')
    assert tls_transport.contest_name('http://127.0.0.1:1/') is None
