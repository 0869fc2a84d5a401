"""Mutual TLS for TCPROS (issue 16): every topic and service connection between AFT-ROS nodes
authenticated by a certificate of its party (a site, the witness, a client site), ciphered, and
allowed by an access-control policy, as SROS does for ROS 1 and SROS2 for ROS 2. No rospy here:
keys and certificates (the ``cryptography`` library, X.509, ECDSA P-256), the TLS contexts
(Python's ``ssl``, OpenSSL), the policy, and the judgement of one connection.

The policy file (YAML; names are fnmatch patterns of resolved topic and service names)::

    plaintext: [/rosout, /account]   # names open to peers without TLS (ROS tools, the unmodified
                                     # application's own client and server)
    readable: ['/sensors/*']         # topics a peer without TLS may subscribe to, never publish
                                     # (a recorder such as rosbag record, which has no TLS)
    parties:
      master:
        nodes: ['/master/*']         # the node names it may run (optional: any name if absent)
        publish: [/ftm/checkpoints/master, /master/*]
        subscribe: ['*']
        serve: [/master/*]
        call: ['*']

A connection is judged at both ends: the subscriber checks that the publisher's party may publish
the topic, the publisher that the subscriber's may subscribe; the caller that the server's party may
serve the service, the server that the caller's may call it. A peer without a certificate is allowed
only on a plaintext name. A party with ``nodes`` is bound to them: a connection whose peer names
itself (its caller id) outside them is refused, so a message's caller id, and an alarm's source,
name a node of the party that holds the certificate. TLS itself gives freshness (a recorded connection cannot be replayed) and
integrity on every message of the connection.

Revocation follows the X.509 way: the CA signs a certificate revocation list (``ca.tls.crl``,
``revoke``) with a number one higher each time; the operator copies it to every party's directory
(as CRLs are distributed); each node follows its copy (``Revocations``: only a list the CA signed,
never an older one) and refuses, and cuts, connections of a revoked certificate. The CA keeps the
serial of every certificate it issued to each party (``ca.tls.issued``): revoking a party revokes
them all, those a re-issue replaced included (a rotation of a suspected key), or only the replaced
ones (``revoke(..., replaced_only=True)``, ``tls_keygen --revoke-replaced``).
"""
import contextlib
import datetime
import fnmatch
import os
import ssl

from .errors import ConfigError

ACTIONS = ('publish', 'subscribe', 'serve', 'call')
TLS_RECORD = (0x16, 0x03)   # a TLS handshake record: content type 22, version 3.x


PEEK = 6   # bytes of an inbound connection looked at before deciding


def looks_like_tls(first):
    """Whether the first PEEK bytes of an inbound connection are a TLS ClientHello: a handshake
    record (22, version 3.1-3.4) of at most 16 kB whose first message is a ClientHello (1). A TCPROS
    header starts with its 4-byte little-endian length, then its first field's: to look the same it
    would have to be 66-328 kB long (16 03 0[1-4] 00) with a first field of 256-511 bytes (.. 01),
    which no rospy header is (a 790-byte one begins 16 03 00 00: not TLS)."""
    if len(first) < PEEK or first[0] != TLS_RECORD[0] or first[1] != TLS_RECORD[1] or not 1 <= first[2] <= 4:
        return False
    record = (first[3] << 8) | first[4]
    return 0 < record <= 16384 and first[5] == 0x01


# -- keys and certificates ------------------------------------------------------------------------
def _names(directory, party):
    return os.path.join(directory, party + '.tls.key'), os.path.join(directory, party + '.tls.crt')


def certificate_files(directory, party):
    """(key, certificate) paths of party in directory."""
    return _names(directory, _check_party(party))


def make_authority(directory, days=3650):
    """ca.tls.key (0600) and ca.tls.crt in directory, unless there; returns the certificate's path."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID
    key_path, crt_path = _names(directory, 'ca')
    if os.path.exists(crt_path):
        return crt_path
    os.makedirs(directory, exist_ok=True)
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, 'aft-ros tls ca')])
    now = datetime.datetime.utcnow()
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .sign(key, hashes.SHA256()))
    write_file(key_path, key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()), 0o600)
    write_file(crt_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return crt_path


def issue(directory, party, days=30, lifetime=None):
    """<party>.tls.key (0600) and <party>.tls.crt, signed by the CA of directory (common name: the
    party), valid for days (or lifetime, a timedelta). Replaces an existing pair (a rotation); the
    serial of each, the replaced one's included, is recorded in ca.tls.issued (``revoke`` uses it)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID
    _check_party(party)
    ca_key_path, ca_crt_path = _names(directory, 'ca')
    with open(ca_key_path, 'rb') as f:
        ca_key = serialization.load_pem_private_key(f.read(), None)
    with open(ca_crt_path, 'rb') as f:
        ca_cert = x509.load_pem_x509_certificate(f.read())
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.utcnow()
    cert = (x509.CertificateBuilder().subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, party)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + (lifetime or datetime.timedelta(days=days)))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .sign(ca_key, hashes.SHA256()))
    key_path, crt_path = _names(directory, party)
    issued = issued_serials(directory)
    serials = issued.setdefault(party, [])
    if os.path.exists(crt_path):   # the certificate replaced, if made before the record was kept
        serials.append(serial_of(directory, party))
    serials.append(cert.serial_number)
    _write_issued(directory, issued)   # recorded before the certificate is written: never one unrecorded
    write_file(key_path, key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()), 0o600)
    write_file(crt_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return crt_path


def party_of_directory(directory):
    """The party a directory of export_party's is for: the one party (not ca) whose key and certificate
    are both there. ConfigError naming the directory if none or several are."""
    try:
        names = os.listdir(directory)
    except OSError as e:
        raise ConfigError('TLS directory %s cannot be read: %s' % (directory, e))
    parties = sorted(n[:-len('.tls.key')] for n in names
                     if n.endswith('.tls.key') and n != 'ca.tls.key' and n[:-len('.tls.key')] + '.tls.crt' in names)
    if len(parties) != 1:
        raise ConfigError('TLS directory %s holds the key and certificate of %s: one party\'s are needed'
                          % (directory, ', '.join(parties) if parties else 'no party'))
    return _check_party(parties[0])


def export_party(directory, party, destination):
    """A directory of party's own (made 0700): its key and certificate and the CA's certificate, never
    the CA's key nor another party's: what one machine of that party is given. Returns it."""
    import shutil
    _check_party(party)
    os.makedirs(destination, mode=0o700, exist_ok=True)
    for path in _names(directory, party) + (_names(directory, 'ca')[1], os.path.join(directory, CRL)):
        if path.endswith(CRL) and not os.path.exists(path):
            continue
        target = os.path.join(destination, os.path.basename(path))
        shutil.copyfile(path, target)
        os.chmod(target, 0o600 if path.endswith('.key') else 0o644)
    return destination


CRL = 'ca.tls.crl'


def _authority(directory):
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    ca_key_path, ca_crt_path = _names(directory, 'ca')
    try:
        with open(ca_key_path, 'rb') as f:
            ca_key = serialization.load_pem_private_key(f.read(), None)
        with open(ca_crt_path, 'rb') as f:
            return ca_key, x509.load_pem_x509_certificate(f.read())
    except (OSError, ValueError) as e:
        raise ConfigError('no usable TLS CA in %s: %s' % (directory, e))


def _certificate_of(directory, party):
    """party's certificate in directory (cryptography's x509), or ConfigError."""
    from cryptography import x509
    path = _names(directory, _check_party(party))[1]
    try:
        with open(path, 'rb') as f:
            return x509.load_pem_x509_certificate(f.read())
    except (OSError, ValueError) as e:
        raise ConfigError('no usable TLS certificate of party %s: %s' % (party, e))


def serial_of(directory, party):
    """The serial number of party's certificate in directory."""
    return _certificate_of(directory, party).serial_number


def span_of(directory, party):
    """(begins, ends): the validity of party's certificate in directory, in seconds since the epoch."""
    cert = _certificate_of(directory, party)
    return tuple(t.replace(tzinfo=datetime.timezone.utc).timestamp()
                 for t in (cert.not_valid_before, cert.not_valid_after))


ENDING_WARN = 7 * 86400.0   # s before its end that a node's own certificate is said to end soon (at most)


def _left(seconds):
    return '%.1f days' % (seconds / 86400.0) if seconds >= 86400 else '%.0f s' % seconds


def ending_notice(party, serial, begins, ends, now, warn=ENDING_WARN):
    """(alarm kind, detail) when a node's own certificate has ended or ends soon, else None. Soon:
    within warn s of its end, or in the last fifth of its life if that is shorter (a certificate of
    hours is not said to end from its first minute; its life counts from its not-before, which issue()
    sets 5 minutes back for clock skew, so one of a minute or so is said at once). Certificates are
    not renewed by themselves (README): without this, the first sign was every peer refusing the
    node. Once it has ended every peer refuses the node, so the expired alarm reaches the node's own
    log at least, and /aft/alarms only over a connection still open."""
    at = datetime.datetime.fromtimestamp(ends, datetime.timezone.utc).isoformat()
    left = ends - now
    if left <= 0:
        return 'own_certificate_expired', (
            'this node\'s TLS certificate (party %s, serial %x) ended at %s: every peer refuses it; issue a new one '
            '(tls_keygen DIR %s) and copy it to the node\'s directory' % (party, serial, at, party))
    if left <= min(warn, (ends - begins) / 5.0):
        return 'own_certificate_ending', (
            'this node\'s TLS certificate (party %s, serial %x) ends in %s, at %s: rotate it before then (tls_keygen '
            'DIR %s, and copy it to the node\'s directory), or every peer refuses the node' % (
                party, serial, _left(left), at, party))
    return None


ISSUED = 'ca.tls.issued'   # {party: [serials, hexadecimal]}: every certificate the CA issued to it


def issued_serials(directory):
    """{party: [serial, ...]}: the certificates the CA of directory issued, oldest first ({} before any
    was recorded). ConfigError names the file and the entry that is wrong."""
    import json
    path = os.path.join(directory, ISSUED)
    try:
        with open(path) as f:
            data = json.load(f)
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as e:
        raise ConfigError('the record of issued TLS certificates %s cannot be read: %s' % (path, e))
    if not isinstance(data, dict):
        raise ConfigError('%s: expected a mapping of party names to lists of serials' % path)
    issued = {}
    for party, serials in data.items():
        if not isinstance(serials, list) or not all(isinstance(s, str) for s in serials):
            raise ConfigError('%s: party %r: expected a list of hexadecimal serials, got %r' % (path, party, serials))
        try:
            issued[party] = [_serial(s) for s in serials]
        except ConfigError as e:
            raise ConfigError('%s: party %r: %s' % (path, party, e))
    return issued


def _write_issued(directory, issued):
    import json
    data = dict((party, ['%x' % s for s in dict.fromkeys(serials)]) for party, serials in issued.items())
    write_file(os.path.join(directory, ISSUED), json.dumps(data, indent=1, sort_keys=True).encode(), 0o600)


def revoke(directory, parties=(), serials=(), days=7, replaced_only=False):
    """Revoke every certificate the CA in directory issued to parties (their current ones and those
    a re-issue replaced: ca.tls.issued), or, with replaced_only, the replaced ones only (the current
    one stays valid: a rotation of a suspected key); and the certificates of serials.
    <directory>/ca.tls.crl is signed again listing every serial revoked so far, its CRL number one
    higher. Returns (the CRL's path, its number)."""
    with file_lock(os.path.join(directory, 'ca.tls.lock')):   # two revocations at once lose nothing
        return _revoke(directory, parties, serials, days, replaced_only)


def _revoke(directory, parties, serials, days, replaced_only):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    ca_key, ca_cert = _authority(directory)
    path = os.path.join(directory, CRL)
    held = Revocations(ca_cert.public_key())
    if os.path.exists(path):
        with open(path, 'rb') as f:
            held.take(f.read())
    issued = issued_serials(directory)
    named = set()
    for party in parties:
        current = serial_of(directory, party)
        every = set(issued.get(party, ())) | {current}
        named |= every - {current} if replaced_only else every
    revoked = set(held.serials) | set(_serial(s) for s in serials) | named
    number = (held.number or 0) + 1
    now = datetime.datetime.utcnow()
    builder = (x509.CertificateRevocationListBuilder().issuer_name(ca_cert.subject).last_update(now)
               .next_update(now + datetime.timedelta(days=days)).add_extension(x509.CRLNumber(number), critical=False))
    for serial in sorted(revoked):
        builder = builder.add_revoked_certificate(
            x509.RevokedCertificateBuilder().serial_number(serial).revocation_date(now).build())
    crl = builder.sign(ca_key, hashes.SHA256())
    write_file(path, crl.public_bytes(serialization.Encoding.PEM), 0o644)
    return path, number


HELD = 'ca.tls.crl.held'   # the highest list number a party's nodes have taken: no rollback across restarts


def held_number(directory):
    """The highest revocation list number a node of this directory took, or None."""
    import json
    path = os.path.join(directory, HELD)
    try:
        with open(path) as f:
            number = json.load(f)['number']
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ConfigError('%s cannot be read (%s): remove it only if the revocation list is right' % (path, e))
    if not isinstance(number, int):
        raise ConfigError('%s: the number must be an integer, got %r' % (path, number))
    return number


def remember_number(directory, number):
    """Keep number as the highest list number taken (never lowers it)."""
    import json
    held = held_number(directory)
    if held is None or number > held:
        write_file(os.path.join(directory, HELD), json.dumps({'number': number}).encode(), 0o600)


def _serial(value):
    """A serial number: an int, or a string in hexadecimal as alarms and logs print it."""
    if isinstance(value, int):
        return value
    try:
        return int(str(value), 16)
    except ValueError:
        raise ConfigError('a certificate serial is hexadecimal, got %r' % (value,))


class Revocations(object):
    """The certificates the CA revoked, as far as one party knows: taken only from a revocation list
    the CA signed, and never from one older (by its CRL number) than the list held, so a replayed old
    list cannot take a revocation back."""

    def __init__(self, ca_public_key):
        self.key = ca_public_key
        self.number = None
        self.serials = frozenset()
        self.next_update = None   # when the CA said it would sign a newer list (seconds since the epoch)

    @classmethod
    def of_directory(cls, directory):
        from cryptography import x509
        try:
            with open(_names(directory, 'ca')[1], 'rb') as f:
                return cls(x509.load_pem_x509_certificate(f.read()).public_key())
        except (OSError, ValueError) as e:
            raise ConfigError('no usable TLS CA certificate in %s: %s' % (directory, e))

    def take(self, data):
        """Take a CRL (PEM bytes): returns the serials it newly revokes. Raises ConfigError, changing
        nothing, for a list that is malformed, not signed by the CA, older than the one held, or of
        the same number with other serials."""
        from cryptography import x509
        try:
            crl = x509.load_pem_x509_crl(data)
            signed = crl.is_signature_valid(self.key)
        except (ValueError, TypeError) as e:
            raise ConfigError('the TLS revocation list cannot be read: %s' % e)
        if not signed:
            raise ConfigError('the TLS revocation list is not signed by the CA')
        try:
            number = crl.extensions.get_extension_for_class(x509.CRLNumber).value.crl_number
        except x509.ExtensionNotFound:
            raise ConfigError('the TLS revocation list has no CRL number')
        serials = frozenset(r.serial_number for r in crl)
        if self.number is not None and number < self.number:
            raise ConfigError('the TLS revocation list number %d is older than the one held (%d): refused'
                              % (number, self.number))
        if number == self.number and serials != self.serials:
            raise ConfigError('the TLS revocation list number %d differs from the one held under that number'
                              % number)
        if not serials >= self.serials:
            raise ConfigError('the TLS revocation list number %d takes back revoked serials: refused' % number)
        new = serials - self.serials
        self.number, self.serials = number, serials
        if crl.next_update is not None:
            self.next_update = crl.next_update.replace(tzinfo=datetime.timezone.utc).timestamp()
        return new

    def revoked(self, serial):
        return serial in self.serials


@contextlib.contextmanager
def file_lock(path):
    """An exclusive flock on path (made 0600 if missing) while the block runs: two writers of one
    file (two revocations at once) take turns, and neither's change is lost."""
    import fcntl
    fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, 'O_NOFOLLOW', 0), 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def write_file(path, data, mode):
    """path replaced whole by data (a reader sees the old file or the new one, never a part)."""
    temporary = '%s.tmp-%d' % (path, os.getpid())
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, 'wb') as f:
        f.write(data)
    os.replace(temporary, path)


def _check_party(party):
    if not party or not all(c.isalnum() or c in '_-' for c in party) or party == 'ca':
        raise ConfigError('TLS party name must be letters, digits, - or _ (and not ca), got %r' % (party,))
    return party


def contexts(directory, party):
    """(server context, client context) of party: its certificate, and only peers the CA certified."""
    key_path, crt_path = _names(directory, _check_party(party))
    ca_crt = _names(directory, 'ca')[1]
    made = []
    for purpose in (ssl.Purpose.CLIENT_AUTH, ssl.Purpose.SERVER_AUTH):
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER if purpose is ssl.Purpose.CLIENT_AUTH
                                 else ssl.PROTOCOL_TLS_CLIENT)
        context.minimum_version = ssl.TLSVersion.TLSv1_3
        context.check_hostname = False      # a party is named by its certificate, not by a host name
        context.verify_mode = ssl.CERT_REQUIRED
        if purpose is ssl.Purpose.CLIENT_AUTH:
            context.num_tickets = 0   # no session resumption: every connection shows a certificate judged now
        try:
            context.load_cert_chain(crt_path, key_path)
            context.load_verify_locations(ca_crt)
        except (OSError, ssl.SSLError) as e:
            raise ConfigError('TLS files of party %s in %s cannot be used: %s' % (party, directory, e))
        made.append(context)
    return tuple(made)


def check_party_certificate(directory, party, ca_public_key, now):
    """The serial of party's certificate in directory if the CA of ca_public_key signed it for party
    and it is valid at now (seconds since the epoch); else ConfigError naming why. What a node checks
    before it takes a rotated certificate: loading a key and certificate checks neither (review of
    session 42: a pair of another CA, an ended one or another party's would have replaced a working
    one, and every peer refused the node from then on)."""
    from cryptography import x509
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives.asymmetric import ec, padding, rsa
    path = certificate_files(directory, party)[1]
    try:
        with open(path, 'rb') as f:
            cert = x509.load_pem_x509_certificate(f.read())
    except (OSError, ValueError) as e:
        raise ConfigError('the certificate %s cannot be read: %s' % (path, e))
    try:
        if isinstance(ca_public_key, ec.EllipticCurvePublicKey):
            ca_public_key.verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
        elif isinstance(ca_public_key, rsa.RSAPublicKey):
            ca_public_key.verify(cert.signature, cert.tbs_certificate_bytes, padding.PKCS1v15(),
                                 cert.signature_hash_algorithm)
        else:
            raise ConfigError('the CA\'s key is of a kind not checked here: %s' % type(ca_public_key).__name__)
    except (InvalidSignature, ValueError, TypeError):
        raise ConfigError('the certificate %s is not signed by this CA' % path)
    names = [a.value for a in cert.subject.get_attributes_for_oid(x509.oid.NameOID.COMMON_NAME)]
    if names != [party]:
        raise ConfigError('the certificate %s names %s, not party %s' % (path, names or 'nobody', party))
    begins = cert.not_valid_before.replace(tzinfo=datetime.timezone.utc).timestamp()
    ends = cert.not_valid_after.replace(tzinfo=datetime.timezone.utc).timestamp()
    if not begins <= now < ends:
        raise ConfigError('the certificate %s is valid from %s to %s, not now' % (
            path, cert.not_valid_before.isoformat(), cert.not_valid_after.isoformat()))
    return cert.serial_number


def serial_and_end(peer_certificate):
    """(serial number, not-after in seconds since the epoch) of a getpeercert() dictionary."""
    serial = int((peer_certificate or {}).get('serialNumber', '0'), 16)
    end = (peer_certificate or {}).get('notAfter')
    return serial, (ssl.cert_time_to_seconds(end) if end else None)


def party_of(peer_certificate):
    """The common name of a peer certificate as ssl.SSLSocket.getpeercert() gives it, or None."""
    for entry in (peer_certificate or {}).get('subject', ()):
        for key, value in entry:
            if key == 'commonName':
                return value
    return None


# -- the policy -------------------------------------------------------------------------------------
class Permissions(object):
    """Who may publish, subscribe, serve or call what (see the module docstring)."""

    def __init__(self, parties, plaintext=(), readable=(), nodes=None):
        self.parties = parties
        self.nodes = dict(nodes or {})   # party: the patterns of its node names (absent: any name)
        self.plaintext_names = list(plaintext)
        self.readable_names = list(readable)

    @classmethod
    def load(cls, path):
        from .sec_policy import read_yaml
        return cls.parse(read_yaml(path, 'TLS policy'), path)

    @classmethod
    def parse(cls, data, where='the TLS policy'):
        if not isinstance(data, dict) or not set(data) <= {'plaintext', 'readable', 'parties'} \
                or 'parties' not in data or not isinstance(data['parties'], dict):
            raise ConfigError('%s: expected the keys parties (a mapping) and, optionally, plaintext and readable '
                              '(lists)' % where)
        plaintext, readable = data.get('plaintext') or [], data.get('readable') or []
        for key, names in (('plaintext', plaintext), ('readable', readable)):
            if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
                raise ConfigError('%s: %s must be a list of names' % (where, key))
        parties, nodes = {}, {}
        keys = ACTIONS + ('nodes',)
        for party, rules in data['parties'].items():
            rules = {} if rules is None else rules
            if not isinstance(rules, dict):
                raise ConfigError('%s: party %r: expected a mapping of %s' % (where, party, ', '.join(keys)))
            unknown = sorted(str(k) for k in set(rules) - set(keys))
            if unknown:
                raise ConfigError('%s: party %r: unknown key(s) %s (known: %s)' % (where, party, ', '.join(unknown),
                                                                                 ', '.join(keys)))
            for action, names in rules.items():
                if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
                    raise ConfigError('%s: party %r: %s must be a list of names' % (where, party, action))
                if action == 'nodes' and not names:
                    raise ConfigError('%s: party %r: nodes is empty (no node could run; leave it out for '
                                      'any name)' % (where, party))
            parties[str(party)] = dict((a, list(rules.get(a) or [])) for a in ACTIONS)
            if 'nodes' in rules:
                nodes[str(party)] = list(rules['nodes'])
        return cls(parties, plaintext, readable, nodes)

    def plaintext(self, name):
        return any(fnmatch.fnmatchcase(name, p) for p in self.plaintext_names)

    def names_node(self, party, callerid):
        """None if a peer of party may call itself callerid (its node's name); else why not. A peer
        without TLS (None), and a party without ``nodes``, are not bound to names."""
        patterns = self.nodes.get(party)
        if party is None or patterns is None:
            return None
        if callerid and any(fnmatch.fnmatchcase(callerid, p) for p in patterns):
            return None
        return 'party %s may not run a node named %s' % (party, callerid or '(none)')

    def allows(self, party, action, name):
        """None if party may do action on name; else why not. party None: a peer without TLS."""
        if self.plaintext(name):
            return None   # open to anyone, with a certificate or without
        if party is None:
            if action == 'subscribe' and any(fnmatch.fnmatchcase(name, p) for p in self.readable_names):
                return None   # readable: anyone may listen, nobody without a certificate may speak
            return '%s needs TLS: a peer without a certificate may not %s it' % (name, action)
        patterns = self.parties.get(party, {}).get(action)
        if patterns is None:
            return 'party %s is in no policy' % party
        if any(fnmatch.fnmatchcase(name, p) for p in patterns):
            return None
        return 'party %s may not %s %s' % (party, action, name)
