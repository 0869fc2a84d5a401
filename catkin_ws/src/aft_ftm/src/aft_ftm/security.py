"""SEC: cipher and signature of requests and replies, with a certification authority (paper
section 5.3.2). Built on PyNaCl (libsodium): SealedBox (X25519 + XSalsa20-Poly1305) ciphers a
payload for its recipient, Ed25519 signs it for its sender; the CA signs each party's public keys.
A SealedBox is anonymous, so the ciphered plaintext itself names its sealer and the hash of the
header it was sealed under: another party cannot keep a captured ciphertext and sign it under its
own name or header (``open_sealed`` refuses it, ``tampered``).

Nothing here logs or returns key material in error messages.
"""
import base64
import collections
import fnmatch
import hashlib
import heapq
import json
import os
import secrets
import struct

import nacl.exceptions
import nacl.public
import nacl.signing

from .errors import AftError, ConfigError

SIGNATURE_BYTES = 64


class Rejected(AftError):
    """A message refused by SEC. ``kind``: unsigned, malformed (too large, or nested too deep to read),
    bad_signature, unknown_party, tampered (its signed header is not the envelope's, or its ciphertext
    was sealed by another party or under another header), replay, undecryptable, misaddressed (signed
    for another destination, or a request presented as a reply or the reverse), spoofed_origin (a
    party sending as a Proxy that is not its own), revoked, expired, bad_certificate, stale_status,
    ca_unreachable (the CA did not answer about a certificate in time, or no status of the CA has come
    yet to judge it by), party_quota (a party with as many requests outstanding as it may have),
    earlier_run (a request an earlier run of the gate let through, after a restart: ReplayGuard),
    replay_log (a request not let through because the replay log could not record it)."""

    def __init__(self, kind, detail):
        super(Rejected, self).__init__('%s: %s' % (kind, detail))
        self.kind = kind
        self.detail = detail


# -- keys -----------------------------------------------------------------------------------------
class Party(object):
    """A participant's key pairs: one to be ciphered for (box), one to sign with."""

    def __init__(self, name, box_private, signing):
        self.name = name
        self.box_private = box_private
        self.signing = signing

    @classmethod
    def generate(cls, name):
        return cls(name, nacl.public.PrivateKey.generate(), nacl.signing.SigningKey.generate())

    @property
    def box_public(self):
        return bytes(self.box_private.public_key)

    @property
    def verify_public(self):
        return bytes(self.signing.verify_key)

    def __repr__(self):
        return 'Party(%r)' % self.name   # never the keys


def _check_name(name):
    if not name or not all(c.isalnum() or c in '_-' for c in name):
        raise ConfigError('party name must be letters, digits, - or _, got %r' % (name,))
    return name


def write_party(directory, party):
    """<party>.key (private, mode 0600) and <party>.pub (public) in directory."""
    _check_name(party.name)
    os.makedirs(directory, exist_ok=True)
    # Each file replaced whole (a rotation rewrites them while gates and the CA read them): the
    # public key first, so that the CA may certify it before its owner signs with it.
    _replace(os.path.join(directory, party.name + '.pub'), 0o644,
             {'box': base64.b64encode(party.box_public).decode(),
              'verify': base64.b64encode(party.verify_public).decode()})
    _replace(os.path.join(directory, party.name + '.key'), 0o600,
             {'box': base64.b64encode(bytes(party.box_private)).decode(),
              'sign': base64.b64encode(bytes(party.signing)).decode()})


def _replace(path, mode, data):
    temporary = '%s.tmp-%d' % (path, os.getpid())
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, 'w') as f:
        json.dump(data, f)
    os.chmod(temporary, mode)
    os.replace(temporary, path)


def _read_json(path, what):
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError) as e:
        raise ConfigError('cannot read %s %s: %s' % (what, path, e.__class__.__name__))


def read_party(directory, name):
    """The private keys of party name; ConfigError naming the file (never its content)."""
    path = os.path.join(directory, _check_name(name) + '.key')
    data = _read_json(path, 'private key file')
    try:
        return Party(name, nacl.public.PrivateKey(base64.b64decode(data['box'])),
                     nacl.signing.SigningKey(base64.b64decode(data['sign'])))
    except (KeyError, TypeError, ValueError, nacl.exceptions.CryptoError):
        raise ConfigError('private key file %s is malformed' % path)


def read_public(directory, name):
    """(box public key, verify key) of party name, as bytes."""
    path = os.path.join(directory, _check_name(name) + '.pub')
    data = _read_json(path, 'public key file')
    try:
        box, verify = base64.b64decode(data['box']), base64.b64decode(data['verify'])
    except (KeyError, TypeError, ValueError):
        raise ConfigError('public key file %s is malformed' % path)
    if len(box) != 32 or len(verify) != 32:
        raise ConfigError('public key file %s is malformed' % path)
    return box, verify


# -- certificates ---------------------------------------------------------------------------------
# A certificate binds a party's name to its public keys, under a serial number (revocation names it)
# and an expiry, both in the CA's own time: nobody compares wall clocks with the CA's (issue 16).
Cert = collections.namedtuple('Cert', 'box_public verify_public serial not_after')


def _certificate_content(name, box_public, verify_public, serial, not_after):
    return (b'aft-cert-v2|' + name.encode() + b'|' + bytes(box_public) + bytes(verify_public)
            + struct.pack('>Qd', serial, not_after))


def certify(ca, name, box_public, verify_public, serial, not_after):
    """The CA's signature over a party's public keys, serial and expiry (CA time, s)."""
    return ca.signing.sign(_certificate_content(name, box_public, verify_public, serial, not_after)).signature


def check_certificate(ca_verify_public, name, box_public, verify_public, serial, not_after, signature):
    """The Cert, or Rejected('bad_certificate') unless the CA signed these keys, serial and expiry
    for this name."""
    try:
        nacl.signing.VerifyKey(bytes(ca_verify_public)).verify(
            _certificate_content(name, box_public, verify_public, serial, not_after), bytes(signature))
    except (nacl.exceptions.BadSignatureError, ValueError, TypeError, struct.error):
        raise Rejected('bad_certificate', 'the certificate of %s is not signed by the CA' % name)
    return Cert(bytes(box_public), bytes(verify_public), serial, not_after)


def _status_content(ca_time, seq, revoked):
    return b'aft-status-v1|' + struct.pack('>dQ', ca_time, seq) + b''.join(struct.pack('>Q', r) for r in
                                                                          sorted(revoked))


def sign_status(ca, ca_time, seq, revoked):
    """The CA's signed status: its time, a sequence number that only grows, the revoked serials."""
    return ca.signing.sign(_status_content(ca_time, seq, revoked)).signature


class CertificateBook(object):
    """The certificates a gate holds, judged by the CA's signed status (its time and revocations).

    The CA publishes its status every period; ``on_status`` takes one only if the CA signed it and
    its sequence number is newer (a replayed status is refused), then drops every certificate it
    revokes. Expiry is judged in the CA's time, carried forward by this gate's monotonic clock from
    the last status (``now``: monotonic seconds): no wall clock is compared with another. A revoked
    key is thus refused within one status period of its revocation, plus delivery. Before the first
    status no certificate is taken (``ca_unreachable``): a revoked or expired one would pass."""

    def __init__(self, ca_verify_public, silent_after=3.0):
        self.ca_verify = bytes(ca_verify_public)
        self.silent_after = silent_after
        self.peers = {}          # party -> Cert: the newest held
        self.previous = {}       # party -> Cert: the one before (a rotated key, valid until revoked)
        self.revoked = set()     # serials
        self.seq = None          # the last status taken
        self.ca_time = None      # the CA's time in it ...
        self.heard_at = None     # ... and when (monotonic) it came

    def on_status(self, ca_time, seq, revoked, signature, now):
        """Take a status; returns the parties whose certificate it ends. Rejected: not the CA's
        (bad_signature) or not newer than the last (stale_status)."""
        try:
            nacl.signing.VerifyKey(self.ca_verify).verify(_status_content(ca_time, seq, revoked), bytes(signature))
        except (nacl.exceptions.BadSignatureError, ValueError, TypeError, struct.error):
            raise Rejected('bad_signature', 'a certificate status not signed by the CA')
        if self.seq is not None and seq <= self.seq:
            raise Rejected('stale_status', 'certificate status %d is not newer than %d (a replay)' % (seq, self.seq))
        self.seq, self.ca_time, self.heard_at = seq, ca_time, now
        self.revoked = set(revoked)
        return self._drop_invalid(now)

    def ca_now(self, now):
        """The CA's time now, as this gate can tell (None before any status)."""
        return None if self.ca_time is None else self.ca_time + (now - self.heard_at)

    def silent(self, now):
        """Seconds since the last status if longer than silent_after (or none ever came), else None."""
        if self.heard_at is None:
            return float('inf')
        waited = now - self.heard_at
        return waited if waited > self.silent_after else None

    def add(self, party, cert, now):
        """Hold a checked certificate, unless revoked or expired (Rejected)."""
        why = self._invalid(cert, now)
        if why:
            raise Rejected(why[0], 'the certificate of %s (serial %d) %s' % (party, cert.serial, why[1]))
        held = self.peers.get(party)
        if held is not None and held.serial != cert.serial:
            self.previous[party] = held
        self.peers[party] = cert
        return cert

    def fetch_again(self, party):
        """Its held certificate may be stale (its key rotated): the next get() returns None, so the
        certificate is fetched again; the one held is kept as the previous one meanwhile."""
        held = self.peers.pop(party, None)
        if held is not None:
            self.previous[party] = held

    def candidates(self, party, now):
        """The valid certificates held for party, newest first (a rotated key's old one second)."""
        found = [self.get(party, now)]
        old = self.previous.get(party)
        if old is not None and self._invalid(old, now):
            del self.previous[party]
            old = None
        return [c for c in found + [old] if c is not None]

    def get(self, party, now):
        """The valid certificate held for party, or None (none held, or it expired: fetch again)."""
        cert = self.peers.get(party)
        if cert is not None and self._invalid(cert, now):
            del self.peers[party]
            return None
        return cert

    def _invalid(self, cert, now):
        if cert.serial in self.revoked:
            return ('revoked', 'is revoked')
        ca_now = self.ca_now(now)
        if ca_now is None:
            # Before the first status nothing says whether it is revoked, nor what time it is for the CA.
            return ('ca_unreachable', 'cannot be judged: no certificate status from the CA has come yet '
                                      '(its revocations and time are unknown)')
        if cert.not_after <= ca_now:
            return ('expired', 'expired at CA time %.1f (now %.1f)' % (cert.not_after, ca_now))
        return None

    def _drop_invalid(self, now):
        dropped = sorted(p for p, c in self.peers.items() if self._invalid(c, now))
        for party in dropped:
            del self.peers[party]
        for party in [p for p, c in self.previous.items() if self._invalid(c, now)]:
            del self.previous[party]
        return dropped


class Issuer(object):
    """The certification authority's book: a certificate per party (serial, expiry in CA time), the
    revoked serials, and its signed status. ``now``: the CA's own clock (s).

    - a party's keys changing (a rotation: a new .pub) get a new certificate; the old one stays
      valid for ``overlap`` seconds (messages signed with the old key meanwhile are still taken,
      while every gate fetches the new certificate), then is revoked;
    - a certificate past half its validity is renewed on the next ask (a new serial; the old one
      stays valid until it expires);
    - a party named in the revocations has every serial it holds revoked and gets no new one until
      it is named no more.

    ``state()`` is what outlives a restart (``restore``): the revoked and retiring serials, every
    serial issued and not expired yet with its expiry and the keys it certifies (so a party revoked,
    or whose key changed, after a restart, or while the CA was down, has its older certificates
    revoked too), and the status sequence number reserved (a restarted CA's statuses stay newer,
    whatever its clock did meanwhile)."""

    SEQ_RESERVE = 60000   # status numbers reserved (saved) ahead of the last published: one save a minute

    def __init__(self, ca, validity, overlap=10.0):
        self.ca = ca
        self.validity = validity
        self.overlap = overlap
        self.retiring = {}       # serial -> CA time from which it is revoked (a rotated key)
        self.keys = {}           # party -> (box_public, verify_public)
        self.saved_keys = {}     # party -> the keys a previous run certified, until set_keys reads its own
        self.issued = {}         # party -> (Cert, signature)
        self.serials = {}        # party -> {serial: not_after}: every serial issued to it, until it expires
        self.revoked = set()
        self.barred = set()      # parties named in the revocations
        self.seq = 0             # the last status number published
        self.seq_reserved = 0    # no status number above it was published: saved in state()

    def set_keys(self, party, box_public, verify_public, now=0.0):
        """A party's public keys (read again every period); returns True if they changed (rotated)."""
        keys = (bytes(box_public), bytes(verify_public))
        old = self.keys.get(party)
        if old is None:   # the first read since a restart: changed while the CA was down?
            old = self.saved_keys.pop(party, None)
        self.keys[party] = keys
        if old is not None and old != keys:
            # Every certificate of the old key ends (a renewal may have made more than one).
            self.issued.pop(party, None)
            for serial in self.serials.get(party, ()):
                if serial not in self.revoked:
                    self.retiring.setdefault(serial, now + self.overlap)
            return True
        return False

    def state(self):
        """What must outlive a restart of the CA (JSON): the revoked serials, those being retired,
        the serials issued with their expiry, the keys certified and the status number reserved."""
        keys = dict(self.saved_keys, **self.keys)
        return {'revoked': sorted(self.revoked),
                'retiring': dict((str(k), v) for k, v in self.retiring.items()),
                'serials': dict((party, dict((str(s), t) for s, t in sorted(serials.items())))
                                for party, serials in self.serials.items() if serials),
                'keys': dict((party, [base64.b64encode(k).decode() for k in pair]) for party, pair in keys.items()),
                'seq': self.seq_reserved}

    def restore(self, state):
        """The state() a previous run saved (ValueError naming what is wrong if it is not one; nothing
        is taken then). ``serials``, ``keys`` and ``seq`` may be missing (a state saved before them)."""
        try:
            revoked = set(int(r) for r in state['revoked'])
            retiring = dict((int(k), float(v)) for k, v in state['retiring'].items())
        except (KeyError, TypeError, ValueError, AttributeError):
            raise ValueError('not a CA state (revoked, retiring): %r' % (state,))
        serials, keys = {}, {}
        for party, entries in _mapping(state.get('serials', {}), 'serials').items():
            for serial, not_after in _mapping(entries, 'serials of %s' % _state_name(party)).items():
                try:
                    serials.setdefault(party, {})[int(serial)] = float(not_after)
                except (TypeError, ValueError):
                    raise ValueError('serials of %s: the entry %r: %r is not a serial and its expiry'
                                     % (party, serial, not_after))
        for party, pair in _mapping(state.get('keys', {}), 'keys').items():
            party = _state_name(party)
            try:
                box, verify = (base64.b64decode(k, validate=True) for k in pair)
            except (TypeError, ValueError):
                box = verify = b''
            if len(box) != 32 or len(verify) != 32:
                raise ValueError('keys of %s: %r are not two base64 public keys' % (party, pair))
            keys[party] = (box, verify)
        seq = state.get('seq', 0)
        if not isinstance(seq, int) or isinstance(seq, bool) or seq < 0:
            raise ValueError('seq: %r is not a status number' % (seq,))
        self.revoked |= revoked
        self.retiring.update(retiring)
        for party, entries in serials.items():
            self.serials.setdefault(party, {}).update(entries)
        self.saved_keys.update(keys)
        self.seq = self.seq_reserved = max(self.seq, seq)

    def bar(self, parties):
        """The parties the revocations name now; returns those newly barred."""
        parties = set(parties)
        newly = parties - self.barred
        for party in parties:
            self.revoked.update(self.serials.get(party, ()))
            self.issued.pop(party, None)
        self.barred = parties
        return sorted(newly)

    def certificate(self, party, now):
        """(Cert, signature) for party, or Rejected (unknown_party, revoked)."""
        if party in self.barred:
            raise Rejected('revoked', 'party %s is revoked' % party)
        if party not in self.keys:
            raise Rejected('unknown_party', 'no certificate for party %r' % party)
        held = self.issued.get(party)
        if held is None or held[0].not_after - now < self.validity / 2.0:
            # Random serials: a restarted CA never gives a new certificate a serial revoked before.
            serial = secrets.randbits(63) | 1
            while serial in self.revoked or serial in self.retiring:
                serial = secrets.randbits(63) | 1
            box, verify = self.keys[party]
            cert = Cert(box, verify, serial, now + self.validity)
            held = (cert, certify(self.ca, party, box, verify, serial, cert.not_after))
            self.issued[party] = held
            self.serials.setdefault(party, {})[serial] = cert.not_after
        return held

    def status(self, now):
        """(ca_time, seq, revoked serials, signature): the next status to publish. The sequence
        number follows the CA's clock (milliseconds) and is above every one published before, a
        previous run's included (its reservation restored): a CA restarted after its clock stepped
        back still publishes statuses the gates take. Serials that expired are forgotten."""
        self.seq = max(self.seq + 1, int(now * 1000))
        if self.seq > self.seq_reserved:
            self.seq_reserved = self.seq + self.SEQ_RESERVE
        for serial, until in list(self.retiring.items()):
            if until <= now:
                self.revoked.add(serial)
                del self.retiring[serial]
        for party, serials in list(self.serials.items()):
            for serial in [s for s, not_after in serials.items() if not_after <= now]:
                del serials[serial]   # expired: no gate takes it any more, revoked or not
            if not serials:
                del self.serials[party]
        revoked = sorted(self.revoked)
        return now, self.seq, revoked, sign_status(self.ca, now, self.seq, revoked)


def _mapping(value, what):
    if not isinstance(value, dict):
        raise ValueError('%s: expected a mapping, got %r' % (what, value))
    return value


def _state_name(name):
    """name, if it is a party name (ValueError otherwise)."""
    if isinstance(name, str) and name and all(c.isalnum() or c in '_-' for c in name):
        return name
    raise ValueError('%r is not a party name' % (name,))


# -- messages -------------------------------------------------------------------------------------
# Every field of a request or reply that affects how it is processed is signed (issue 16: a replayed
# request with its unsigned ``attempt`` changed executed again; ``batch``, PBR's group commit, acted
# on by the After), and so are the party it is for (``to``), its direction (``dir``: request or
# reply) and its destination (``dest``: the service's request topic, as the gates name it), so
# that a request sealed for one service and copied to another's topic is refused there.
REQUEST_FIELDS = ('origin', 'id', 'client', 'service_type', 'oldest_pending', 'attempt', 'epoch', 'transfer',
                  'batch')
REPLY_FIELDS = ('origin', 'id', 'client', 'oldest_pending', 'attempt', 'status', 'error', 'epoch', 'batch')
DIRECTIONS = {REQUEST_FIELDS: 'request', REPLY_FIELDS: 'reply'}
MAX_SEALED_BYTES = 64 * 1024 * 1024   # a larger payload is refused unread (``malformed``)
_SEALED_TAG = b'aft-sealed-v2|'       # the ciphered plaintext: tag, sealer, '|', sha256(header), plaintext


def header_of(message, fields, to, destination=None):
    """The header to sign for ``message`` (any object with those attributes): its fields (arrays as
    lists, as JSON gives them back), ``to``, the party it is sealed for, ``dir``, its direction (for
    REQUEST_FIELDS and REPLY_FIELDS), and ``dest``, its destination, when given."""
    header = dict((name, _plain(getattr(message, name))) for name in fields)
    header['to'] = to
    direction = DIRECTIONS.get(tuple(fields))
    if direction is not None:
        header['dir'] = direction
    if destination is not None:
        header['dest'] = destination
    return header


def _plain(value):
    return list(value) if isinstance(value, (tuple, list)) else value


def _digest(header):
    return hashlib.sha256(json.dumps(header, sort_keys=True, separators=(',', ':')).encode()).digest()


def seal(sender, recipient_box_public, header, plaintext):
    """Cipher plaintext for the recipient and sign it with the header: bytes to put in a payload. The
    ciphered plaintext names the sender and the hash of the header: see open_sealed."""
    header = json.loads(json.dumps(header))   # as the recipient will read it
    inner = _SEALED_TAG + sender.name.encode() + b'|' + _digest(header) + bytes(plaintext)
    ciphertext = nacl.public.SealedBox(nacl.public.PublicKey(bytes(recipient_box_public))).encrypt(inner)
    content = json.dumps({'party': sender.name, 'header': header,
                          'ct': base64.b64encode(ciphertext).decode()}, sort_keys=True).encode()
    return sender.signing.sign(content)


def _parse(data):
    """The JSON object in data, or Rejected: too large or nested too deep (malformed), not one
    (unsigned)."""
    if len(data) > MAX_SEALED_BYTES:
        raise Rejected('malformed', 'the payload is %d bytes, more than a SEC message may be (%d)'
                       % (len(data), MAX_SEALED_BYTES))
    try:
        content = json.loads(data.decode())
    except RecursionError:
        raise Rejected('malformed', 'the payload is nested too deep to be a SEC message')
    except (ValueError, TypeError, UnicodeDecodeError):
        content = None
    if not isinstance(content, dict) or not isinstance(content.get('party'), str) \
            or not isinstance(content.get('header'), dict):
        raise Rejected('unsigned', 'the payload is not a signed SEC message')
    return content


def _claims(blob):
    """The (not yet verified) content of a sealed blob, or Rejected('unsigned', 'malformed')."""
    return _parse(bytes(blob)[SIGNATURE_BYTES:])


def sender_of(blob):
    """The party a sealed blob claims to come from (not verified yet)."""
    return _claims(blob)['party']


def addressee_of(blob):
    """The party a sealed blob claims to be for (its header's ``to``; not verified yet), or None."""
    to = _claims(blob)['header'].get('to')
    return to if isinstance(to, str) else None


def destination_of(blob):
    """The destination a sealed blob's header names (``dest``; not verified yet), or None."""
    dest = _claims(blob)['header'].get('dest')
    return dest if isinstance(dest, str) else None


def nonce_of(blob):
    """The nonce a sealed blob's header names (``nonce``; not verified yet), or None: the run of the
    client's gate that sealed a request, which its reply must name (see ReplyNonces)."""
    nonce = _claims(blob)['header'].get('nonce')
    return nonce if isinstance(nonce, str) else None


def challenge_of(blob):
    """The freshness challenge a sealed request's header answers (``challenge``; not verified yet), or
    None: see Freshness."""
    challenge = _claims(blob)['header'].get('challenge')
    return challenge if isinstance(challenge, str) else None


def new_nonce():
    """A client gate's nonce for one run: 128 random bits, as hex."""
    return secrets.token_hex(16)


def open_sealed(recipient, sender_verify_public, blob, header):
    """Verify the sender's signature, check the signed header against header (the envelope's, as
    header_of makes it), decipher, and check that the ciphertext was sealed by the signer under that
    very header (not kept from another message and signed again).

    A signed header without ``dest`` (a signer that names no destination) is taken for any: only a
    destination signed and different is refused. Raises Rejected: unsigned, malformed, bad_signature,
    misaddressed (another direction or destination), tampered (another header, or a ciphertext
    sealed by another party or under another header), undecryptable."""
    blob = bytes(blob)
    if len(blob) <= SIGNATURE_BYTES:
        raise Rejected('unsigned', 'the payload is not a signed SEC message')
    if len(blob) > MAX_SEALED_BYTES:
        _parse(blob)   # refused, unread
    try:
        content = nacl.signing.VerifyKey(bytes(sender_verify_public)).verify(blob)
    except nacl.exceptions.BadSignatureError:
        raise Rejected('bad_signature', 'the signature does not match the sender\'s certified key')
    message = _parse(content)
    signer, signed = message['party'], message['header']
    if signed.get('dir') != header.get('dir'):
        raise Rejected('misaddressed', 'party %s signed it as a %s, it came as a %s'
                       % (signer, signed.get('dir') or 'message of no direction', header.get('dir')))
    if 'dest' in header and signed.get('dest') != header['dest']:
        # A message signed for no destination could be taken by any service's gate: every gate signs
        # one, so none is taken (review of SEC, session 33: they were taken, and counted).
        raise Rejected('misaddressed', 'party %s signed it for %s, it came to %s'
                       % (signer, signed.get('dest') or 'no destination', header['dest']))
    expected = header if 'dest' in signed else dict((k, v) for k, v in header.items() if k != 'dest')
    if signed != expected:
        changed = sorted(k for k in set(signed) | set(expected) if signed.get(k) != expected.get(k))
        raise Rejected('tampered', 'field(s) %s: the envelope says %s but the header party %s signed says %s'
                       % (', '.join(changed), expected, signer, signed))
    try:
        inner = nacl.public.SealedBox(recipient.box_private).decrypt(base64.b64decode(message['ct']))
    except (nacl.exceptions.CryptoError, KeyError, ValueError, TypeError):
        raise Rejected('undecryptable', 'the payload was not ciphered for %s' % recipient.name)
    binding = _SEALED_TAG + signer.encode() + b'|' + _digest(signed)
    if not inner.startswith(binding):
        raise Rejected('tampered', 'party %s signed a ciphertext %s' % (signer, _sealer(inner, signer)))
    return inner[len(binding):]


def _sealer(inner, signer):
    """Who sealed a ciphered plaintext whose binding is not its signer's, for a refusal's detail."""
    if not inner.startswith(_SEALED_TAG):
        return 'that names no sealer (sealed by an older SEC, or re-signed)'
    name = inner[len(_SEALED_TAG):len(_SEALED_TAG) + 64].split(b'|', 1)[0].decode('ascii', 'replace')
    name = ''.join(c if c.isalnum() or c in '_-' else '?' for c in name)
    if name == signer:
        return 'it sealed under another header (kept from another message and signed again)'
    return 'sealed by party %s (kept from its message and signed again)' % name


ERROR_FRAME = b'AFTERR1'   # a sealed reply's plaintext: this mark, the error's length (4 bytes), the error, the payload


def frame_error(error, payload):
    """The plaintext of a reply sealed with its error text (review of SEC, session 33: the error went
    in clear, and a server's error names the client's data)."""
    text = (error or '').encode('utf-8')
    return ERROR_FRAME + struct.pack('>I', len(text)) + text + bytes(payload)


def unframe_error(plaintext):
    """(error, payload) of a reply's plaintext; (None, plaintext) if it carries no framed error.
    Rejected ('malformed') if the frame is cut."""
    plaintext = bytes(plaintext)
    if not plaintext.startswith(ERROR_FRAME):
        return None, plaintext
    start = len(ERROR_FRAME) + 4
    if len(plaintext) < start:
        raise Rejected('malformed', 'a sealed reply\'s error frame is cut')
    (length,) = struct.unpack('>I', plaintext[len(ERROR_FRAME):start])
    if len(plaintext) < start + length:
        raise Rejected('malformed', 'a sealed reply\'s error is cut (%d bytes said, %d there)'
                       % (length, len(plaintext) - start))
    try:
        error = plaintext[start:start + length].decode('utf-8')
    except UnicodeDecodeError:
        raise Rejected('malformed', 'a sealed reply\'s error is not UTF-8')
    return error, plaintext[start + length:]


class OriginBinding(object):
    """Which party may send requests as which origin (a Proxy's name): the reply to an origin is
    sealed for that party only, so a party sending as another's Proxy could otherwise read its
    replies and push its replay watermark to the end.

    ``allowed``: {party: [origin patterns (fnmatch)]}, from the policy file; None: no policy, and
    each origin is bound to the first party whose verified request used it (said in the log and the
    gate's diagnostics). Either way an origin bound to one party is refused to every other."""

    def __init__(self, allowed=None):
        self.allowed = allowed
        self.bound = {}   # origin -> party

    def bind(self, party, origin, keep=True):
        """The party that signed a request from origin: allowed, returns it (bound to it, unless not
        ``keep``: only checked); else Rejected."""
        if self.allowed is not None and not any(fnmatch.fnmatchcase(origin, pattern)
                                                for pattern in self.allowed.get(party, ())):
            raise Rejected('spoofed_origin', 'party %s may not send as %s (policy: %s)'
                           % (party, origin, ', '.join(self.allowed.get(party, ())) or 'no origin'))
        owner = self.bound.get(origin, party)
        if owner != party:
            raise Rejected('spoofed_origin', 'party %s sent as %s, which is bound to party %s' % (party, origin, owner))
        if keep:
            self.bound[origin] = party
        return party

    def party_of(self, origin):
        return self.bound.get(origin)


class ProxyRuns(object):
    """Client side: the nonce of each Proxy's run behind this gate. Within one run a Proxy never sends
    a request whose id is below an ``oldest_pending`` it sent (every id below it was answered); one
    that does is a new run (started again, its clock behind, using ids again): it gets a new nonce,
    so that a reply sealed for the earlier run is refused for it (review of session 34: the nonce was
    the gate's, and a Proxy started again alone kept it). (Not ``oldest_pending`` going down: two
    calls of one Proxy built and published in the other order do that within one run.)"""

    def __init__(self):
        self.runs = {}   # origin -> (nonce, the highest oldest_pending sent)

    def nonce_for(self, origin, request_id, oldest_pending):
        nonce, floor = self.runs.get(origin, (None, 0))
        if nonce is None or request_id < floor:
            nonce, floor = new_nonce(), oldest_pending
        self.runs[origin] = (nonce, max(floor, oldest_pending))
        return nonce

    def current(self, origin):
        return self.runs.get(origin, (None, 0))[0]


class ReplyNonces(object):
    """Server side: the nonce each pending request of an origin came with (its client gate's run), so
    that its reply is sealed for that run only. A Proxy started again with its clock behind uses ids
    again; without the nonce, an old sealed reply captured for such an id was accepted for the new
    call (review of SEC, session 33). Forgotten below the origin's oldest pending id, and at most
    ``per_origin`` ids kept per origin: the one noted longest ago goes first (its reply then names no
    nonce and the client's gate refuses it; the Proxy's re-send notes it again, newest). Evicting the
    lowest id instead evicted a slow call's again at each re-send: refused for good (review of session 34)."""

    def __init__(self, per_origin=4096):
        self.per_origin = per_origin
        self.by_origin = {}   # origin -> OrderedDict {id: nonce}, the one noted last at the end

    def note(self, origin, request_id, nonce, oldest_pending):
        ids = self.by_origin.setdefault(origin, collections.OrderedDict())
        for answered in [i for i in ids if i < oldest_pending]:
            del ids[answered]
        if nonce is not None:
            ids[request_id] = nonce
            ids.move_to_end(request_id)
        while len(ids) > self.per_origin:
            ids.popitem(last=False)

    def of(self, origin, request_id):
        return self.by_origin.get(origin, {}).get(request_id)


class ReplayGuard(object):
    """Per origin, every id below the newest watermark a verified request carried has been answered:
    a request with such an id is a replay. Re-sends of pending requests are not replays.

    ``restore()`` takes what an earlier run of the gate let through (aft_ftm.replay_log): its
    watermarks, and per origin the highest id it forwarded. An id at or below that one and not below
    the watermark was in flight when that run ended (or was the last its Proxy sent: only the next
    request's watermark confirms a reply): it may have executed, in a history this run cannot see.
    It is refused (``earlier_run``), never executed and never told to renumber (its outcome is
    unknown, not "not executed"). Its honest Proxy's call ends at its timeout, outcome unknown."""

    def __init__(self):
        self.watermarks = {}
        self.highest = {}     # origin -> the highest id of a verified request
        self.earlier = {}     # origin -> the highest id an earlier run of the gate let through

    def restore(self, floors):
        """floors: {origin: (watermark, highest)} of an earlier run."""
        for origin, (watermark, highest) in floors.items():
            self.watermarks[origin] = max(self.watermarks.get(origin, 0), watermark)
            self.highest[origin] = max(self.highest.get(origin, 0), highest)
            self.earlier[origin] = max(self.earlier.get(origin, 0), highest)

    def check(self, origin, request_id):
        if request_id < self.watermarks.get(origin, 0):
            raise Rejected('replay', 'request %s/%d was already answered (or its Proxy started again with a '
                                     'clock behind: it is told to number from %d on)'
                           % (origin, request_id, self.first_free(origin)))
        if origin in self.earlier and request_id <= self.earlier[origin]:
            raise Rejected('earlier_run', 'request %s/%d was let through by an earlier run of this gate (before '
                                          'it started again): it may have executed then; refused, not executed '
                                          'now, its outcome unknown' % (origin, request_id))

    def advance(self, origin, oldest_pending, request_id=0):
        self.watermarks[origin] = max(self.watermarks.get(origin, 0), oldest_pending)
        self.highest[origin] = max(self.highest.get(origin, 0), request_id)

    def learn(self, watermarks):
        """Take the watermarks another gate of this service holds (its peer's, at a join: see
        seal_floors), {origin: watermark}: every id below one was answered, wherever. Only watermarks
        are taken, never a highest id (a request in flight there is not a replay here), and only raised.
        Returns the origins whose watermark rose."""
        raised = []
        for origin, watermark in watermarks.items():
            if watermark > self.watermarks.get(origin, 0):
                self.watermarks[origin] = watermark
                raised.append(origin)
        return raised

    def floors(self, origin):
        """(watermark, highest) of origin now: what the replay log must hold before its request goes on."""
        return self.watermarks.get(origin, 0), self.highest.get(origin, 0)

    def first_free(self, origin):
        """The lowest id of origin above every one verified here: where a Proxy started again with its
        clock behind numbers from (a STALE_ID answer, aft_msgs/Reply)."""
        return max(self.watermarks.get(origin, 0), self.highest.get(origin, 0) + 1)


class Freshness(object):
    """Server side: per origin, whether a request signed during this run of the gate has come. Until
    one has, the gate's floors for that origin are only what its replay log and its peer said, and
    those can be behind: a log lost (deleted, moved, its gate renamed), or a site that was down while
    its peer served and is now first to serve again after a restart of the whole service. Every
    request its Proxy sent meanwhile, replayed, would pass. So the first request of each origin in a
    run is asked to prove it is fresh: the gate answers it with a challenge (a nonce of this run,
    sealed for the party that signed it, aft_msgs/Reply CHALLENGE), and only a request whose signed
    header names that nonce is taken. A client gate answers for a request it has pending (it seals
    it again with the nonce); a replay, whose signer is not asked, never answers. The first request
    that answers and is let through confirms the origin, and its signed ``oldest_pending`` raises the
    watermark: every older replay is then refused as ``replay``. (Ids at or above it are taken as in
    flight, as always: a Proxy with calls outstanding across the restart leaves the ids it had answered
    above its oldest pending one to the Protocol's reply cache.)

    At most ``limit`` origins are asked and not yet confirmed: beyond, the one asked longest ago is
    asked again afresh if it comes back (a flood of one-shot origins grows nothing for ever)."""

    def __init__(self, ask=True, limit=100000):
        self.ask = ask
        self.limit = limit
        self.asked = collections.OrderedDict()   # origin -> [nonce, when first asked, told]; unconfirmed only
        self.confirmed = {}                       # origin -> the nonce it answered
        self.sent = 0                             # challenges sent

    def check(self, origin, challenge, now):
        """None if a request of origin naming challenge may go on (the origin confirmed in this run, or
        the request answers its challenge: confirm() it once it is let through); otherwise the
        challenge to answer it with."""
        if not self.ask or origin in self.confirmed:
            return None
        asked = self.asked.get(origin)
        if asked is not None and challenge == asked[0]:
            return None
        if asked is None:
            asked = self.asked[origin] = [new_nonce(), now, False]
            while len(self.asked) > self.limit:
                self.asked.popitem(last=False)
        self.sent += 1
        return asked[0]

    def confirm(self, origin):
        """origin's request that answered its challenge was let through (its watermark taken): confirmed
        for the rest of the run. Only then: confirmed before, a request the party's quota then refused
        left the watermark behind with the origin taken as fresh (review of session 48)."""
        asked = self.asked.pop(origin, None)
        if self.ask and asked is not None:
            self.confirmed[origin] = asked[0]

    def unanswered(self, now, wait):
        """The origins first asked more than wait s ago and not confirmed since, each once: (origin, s)."""
        late = []
        for origin, asked in self.asked.items():
            if not asked[2] and now - asked[1] > wait:
                asked[2] = True
                late.append((origin, now - asked[1]))
        return late


MAX_FLOOR_ORIGINS = 1000000   # a larger floors answer is refused (``malformed``)


def floors_header(party, nonce):
    """The header a server gate's floors answer is signed with: sealed by and for its own party
    (both sites' gates), naming the asker's nonce."""
    return {'dir': 'floors', 'nonce': nonce, 'to': party}


def seal_floors(me, watermarks, nonce):
    """A server gate's replay watermarks ({origin: watermark}) for its peer's gate, which asked with
    nonce: ciphered for this gate's own party and signed by it (a peer's gate is the same party)."""
    plaintext = json.dumps(sorted([origin, int(mark)] for origin, mark in watermarks.items() if mark > 0),
                           separators=(',', ':')).encode()
    return seal(me, me.box_public, floors_header(me.name, nonce), plaintext)


def read_floors(plaintext):
    """{origin: watermark} of an opened floors answer; Rejected ('malformed') if it is not a list of
    [origin, watermark] pairs (a name, an integer >= 0), at most MAX_FLOOR_ORIGINS of them."""
    try:
        pairs = json.loads(bytes(plaintext).decode())
    except (ValueError, UnicodeDecodeError, RecursionError):
        pairs = None
    if not isinstance(pairs, list) or len(pairs) > MAX_FLOOR_ORIGINS:
        raise Rejected('malformed', 'a floors answer is not a list of at most %d [origin, watermark] pairs'
                       % MAX_FLOOR_ORIGINS)
    out = {}
    for pair in pairs:
        if not (isinstance(pair, list) and len(pair) == 2 and isinstance(pair[0], str) and pair[0]
                and isinstance(pair[1], int) and not isinstance(pair[1], bool) and 0 <= pair[1] < 2 ** 64):
            raise Rejected('malformed', 'a floors answer holds %r: not an [origin, watermark] pair' % (pair,))
        out[pair[0]] = max(out.get(pair[0], 0), pair[1])
    return out


class PartyQuota(object):
    """Server side: the requests each party has outstanding (ids at or above their origin's oldest
    pending, whose replies the Protocol must keep), at most ``limit`` per party (0: no bound, nothing
    tracked). An origin is tracked only while it has one outstanding, so a party's origins tracked are
    bounded by its quota too. The caller binds each origin to one party first (OriginBinding), so an
    origin's ids always count for the party that sends them.

    The Protocol's reply cache is shared: at its bound it refuses every new request, of every client
    (README, Limits of session 33). A certified insider sending many ids it never confirms, from one
    origin or from many one-shot ones, filled it and denied service to all. Past its quota a party's new
    ids are refused here (``party_quota``) and dropped, not answered: its Proxy sends them again, and
    they pass once its older calls are confirmed (a refusal answered "not executed" would have to be
    remembered, so that a copy is not executed later, and that memory is what the flood grows).
    Re-sends of an id counted already always pass. The other parties keep their quotas: with
    ``parties x limit`` within the cache's bound, no party can fill it. A request whose id is below its
    origin's oldest pending (the Protocol drops it as a late copy) is not counted; one below an oldest
    pending admitted before is a replay, refused earlier (security.ReplayGuard).

    Only an admitted request moves its origin's floor (its oldest pending, which the Protocol then
    learns too): a refused one changes nothing. Its floor moved the quota's count away from the
    Protocol's cache (review of session 35: ids below it then passed uncounted, 503 against a quota of 3).
    A party refused is told (``first``) at its first refusal, and again only after it had room and
    ``retell`` seconds passed."""

    def __init__(self, limit=10000, clock=None, retell=10.0):
        self.limit = limit
        self.clock = clock or (lambda: 0.0)
        self.retell = retell
        self.ids = {}      # origin -> set of outstanding ids
        self.heaps = {}    # origin -> min-heap of the same ids (the lowest forgotten first)
        self.floors = {}   # origin -> the highest oldest_pending admitted from it (while it has ids)
        self.count = collections.Counter()     # party -> outstanding ids over all its origins
        self.full = set()  # parties refused since they last had room
        self.told = {}     # party -> when it was last told

    def admit(self, party, origin, request_id, oldest_pending):
        """Count request ``request_id`` of ``origin`` for ``party``, once; raises Rejected
        ``party_quota`` if the party holds ``limit`` ids already, changing nothing. Its ``first`` says
        whether to raise an alarm for it."""
        if not self.limit:
            return
        floor = max(self.floors.get(origin, 0), oldest_pending)
        ids, heap = self.ids.get(origin, set()), self.heaps.get(origin, [])
        confirmed = []
        while heap and heap[0] < floor:   # confirmed by this request: forgotten only if it is admitted
            confirmed.append(heapq.heappop(heap))
        fresh = request_id >= floor and request_id not in ids
        count = self.count[party] - len(confirmed) + (1 if fresh else 0)
        if fresh and count > self.limit:
            for i in confirmed:
                heapq.heappush(heap, i)
            error = Rejected('party_quota', 'party %s has %d requests outstanding (its quota): %s/%d is dropped '
                             'until its older calls are confirmed' % (party, self.count[party], origin, request_id))
            now = self.clock()
            error.first = party not in self.full and now - self.told.get(party, -self.retell) >= self.retell
            if error.first:
                self.told[party] = now
            self.full.add(party)
            raise error
        for i in confirmed:
            ids.discard(i)
        if fresh:
            ids.add(request_id)
            heapq.heappush(heap, request_id)
        if count:
            self.count[party] = count
        else:
            self.count.pop(party, None)
        if ids:
            self.ids[origin], self.heaps[origin], self.floors[origin] = ids, heap, floor
        else:   # nothing outstanding: forgotten (its replays are ReplayGuard's), so that it costs nothing here
            for table in (self.ids, self.heaps, self.floors):
                table.pop(origin, None)
        if count < self.limit:
            self.full.discard(party)   # room again

    def at_quota(self):
        """The parties refused since they last had room."""
        return sorted(self.full)
