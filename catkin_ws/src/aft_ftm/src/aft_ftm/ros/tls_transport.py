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
name every 10 s.

Revocation and expiry on a running graph: the node follows the CA's revocation list in its TLS
directory (``ca.tls.crl``, checked every CRL_PERIOD); a certificate it revokes is refused from then
on, and every live connection of it is cut (alarm ``tls certificate_revoked``); a connection whose
peer certificate has expired is cut too (``tls certificate_expired``) and refused at every later
handshake (no session is resumed). A list not signed by the CA, or older than the one held, is
refused (``tls bad_crl``) and changes nothing; the highest list number taken is kept in the
directory (``ca.tls.crl.held``), so a restarted node refuses an older or missing list; a list past
its next update raises ``tls stale_crl``; this node's own certificate revoked raises
``tls own_certificate_revoked``; its own certificate within a week of its end (or in the last fifth
of its life, if shorter) raises ``tls own_certificate_ending``, and past it ``tls
own_certificate_expired`` (logged; published only while a connection is open: every peer refuses
the node then), each once per certificate (tls.ending_notice).

A rotation without a restart: the same watcher sees the party's key and certificate change in its
directory (``tls_keygen DIR PARTY`` again, or the new pair copied there) and, once the pair loads,
makes every new connection with it; live connections keep the old certificate until they are cut
(``tls_keygen DIR --revoke-replaced PARTY``: the peers cut them, and each reconnects with the new
one: the node sees its old certificate revoked, and its subscription keeper makes the cut
subscriptions again at once, HURRY_WINDOW, where it waited its grace otherwise) or it ends. A certificate the node's CA did not sign for its party, not valid now, or revoked
is refused at once (``tls rotation_refused``), the old one kept. A pair that does not load (a key
and a certificate of different issues: one copied, the other not yet) is tried again each round,
the old one kept, and after ROTATION_GRACE said (``tls rotation_failed``)."""
import collections
import os
import socket
import ssl
import threading
import time
import weakref

from .. import tls
from ..errors import ConfigError

HANDSHAKE_TIMEOUT = 5.0
NAME_PROOF_TIMEOUT = 2.0   # s in all to check a node that took this node's name at the master
PROOF_SLOTS = 4            # such checks at once, at most
PROOF_FIELD = 'aft_name_proof'   # the nonce of a name proof, in its subscription header
_PROOF_SLOTS = threading.BoundedSemaphore(PROOF_SLOTS)
_PROOFS = set()            # the nonces of this process's proofs under way
_REGISTERING = {'running': False, 'again': False}
CRL_PERIOD = 0.25   # s between two looks at the revocation list and the live connections' expiry
ROTATION_GRACE = 5.0   # s a changed key and certificate may fail to load (half copied) before it is said
HURRY_WINDOW = 5.0     # s the subscription keeper reconnects at once after a cut on purpose (a rotation)
_STATE = {}
_PEERS = weakref.WeakKeyDictionary()   # inbound socket -> its peer's party (None: in clear)
_LIVE = weakref.WeakKeyDictionary()    # TLS socket -> (peer party, certificate serial, not-after s)
_TOLD = {}
_LOCK = threading.Lock()
_PENDING = collections.deque(maxlen=200)   # alarms not yet published (the watcher publishes them)
PUBLISHER_SETTLE = 0.5   # s a new publisher is given to be heard before the first alarm goes out


def installed():
    """Whether mutual TLS is installed in this process."""
    return bool(_STATE)


def install(directory, party, permissions):
    """Mutual TLS for every TCPROS connection of this process (idempotent)."""
    import rospy.impl.tcpros_base as base
    from . import handshake
    handshake.bound_handshakes()   # the inbound hook runs in the per-connection threads it makes
    files = _files_stat(directory, party)   # before the load: a rotation meanwhile is seen by the watcher
    server, client = tls.contexts(directory, party)
    revocations = tls.Revocations.of_directory(directory)
    crl = os.path.join(directory, tls.CRL)
    seen = _crl_stat(crl)
    if seen is not None:
        with open(crl, 'rb') as f:
            try:
                revocations.take(f.read())
            except ConfigError as e:
                raise ConfigError('%s: %s' % (crl, e))
    held = tls.held_number(directory)
    if held is not None and (revocations.number is None or revocations.number < held):
        raise ConfigError('%s: the revocation list is %s, but list %d was taken here before: a rollback '
                          '(copy the CA\'s newest list)' % (crl, 'missing' if revocations.number is None
                                                             else 'number %d' % revocations.number, held))
    if revocations.number is not None:
        tls.remember_number(directory, revocations.number)
    own = tls.serial_of(directory, party)
    if revocations.revoked(own):
        raise ConfigError('the TLS certificate of party %s in %s is revoked (%s)' % (party, directory, crl))
    started = bool(_STATE)
    _STATE.update(server=server, client=client, permissions=permissions, party=party, revocations=revocations,
                  crl=crl, crl_seen=seen, own_serial=own, own_span=tls.span_of(directory, party), directory=directory,
                  files_seen=files)
    if not started:
        threading.Thread(target=_follow_revocations, name='tls_revocations', daemon=True).start()
    if not getattr(base.TCPROSTransport.write_header, 'tls', False):
        original = base.TCPROSTransport.write_header

        def write_header(self):
            # (no protocol: rospy is closing the connection, and writes no header either)
            protocol = self.protocol
            if self.dest_address is not None and self.socket is not None and protocol is not None \
                    and not isinstance(self.socket, ssl.SSLSocket):
                _secure_outbound(self, protocol)
            return original(self)
        write_header.tls = True
        base.TCPROSTransport.write_header = write_header
        read_original = base.TCPROSTransport.read_header

        def read_header(self):
            read_original(self)
            _check_caller(self)
        base.TCPROSTransport.read_header = read_header
    handshake.INBOUND_HOOKS[:] = [_accept]
    _refuse_xmlrpc_shutdowns()
    return party


def _refuse_xmlrpc_shutdowns():
    """Under TLS a node's XML-RPC ``shutdown`` (``rosnode kill``) is refused with the alarm
    ``tls shutdown_refused``: that API is open to anyone on the network, and whoever can call it would
    stop any node. A node stops by a signal on its own host (roslaunch, the Adaptation Engine, a power
    switch). Two requests keep their meaning: one naming another node (the master's, meant for a dead
    process that had this address) is ignored, without an alarm; the master's for this node's name
    registered again is obeyed if the master does map the name to another address now."""
    from rospy.impl import masterslave
    from ..rejoin import misdirected_shutdown
    current = masterslave.ROSHandler.shutdown
    if getattr(current, 'tls_refuses', False):
        return

    def shutdown(handler, caller_id, msg=''):
        import rospy
        own = rospy.get_name()
        if misdirected_shutdown(msg, own):
            rospy.logwarn('%s: a shutdown request from %s ignored: it names another node (%s)', own, caller_id, msg)
            return 1, 'ignored: %s is not the node named' % own, 0
        replaced_by = _replaced_at_master(msg, own)
        if replaced_by:   # the master knows another node by this name: obeyed if that one proves it
            why = contest_name(replaced_by)
            if why is None:
                rospy.logwarn('%s: a node proving this name over TLS registered at %s: shutting down', own,
                              replaced_by)
                return current(handler, caller_id, msg)
            return 0, 'refused: %s; this node goes on and registers its name again' % why, 0
        key = ('xmlrpc', str(caller_id)[:80], str(msg)[:120])
        if _first_in_a_while(key):
            _alarm('shutdown_refused', 'a shutdown asked over XML-RPC by %r (%r) refused: under TLS a node stops '
                   'by a signal on its own host (roslaunch, the Adaptation Engine, a power switch), since anyone '
                   'on the network can call its XML-RPC API' % key[1:])
        return 0, 'refused: %s runs under TLS and stops only by a signal on its own host' % rospy.get_name(), 0
    shutdown.tls_refuses = True
    masterslave.ROSHandler.shutdown = shutdown


def _replaced_at_master(message, own):
    """The URI the master maps this node's name to now, if ``message`` is the master's for a name
    registered again, naming this node, and that URI is another (asked, within 2 s); else None."""
    if message != '[%s] Reason: new node registered with same name' % own:
        return None
    import rosgraph
    from rospy.core import get_node_uri
    from .fencing import node_api
    try:
        code, _, uri = node_api(rosgraph.get_master_uri(), 2.0).lookupNode(own, own)
    except Exception:   # the master does not answer: nothing says this node was replaced
        return None
    return uri if code == 1 and uri.rstrip('/') != get_node_uri().rstrip('/') else None


def name_proof(uri, own, timeout=NAME_PROOF_TIMEOUT):
    """None if the node registered at ``uri`` proves it may run the name ``own``; else why not. The
    master's XML-RPC API is open: anyone can register any name, and the master then asks the node that
    had it to shut down. The proof: the TCPROS server that ``uri`` gives for ``/rosout`` (every rospy
    node publishes it) completes a TLS handshake with a certificate of the CA, not revoked, whose party
    the policy binds to node names that include ``own``, and answers a subscription to ``/rosout`` as
    node ``own``; and it is not this very node (its own address, or any way back to it: a relay,
    another address of this host): the subscription carries a nonce, and this node refuses a
    subscription carrying one of its own proofs under way (_guard). Each step within what is left of
    ``timeout`` s (the caller bounds the whole: contest_name)."""
    from rosgraph.network import encode_ros_handshake_header, read_ros_handshake_header
    from .fencing import is_local, node_api
    deadline = time.monotonic() + timeout

    def left():
        return max(0.05, deadline - time.monotonic())
    try:
        code, said, protocol = node_api(uri, left()).requestTopic(own, '/rosout', [['TCPROS']])
    except Exception as e:
        return 'its XML-RPC API at %s does not answer (%s)' % (uri, str(e)[:80])
    if code != 1 or not isinstance(protocol, list) or len(protocol) != 3 or protocol[0] != 'TCPROS':
        return 'it offers no TCPROS connection at %s (%s)' % (uri, str(said)[:80])
    host, port = protocol[1], protocol[2]
    own_host, own_port = _own_tcpros_address()
    if port == own_port and (host == own_host or is_local('http://%s:1/' % host)):
        return 'it gives this node\'s own TCPROS address'
    try:
        plain = socket.create_connection((host, port), left())
    except (OSError, TypeError, ValueError) as e:
        return 'its TCPROS address %s:%s cannot be reached (%s)' % (host, port, e)
    try:
        plain.settimeout(left())
        secured = _STATE['client'].wrap_socket(plain)
    except (ssl.SSLError, OSError) as e:
        plain.close()
        return 'no TLS handshake with a certificate of the CA at %s:%s (%s)' % (host, port, str(e)[:80])
    nonce = os.urandom(16).hex()
    with _LOCK:
        _PROOFS.add(nonce)
    try:
        certificate = secured.getpeercert()
        party = tls.party_of(certificate)
        why = _revoked(certificate)
        if why:
            return why
        if party is None or _STATE['permissions'].nodes.get(party) is None \
                or _STATE['permissions'].names_node(party, own):
            return 'its certificate (party %s) may not run a node named %s' % (party, own)
        secured.settimeout(left())
        secured.sendall(encode_ros_handshake_header({'topic': '/rosout', 'md5sum': '*', 'type': '*',
                                                     'callerid': own, PROOF_FIELD: nonce}))
        secured.settimeout(left())
        import io
        header = read_ros_handshake_header(secured, io.BytesIO(), 65536)
        if header.get('callerid') != own:
            return 'its TCPROS server answers as %r, not %s%s' % (
                header.get('callerid'), own, ' (%s)' % header['error'][:80] if header.get('error') else '')
        return None
    except Exception as e:
        return 'its TCPROS server at %s:%s did not answer as %s (%s)' % (host, port, own, str(e)[:80])
    finally:
        with _LOCK:
            _PROOFS.discard(nonce)
        secured.close()


def _own_tcpros_address():
    """(host, port) of this node's TCPROS server, or (None, None) before it runs."""
    from rospy.impl.tcpros_base import get_tcpros_server_address
    try:
        return get_tcpros_server_address()
    except AttributeError:
        return None, None


def contest_name(uri):
    """Under TLS, the master maps this node's name to ``uri``: None if that node proves the name
    (name_proof: this node must give way), else why not, after raising the alarm ``tls name_taken``
    (at most once per URI every 10 s) and registering this node again (one thread at a time), which
    maps the name back (the master then sends the impostor's address the shutdown). A proof takes at
    most NAME_PROOF_TIMEOUT in all (a peer answering a byte at a time holds a thread of its own, not
    the caller), and at most PROOF_SLOTS run at once (more are not proven). A node whose own party
    the policy binds to no names can prove nothing, nor can its successor: it gives way, as plain
    rospy does."""
    import rospy
    own = rospy.get_name()
    if _STATE['permissions'].nodes.get(_STATE['party']) is None:
        return None
    why = _proof_within(uri, own)
    if why is None:
        return None
    told = not _first_in_a_while(('name_taken', uri[:120]))
    with _LOCK:
        start = not _REGISTERING['running']
        _REGISTERING['running'] = True
        _REGISTERING['again'] = not start
    if not told:
        _alarm('name_taken', 'the ROS master maps %s to %s now, which does not prove the name (%s): this node '
               'goes on and registers its name again' % (own, uri, why))
    if start:
        threading.Thread(target=_register_until_done, name='tls_name_back', daemon=True).start()
    return why


def _proof_within(uri, own):
    """name_proof in a daemon thread of its own, awaited NAME_PROOF_TIMEOUT (+0.5 s) at most."""
    if not _PROOF_SLOTS.acquire(blocking=False):
        return '%d registrations of this name are being checked already' % PROOF_SLOTS
    result = {}

    def run():
        try:
            result['why'] = name_proof(uri, own)
        except Exception as e:   # (never a proof by accident)
            result['why'] = 'the check failed: %s' % e
        finally:
            _PROOF_SLOTS.release()
    worker = threading.Thread(target=run, name='tls_name_proof', daemon=True)
    worker.start()
    worker.join(NAME_PROOF_TIMEOUT + 0.5)
    return result.get('why', 'no proof within %.1f s' % NAME_PROOF_TIMEOUT)


def _register_until_done():
    """Register this node again, and once more if the name was taken again meanwhile."""
    while True:
        _register_again()
        with _LOCK:
            if not _REGISTERING['again']:
                _REGISTERING['running'] = False
                return
            _REGISTERING['again'] = False


def _register_again():
    import rosgraph
    import rospy
    from .fencing import node_api
    from .rejoin import register_again
    try:
        register_again(node_api(rosgraph.get_master_uri(), 5.0), rospy.get_name(), rospy.core.get_node_uri())
    except Exception as e:   # the master does not answer: the rejoin loop contests again
        rospy.logwarn('%s: registering again after the name was taken failed: %s', rospy.get_name(), e)


def active():
    return bool(_STATE)


def _secure_outbound(transport, protocol):
    from rospy.exceptions import TransportInitError
    fields = protocol.get_header_fields()
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
        if transport.done or transport.protocol is None:
            # rospy closed this connection meanwhile (a duplicate of a connection it has, a subscription
            # going away): it shut the socket down under the handshake. Not a refusal.
            raise TransportInitError('closed during the TLS handshake for %s' % name)
        _refused(transport.dest_address, name, 'TLS with %s:%s failed: %s' % (transport.dest_address + (e,)))
        plain.close()
        transport.socket = None   # not a half-made connection rospy would go on reading
        raise TransportInitError('TLS refused for %s: %s' % (name, e))
    if transport.done or transport.protocol is None:   # rospy closed it while the handshake ran
        secured.close()
        raise TransportInitError('closed during the TLS handshake for %s' % name)
    certificate = secured.getpeercert()
    why = _revoked(certificate) or permissions.allows(tls.party_of(certificate), action, name)
    if why:
        _refused(transport.dest_address, name, why)
        secured.close()
        transport.socket = None
        raise TransportInitError('refused by the TLS policy: %s' % why)
    secured.settimeout(timeout)
    _keep(secured, certificate)
    transport.socket = secured
    transport.tls_party = tls.party_of(certificate)   # the peer's header is bound to it (_read_header)


def _check_caller(transport):
    """After the peer's header is read on an outbound connection: its caller id must be a node name its
    party may run (Permissions.names_node), or the connection is refused and closed."""
    from rospy.exceptions import TransportInitError
    party = getattr(transport, 'tls_party', None)
    header = getattr(transport, 'header', None)
    if transport.socket is None or not header:
        # Closed before a header was read (the peer died, rospy is closing the connection): nothing was
        # said, so nothing is judged (it once counted as a node of the car "named (none)").
        return
    why = _STATE['permissions'].names_node(party, header.get('callerid')) if party is not None else None
    if why:
        name = header.get('topic') or header.get('service') or '?'
        _refused(transport.dest_address, name, why)
        transport.close()
        raise TransportInitError('refused by the TLS policy: %s' % why)


def _accept(server, sock, client_addr):
    """The inbound hook (aft_ftm.ros.handshake): the socket to hand to rospy, or None (closed)."""
    _guard_handlers(server)
    try:
        sock.settimeout(HANDSHAKE_TIMEOUT)
        first = sock.recv(tls.PEEK, socket.MSG_PEEK | socket.MSG_WAITALL)
        if tls.looks_like_tls(first):
            secured = _STATE['server'].wrap_socket(sock, server_side=True)
            certificate = secured.getpeercert()
            why = _revoked(certificate)
            if why:
                _refused(client_addr, '(handshake)', why)
                secured.close()
                return None
            secured.settimeout(None)
            _PEERS[secured] = tls.party_of(certificate)
            _keep(secured, certificate)
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
        if header.get(PROOF_FIELD):
            with _LOCK:
                own_proof = header[PROOF_FIELD] in _PROOFS
            if own_proof:   # a name proof of this node that came back to it: it proves nothing
                return 'refused: this name proof reached the node that made it'
        if header.get('probe') == '1' and action == 'call':
            # rospy.wait_for_service's probe: a bare header, in clear, closed unanswered; it learns only
            # that the service is there, which the master tells anyone
            return handler(sock, client_addr, header)
        party = _PEERS.get(sock)
        why = _STATE['permissions'].allows(party, action, name) or \
            _STATE['permissions'].names_node(party, header.get('callerid'))
        if why:
            _refused(client_addr, name, why)
            return 'refused by the TLS policy: %s' % why
        return handler(sock, client_addr, header)
    handle.tls_guard = True
    handle.one_subscriber_at_a_time = getattr(handler, 'one_subscriber_at_a_time', False)
    return handle


def _judged(party, serial, end, now):
    """(alarm kind, why) if a certificate is no longer accepted (revoked, or past its end), else None:
    the one rule for a new connection and for a live one."""
    if _STATE['revocations'].revoked(serial):
        return 'certificate_revoked', 'certificate %x of party %s is revoked' % (serial, party)
    if end is not None and now > end:
        return 'certificate_expired', 'certificate %x of party %s has expired' % (serial, party)
    return None


def _revoked(certificate):
    """Why a peer certificate is refused at its handshake, or None."""
    serial, end = tls.serial_and_end(certificate)
    judged = _judged(tls.party_of(certificate), serial, end, time.time())
    return judged[1] if judged else None


def _keep(secured, certificate):
    serial, end = tls.serial_and_end(certificate)
    with _LOCK:
        _LIVE[secured] = (tls.party_of(certificate), serial, end)


def _crl_stat(path):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_ino, st.st_size, st.st_mtime_ns)


def _follow_revocations():
    """The watcher thread: the revocation list again when its file changed, and every live
    connection whose certificate is revoked or has expired cut (bounded: CRL_PERIOD per round)."""
    while True:
        time.sleep(CRL_PERIOD)
        try:
            _look_once(time.time())
        except Exception as e:   # never let the watcher die silently
            try:
                _alarm('watch_failed', 'the TLS revocation watcher: %s' % e)
            except Exception:
                pass
        try:
            _publish_pending(time.monotonic())
        except Exception as e:   # shutting down; else said once, the alarms kept for the next round
            if not _STATE.get('publish_failed'):
                _STATE['publish_failed'] = True
                try:
                    import rospy
                    rospy.logerr('TLS alarms cannot be published (kept): %s', e)
                except Exception:
                    pass


def _publish_pending(now):
    """The alarms raised so far, on /aft/alarms: the publisher is made at the first alarm once the
    node is initialised, and given PUBLISHER_SETTLE to be heard, so that alarm is not lost."""
    import rospy
    if not _PENDING or not rospy.core.is_initialized() or rospy.is_shutdown():
        return
    if 'alarms' not in _STATE:
        from aft_msgs.msg import Alarm
        _STATE['alarms'] = rospy.Publisher('/aft/alarms', Alarm, queue_size=_PENDING.maxlen * 2)
        _STATE['alarms_since'] = now
    if now - _STATE['alarms_since'] < PUBLISHER_SETTLE:
        return
    while _PENDING:
        # its source is this node's name now (an alarm queued before init_node had none yet, and the
        # Monitoring Engine takes an alarm only from the node it names)
        _PENDING[0].source = rospy.get_name()
        _STATE['alarms'].publish(_PENDING[0])
        _PENDING.popleft()   # only once published


def _files_stat(directory, party):
    return tuple(_crl_stat(path) for path in tls.certificate_files(directory, party))


def _rotate(files, monotonic):
    """The party's key or certificate changed (module docstring). A certificate that this node's CA
    did not sign for its party, or that is not valid now, or revoked, is refused at once (alarm
    ``rotation_refused``), the old pair kept; a pair that does not load (half copied) is tried again
    each round and said once past ROTATION_GRACE; a pair that loads and passes is used by every new
    connection."""
    import rospy
    directory, party = _STATE['directory'], _STATE['party']
    try:
        serial = tls.check_party_certificate(directory, party, _STATE['revocations'].key, time.time())
        span = tls.span_of(directory, party)
        if _STATE['revocations'].revoked(serial):
            raise ConfigError('its serial %x is revoked' % serial)
    except ConfigError as e:
        if _loads(directory, party):   # whole, and wrong: said at once, not tried again until it changes
            _STATE['files_seen'] = files
            _alarm('rotation_refused', 'the new TLS certificate of party %s in %s is refused: %s (the certificate '
                   'in use stays)' % (party, directory, e))
            return
        serial = None   # half copied: below
    try:
        if serial is None:
            raise ConfigError('the key and certificate do not load as a pair yet')
        server, client = tls.contexts(directory, party)
    except ConfigError as e:
        if _STATE.get('rotation_failing_files') != files:   # another half-copied pair: its own grace
            _STATE.update(rotation_failing_files=files, rotation_failing_since=monotonic, rotation_told=False)
        if monotonic - _STATE['rotation_failing_since'] > ROTATION_GRACE and not _STATE['rotation_told']:
            _STATE['rotation_told'] = True
            _alarm('rotation_failed', 'the changed TLS files of party %s in %s cannot be used: %s (the certificate '
                   'in use stays)' % (party, directory, e))
        return
    old = _STATE['own_serial']
    _STATE.update(server=server, client=client, own_serial=serial, own_span=span, files_seen=files)
    if serial != old:   # its revocation (revoke-replaced) cuts the live connections made with it
        replaced = _STATE.setdefault('replaced_serials', collections.deque(maxlen=16))
        replaced.append(old)
    for key in ('rotation_failing_files', 'rotation_failing_since', 'rotation_told'):
        _STATE.pop(key, None)
    if serial != old:
        rospy.loginfo('%s: tls: party %s rotated: new connections use certificate %x (live ones keep %x until cut)',
                      rospy.get_name(), party, serial, old)


def _loads(directory, party):
    """Whether party's key and certificate in directory load as a pair (else: half copied)."""
    try:
        tls.contexts(directory, party)
        return True
    except ConfigError:
        return False


def _look_once(now):
    files = _files_stat(_STATE['directory'], _STATE['party'])
    if files != _STATE['files_seen']:
        _rotate(files, time.monotonic())
    crl = _STATE['crl']
    seen = _crl_stat(crl)
    if seen is not None and seen != _STATE['crl_seen']:
        _STATE['crl_seen'] = seen
        try:
            with open(crl, 'rb') as f:
                new = _STATE['revocations'].take(f.read())
        except (OSError, ConfigError) as e:
            _alarm('bad_crl', '%s: %s (the list held stays)' % (crl, e))
            new = ()
        else:
            try:
                tls.remember_number(_STATE['directory'], _STATE['revocations'].number)
            except (OSError, ConfigError) as e:
                _alarm('crl_not_kept', 'the revocation list number cannot be kept in %s: %s (a restart could '
                       'take an older list)' % (_STATE['directory'], e))
        if _STATE['own_serial'] in new:
            _alarm('own_certificate_revoked', 'this node\'s certificate (party %s) is revoked by %s: its peers '
                   'refuse it' % (_STATE['party'], crl))
        elif set(new) & set(_STATE.get('replaced_serials', ())):
            # a rotation's old certificate revoked: the peers cut the connections made with it, and
            # this node makes them again with its new one at once, not after the keeper's grace
            _hurry_subscriptions()
    revocations = _STATE['revocations']
    if revocations.next_update is not None and now > revocations.next_update \
            and _STATE.get('stale_told') != revocations.number:
        _STATE['stale_told'] = revocations.number
        _alarm('stale_crl', 'the revocation list %s (number %d) is past its next update: the CA has not '
               'signed a newer one' % (crl, revocations.number))
    _tell_ending(now)
    with _LOCK:
        live = list(_LIVE.items())
    for sock, (party, serial, end) in live:
        judged = _judged(party, serial, end, now)
        if judged is None:
            continue
        with _LOCK:
            _LIVE.pop(sock, None)
        try:
            socket.socket.shutdown(sock, socket.SHUT_RDWR)   # wakes rospy's reader; it drops the connection
        except OSError:
            pass
        _alarm(judged[0], 'cut the connection: %s' % judged[1])
        _hurry_subscriptions()   # a subscription cut here is made again at once (a rotated peer's new certificate)


def _tell_ending(now):
    """``own_certificate_ending`` once this node's own certificate ends soon, ``own_certificate_expired``
    once it has ended (tls.ending_notice): each once per certificate (a rotation's new one is judged
    afresh)."""
    span = _STATE.get('own_span')
    if span is None:
        return
    notice = tls.ending_notice(_STATE['party'], _STATE['own_serial'], span[0], span[1], now)
    if notice is not None and _STATE.get('ending_told') != (_STATE['own_serial'], notice[0]):
        _STATE['ending_told'] = (_STATE['own_serial'], notice[0])
        _alarm(*notice)


def _hurry_subscriptions():
    from .subscription_keeper import hurry
    hurry(HURRY_WINDOW)


def _first_in_a_while(key, period=10.0):
    """Whether ``key`` was not told in the last ``period`` s (and it is now): one alarm per key and
    period. The keys are what an attacker chooses (names, URIs): at most 1000 are kept."""
    now = time.monotonic()
    with _LOCK:
        if now - _TOLD.get(key, -1e9) < period:
            return False
        if len(_TOLD) > 1000:
            _TOLD.clear()
        _TOLD[key] = now
        return True


def _refused(peer, name, why):
    key = (str(peer[0]) if peer else '?', name, why[:120])   # each peer's reason apart (one host, NAT)
    if _first_in_a_while(key):
        _alarm('connection_refused', '%s from %s: %s' % (name, key[0], why))


def _alarm(kind, detail):
    """Log it now; the watcher publishes it within CRL_PERIOD (once the node is initialised)."""
    import rospy
    from aft_msgs.msg import Alarm
    rospy.logwarn('%s: tls %s: %s', rospy.get_name(), kind, detail)
    with _LOCK:
        if len(_PENDING) == _PENDING.maxlen:   # a flood (an attacker's): the oldest goes, counted and said
            _STATE['alarms_dropped'] = _STATE.get('alarms_dropped', 0) + 1
            rospy.logwarn('%s: tls: %d alarm(s) not published (more than %d waiting)', rospy.get_name(),
                          _STATE['alarms_dropped'], _PENDING.maxlen)
    _PENDING.append(Alarm(source=rospy.get_name(), mechanism='tls', kind=kind, detail=detail,
                          stamp=rospy.Time.from_sec(time.time())))
