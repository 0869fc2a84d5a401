"""SEC: cipher and signature of requests and replies, with a certification authority (paper
section 5.3.2). Built on PyNaCl (libsodium): SealedBox (X25519 + XSalsa20-Poly1305) ciphers a
payload for its recipient, Ed25519 signs it for its sender; the CA signs each party's public keys.

Nothing here logs or returns key material in error messages.
"""
import base64
import fnmatch
import json
import os

import nacl.exceptions
import nacl.public
import nacl.signing

from .errors import AftError, ConfigError

SIGNATURE_BYTES = 64


class Rejected(AftError):
    """A message refused by SEC. ``kind``: unsigned, bad_signature, unknown_party, tampered, replay,
    undecryptable, misaddressed (signed for another party), spoofed_origin (a party sending as a
    Proxy that is not its own)."""

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
    private = os.path.join(directory, party.name + '.key')
    fd = os.open(private, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, 'w') as f:
        json.dump({'box': base64.b64encode(bytes(party.box_private)).decode(),
                   'sign': base64.b64encode(bytes(party.signing)).decode()}, f)
    with open(os.path.join(directory, party.name + '.pub'), 'w') as f:
        json.dump({'box': base64.b64encode(party.box_public).decode(),
                   'verify': base64.b64encode(party.verify_public).decode()}, f)


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
def _certificate_content(name, box_public, verify_public):
    return b'aft-cert-v1|' + name.encode() + b'|' + box_public + verify_public


def certify(ca, name, box_public, verify_public):
    """The CA's signature over a party's public keys."""
    return ca.signing.sign(_certificate_content(name, box_public, verify_public)).signature


def check_certificate(ca_verify_public, name, box_public, verify_public, signature):
    """Raise Rejected('bad_certificate') unless the CA signed these keys for this name."""
    try:
        nacl.signing.VerifyKey(bytes(ca_verify_public)).verify(
            _certificate_content(name, bytes(box_public), bytes(verify_public)), bytes(signature))
    except (nacl.exceptions.BadSignatureError, ValueError, TypeError):
        raise Rejected('bad_certificate', 'the certificate of %s is not signed by the CA' % name)


# -- messages -------------------------------------------------------------------------------------
# Every field of a request or reply that affects how it is processed is signed (issue 16: a replayed
# request with its unsigned ``attempt`` changed executed again), and so is the party it is for.
REQUEST_FIELDS = ('origin', 'id', 'client', 'service_type', 'oldest_pending', 'attempt', 'epoch', 'transfer')
REPLY_FIELDS = ('origin', 'id', 'client', 'oldest_pending', 'attempt', 'status', 'error', 'epoch')


def header_of(message, fields, to):
    """The header to sign for ``message`` (any object with those attributes): its fields, and ``to``,
    the party it is sealed for."""
    header = dict((name, getattr(message, name)) for name in fields)
    header['to'] = to
    return header


def seal(sender, recipient_box_public, header, plaintext):
    """Cipher plaintext for the recipient and sign it with the header: bytes to put in a payload."""
    ciphertext = nacl.public.SealedBox(nacl.public.PublicKey(bytes(recipient_box_public))).encrypt(bytes(plaintext))
    content = json.dumps({'party': sender.name, 'header': header,
                          'ct': base64.b64encode(ciphertext).decode()}, sort_keys=True).encode()
    return sender.signing.sign(content)


def _claims(blob):
    """The (not yet verified) content of a sealed blob, or Rejected('unsigned')."""
    try:
        content = json.loads(bytes(blob)[SIGNATURE_BYTES:].decode())
    except (ValueError, TypeError, UnicodeDecodeError):
        content = None
    if not isinstance(content, dict) or not isinstance(content.get('party'), str) \
            or not isinstance(content.get('header'), dict):
        raise Rejected('unsigned', 'the payload is not a signed SEC message')
    return content


def sender_of(blob):
    """The party a sealed blob claims to come from (not verified yet)."""
    return _claims(blob)['party']


def addressee_of(blob):
    """The party a sealed blob claims to be for (its header's ``to``; not verified yet), or None."""
    to = _claims(blob)['header'].get('to')
    return to if isinstance(to, str) else None


def open_sealed(recipient, sender_verify_public, blob, header):
    """Verify the sender's signature, check the signed header equals header, decipher.

    Raises Rejected: bad_signature, tampered (header changed), undecryptable."""
    blob = bytes(blob)
    if len(blob) <= SIGNATURE_BYTES:
        raise Rejected('unsigned', 'the payload is not a signed SEC message')
    try:
        content = nacl.signing.VerifyKey(bytes(sender_verify_public)).verify(blob)
    except nacl.exceptions.BadSignatureError:
        raise Rejected('bad_signature', 'the signature does not match the sender\'s certified key')
    message = json.loads(content.decode())
    if message.get('header') != header:
        raise Rejected('tampered', 'the envelope says %s but the signed header says %s'
                       % (header, message.get('header')))
    try:
        return nacl.public.SealedBox(recipient.box_private).decrypt(base64.b64decode(message['ct']))
    except (nacl.exceptions.CryptoError, KeyError, ValueError, TypeError):
        raise Rejected('undecryptable', 'the payload was not ciphered for %s' % recipient.name)


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

    def bind(self, party, origin):
        """The party that signed a request from origin: allowed, returns it; else Rejected."""
        if self.allowed is not None and not any(fnmatch.fnmatchcase(origin, pattern)
                                                for pattern in self.allowed.get(party, ())):
            raise Rejected('spoofed_origin', 'party %s may not send as %s (policy: %s)'
                           % (party, origin, ', '.join(self.allowed.get(party, ())) or 'no origin'))
        owner = self.bound.setdefault(origin, party)
        if owner != party:
            raise Rejected('spoofed_origin', 'party %s sent as %s, which is bound to party %s' % (party, origin, owner))
        return party

    def party_of(self, origin):
        return self.bound.get(origin)


class ReplayGuard(object):
    """Per origin, every id below the newest watermark a verified request carried has been answered:
    a request with such an id is a replay. Re-sends of pending requests are not replays."""

    def __init__(self):
        self.watermarks = {}

    def check(self, origin, request_id):
        if request_id < self.watermarks.get(origin, 0):
            raise Rejected('replay', 'request %s/%d was already answered' % (origin, request_id))

    def advance(self, origin, oldest_pending):
        self.watermarks[origin] = max(self.watermarks.get(origin, 0), oldest_pending)
