"""Mutual TLS inside rospy's TCPROS (aft_ftm.tls): installed by run_node before init_node when the
environment names a TLS directory (AFT_TLS_DIR, with AFT_TLS_PARTY and AFT_TLS_POLICY).

- outbound (this node subscribes, or calls a service): the socket rospy has just connected is
  wrapped in TLS before the TCPROS header is written, the peer's certificate names its party, and
  the policy must let that party publish the topic (serve the service); a name the policy lists as
  plaintext is left in clear (ROS tools, the unmodified application's client and server);
- inbound (a subscriber connects to this node's publisher, a client calls its service): the first
  bytes tell a TLS ClientHello from a TCPROS header; TLS is accepted with the peer's certificate
  required, and after the header the policy must let the peer's party subscribe (call) that name;
  a peer in clear only on a plaintext name.
A refused connection is closed (rospy logs it; the peer gets the reason in the TCPROS error header
where there is one) and an alarm ``tls connection_refused`` is raised, at most once per peer and
name every 10 s."""
import socket
import ssl
import threading
import time
import weakref

from .. import tls

HANDSHAKE_TIMEOUT = 5.0
_STATE = {}
_PEERS = weakref.WeakKeyDictionary()   # inbound socket -> its peer's party (None: in clear)
_TOLD = {}
_LOCK = threading.Lock()


def install(directory, party, permissions):
    """Mutual TLS for every TCPROS connection of this process (idempotent)."""
    import rospy.impl.tcpros_base as base
    from . import handshake
    handshake.bound_handshakes()   # the inbound hook runs in the per-connection threads it makes
    server, client = tls.contexts(directory, party)
    _STATE.update(server=server, client=client, permissions=permissions, party=party)
    if not getattr(base.TCPROSTransport.write_header, 'tls', False):
        original = base.TCPROSTransport.write_header

        def write_header(self):
            if self.dest_address is not None and self.socket is not None and \
                    not isinstance(self.socket, ssl.SSLSocket):
                _secure_outbound(self)
            return original(self)
        write_header.tls = True
        base.TCPROSTransport.write_header = write_header
    handshake.INBOUND_HOOKS[:] = [_accept]
    return party


def active():
    return bool(_STATE)


def _secure_outbound(transport):
    from rospy.exceptions import TransportInitError
    fields = transport.protocol.get_header_fields() if transport.protocol is not None else {}
    name, action = (fields['topic'], 'publish') if 'topic' in fields else (fields.get('service', '?'), 'serve')
    permissions = _STATE['permissions']
    if permissions.plaintext(name):
        return
    plain = transport.socket
    timeout = plain.gettimeout()
    plain.settimeout(HANDSHAKE_TIMEOUT)
    try:
        secured = _STATE['client'].wrap_socket(plain)
    except (ssl.SSLError, OSError) as e:
        _refused(transport.dest_address, name, 'TLS with %s:%s failed: %s' % (transport.dest_address + (e,)))
        plain.close()
        transport.socket = None   # not a half-made connection rospy would go on reading
        raise TransportInitError('TLS refused for %s: %s' % (name, e))
    why = permissions.allows(tls.party_of(secured.getpeercert()), action, name)
    if why:
        _refused(transport.dest_address, name, why)
        secured.close()
        transport.socket = None
        raise TransportInitError('refused by the TLS policy: %s' % why)
    secured.settimeout(timeout)
    transport.socket = secured


def _accept(server, sock, client_addr):
    """The inbound hook (aft_ftm.ros.handshake): the socket to hand to rospy, or None (closed)."""
    _guard_handlers(server)
    try:
        sock.settimeout(HANDSHAKE_TIMEOUT)
        first = sock.recv(tls.PEEK, socket.MSG_PEEK | socket.MSG_WAITALL)
        if tls.looks_like_tls(first):
            secured = _STATE['server'].wrap_socket(sock, server_side=True)
            secured.settimeout(None)
            _PEERS[secured] = tls.party_of(secured.getpeercert())
            return secured
        sock.settimeout(None)
        _PEERS[sock] = None
        return sock
    except (ssl.SSLError, OSError) as e:
        _refused(client_addr, '(handshake)', 'TLS handshake failed: %s' % e)
        try:
            sock.close()
        except OSError:
            pass
        return None


def _guard_handlers(server):
    for attribute, action, key in (('topic_connection_handler', 'subscribe', 'topic'),
                                   ('service_connection_handler', 'call', 'service')):
        handler = getattr(server, attribute, None)
        if handler is None or getattr(handler, 'tls_guard', False):
            continue
        setattr(server, attribute, _guard(handler, action, key))


def _guard(handler, action, key):
    def handle(sock, client_addr, header):
        name = header.get(key, '?')
        if header.get('probe') == '1' and action == 'call':
            # rospy.wait_for_service's probe: a bare header, in clear, closed unanswered; it learns only
            # that the service is there, which the master tells anyone
            return handler(sock, client_addr, header)
        why = _STATE['permissions'].allows(_PEERS.get(sock), action, name)
        if why:
            _refused(client_addr, name, why)
            return 'refused by the TLS policy: %s' % why
        return handler(sock, client_addr, header)
    handle.tls_guard = True
    handle.one_subscriber_at_a_time = getattr(handler, 'one_subscriber_at_a_time', False)
    return handle


def _refused(peer, name, why):
    import rospy
    key = (str(peer[0]) if peer else '?', name)
    now = time.monotonic()
    with _LOCK:
        if now - _TOLD.get(key, -1e9) < 10.0:
            return
        if len(_TOLD) > 1000:   # names an attacker chooses: bounded
            _TOLD.clear()
        _TOLD[key] = now
    rospy.logwarn('%s: tls connection_refused: %s from %s: %s', rospy.get_name(), name, key[0], why)
    try:
        from aft_msgs.msg import Alarm
        publisher = _STATE.get('alarms')
        if publisher is None:
            publisher = _STATE['alarms'] = rospy.Publisher('/aft/alarms', Alarm, queue_size=100)
        publisher.publish(Alarm(source=rospy.get_name(), mechanism='tls', kind='connection_refused',
                                detail='%s from %s: %s' % (name, key[0], why), stamp=rospy.Time.now()))
    except Exception:   # before init_node, or shutting down: the log line above stands
        pass
