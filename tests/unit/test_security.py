"""SEC's checks, table-driven: each kind of bad message rejected, naming why. No ROS."""
import json
import os
import stat

import pytest

from aft_ftm import security
from aft_ftm.errors import ConfigError
from aft_ftm.security import Party, Rejected

CLIENT, SERVER, CA, MALLORY = (Party.generate(n) for n in ('client', 'server', 'ca', 'client'))
HEADER = {'origin': '/proxy', 'id': 7, 'oldest_pending': 7, 'service_type': 'aft_msgs/Account'}


def sealed(sender=CLIENT, header=HEADER, plaintext=b'deposit 10'):
    return security.seal(sender, SERVER.box_public, header, plaintext)


def flip_in_ciphertext(blob):
    data = bytearray(blob)
    at = bytes(data).index(b'"ct": "') + 12
    data[at] = ord('A') if data[at] != ord('A') else ord('B')
    return bytes(data)


def test_round_trip_and_the_wire_does_not_show_the_plaintext():
    blob = sealed()
    assert b'deposit' not in blob
    assert security.sender_of(blob) == 'client'
    assert security.open_sealed(SERVER, CLIENT.verify_public, blob, HEADER) == b'deposit 10'


@pytest.mark.parametrize('blob,header,recipient,kind', [
    (flip_in_ciphertext(sealed()), HEADER, SERVER, 'bad_signature'),          # altered ciphertext
    (sealed(), dict(HEADER, id=8), SERVER, 'tampered'),                       # envelope changed
    (sealed(sender=MALLORY), HEADER, SERVER, 'bad_signature'),                # signed with a wrong key
    (b'plain request bytes', HEADER, SERVER, 'unsigned'),
    (b'', HEADER, SERVER, 'unsigned'),
    (sealed(), HEADER, CLIENT, 'undecryptable'),                              # not ciphered for this party
])
def test_bad_messages_are_rejected_with_their_kind(blob, header, recipient, kind):
    with pytest.raises(Rejected) as error:
        security.open_sealed(recipient, CLIENT.verify_public, blob, header)
    assert error.value.kind == kind


def test_unsigned_payload_has_no_sender():
    with pytest.raises(Rejected, match='unsigned'):
        security.sender_of(b'x' * 100)


def test_replay_of_an_answered_request_is_rejected_but_a_resend_of_a_pending_one_is_not():
    guard = security.ReplayGuard()
    guard.check('/proxy', 5)
    guard.advance('/proxy', 5)          # ids below 5 were answered
    guard.check('/proxy', 5)            # pending: a re-send, answered from the duplicate cache
    guard.check('/other', 1)            # another Proxy has its own ids
    with pytest.raises(Rejected, match='replay: request /proxy/4 was already answered'):
        guard.check('/proxy', 4)
    guard.advance('/proxy', 3)          # a watermark never goes back
    with pytest.raises(Rejected):
        guard.check('/proxy', 4)


def test_certificates_bind_a_name_to_its_keys_serial_and_expiry():
    signature = security.certify(CA, 'server', SERVER.box_public, SERVER.verify_public, 7, 1000.0)
    cert = security.check_certificate(CA.verify_public, 'server', SERVER.box_public, SERVER.verify_public, 7,
                                      1000.0, signature)
    assert (cert.serial, cert.not_after, cert.verify_public) == (7, 1000.0, SERVER.verify_public)
    for name, box, verify, serial, not_after in [
            ('client', SERVER.box_public, SERVER.verify_public, 7, 1000.0),      # another name
            ('server', MALLORY.box_public, SERVER.verify_public, 7, 1000.0),     # another key
            ('server', SERVER.box_public, SERVER.verify_public, 8, 1000.0),      # another serial
            ('server', SERVER.box_public, SERVER.verify_public, 7, 10 ** 9)]:    # a longer life
        with pytest.raises(Rejected, match='bad_certificate'):
            security.check_certificate(CA.verify_public, name, box, verify, serial, not_after, signature)
    forged = security.certify(MALLORY, 'server', MALLORY.box_public, MALLORY.verify_public, 7, 1000.0)
    with pytest.raises(Rejected, match='not signed by the CA'):
        security.check_certificate(CA.verify_public, 'server', MALLORY.box_public, MALLORY.verify_public, 7, 1000.0,
                                   forged)


def fetch(issuer, book, party, ca_time, now):
    """What a gate does: ask the CA (the Issuer), check the answer, hold it in its book."""
    cert, signature = issuer.certificate(party, ca_time)
    checked = security.check_certificate(CA.verify_public, party, cert.box_public, cert.verify_public, cert.serial,
                                         cert.not_after, signature)
    return book.add(party, checked, now)


def test_a_revoked_party_is_dropped_by_the_next_status_and_refused_by_the_ca():
    issuer = security.Issuer(CA, validity=100.0)
    issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public)
    book = security.CertificateBook(CA.verify_public, silent_after=3.0)
    assert book.on_status(*issuer.status(5000.0), now=10.0) == []
    cert = fetch(issuer, book, 'client', 5000.0, 10.0)
    assert book.get('client', 10.5) == cert
    assert issuer.bar(['client']) == ['client']
    assert book.get('client', 10.6) == cert                  # until the status says so
    assert book.on_status(*issuer.status(5000.7), now=10.7) == ['client']
    assert book.get('client', 10.7) is None
    with pytest.raises(Rejected, match='revoked'):
        issuer.certificate('client', 5000.8)
    with pytest.raises(Rejected, match='is revoked'):       # a certificate kept from before: refused too
        book.add('client', cert, 10.8)
    issuer.bar([])                                           # named no more: a new certificate, a new serial
    assert book.on_status(*issuer.status(5001.0), now=11.0) == []
    again = fetch(issuer, book, 'client', 5001.0, 11.0)
    assert again.serial != cert.serial
    with pytest.raises(Rejected, match='is revoked'):       # the old serial stays revoked
        book.add('client', cert, 11.0)


def test_expiry_is_judged_in_the_cas_time_carried_by_the_gates_own_clock():
    issuer = security.Issuer(CA, validity=100.0)
    issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public)
    book = security.CertificateBook(CA.verify_public)
    book.on_status(*issuer.status(5000.0), now=1.0e6)        # the gate's monotonic clock is unrelated
    cert = fetch(issuer, book, 'client', 5000.0, 1.0e6)
    assert cert.not_after == 5100.0
    assert book.get('client', 1.0e6 + 99.9) == cert
    assert book.get('client', 1.0e6 + 100.1) is None         # CA time 5100.1: expired
    with pytest.raises(Rejected, match='expired'):
        book.add('client', cert, 1.0e6 + 100.1)
    renewed = fetch(issuer, book, 'client', 5060.0, 1.0e6 + 60.0)   # past half its life: a new one
    assert renewed.serial != cert.serial and renewed.not_after == 5160.0


def test_a_status_not_signed_by_the_ca_or_replayed_is_refused_and_changes_nothing():
    issuer = security.Issuer(CA, validity=100.0)
    book = security.CertificateBook(CA.verify_public, silent_after=3.0)
    assert book.silent(0.0) == float('inf')
    first = issuer.status(5000.0)
    issuer.revoked.add(99)
    second = issuer.status(5001.0)
    book.on_status(*second, now=2.0)
    with pytest.raises(Rejected, match='stale_status'):
        book.on_status(*first, now=3.0)                       # an older status replayed (99 not revoked in it)
    assert book.revoked == {99}
    ca_time, seq, revoked, _ = issuer.status(5002.0)
    forged = security.sign_status(MALLORY, ca_time, seq, [])
    with pytest.raises(Rejected, match='bad_signature'):
        book.on_status(ca_time, seq, [], forged, now=4.0)
    with pytest.raises(Rejected, match='bad_signature'):     # the CA's signature on other revocations
        book.on_status(ca_time, seq, [], issuer.status(5003.0)[3], now=4.0)
    assert book.revoked == {99} and book.silent(4.0) is None and book.silent(6.0) == pytest.approx(4.0)


def test_a_rotated_key_gets_a_new_certificate_and_the_old_one_ends_after_the_overlap():
    issuer = security.Issuer(CA, validity=100.0, overlap=10.0)
    issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public, now=0.0)
    book = security.CertificateBook(CA.verify_public)
    book.on_status(*issuer.status(0.0), now=0.0)
    old = fetch(issuer, book, 'client', 0.0, 0.0)
    assert issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public, now=1.0) is False   # unchanged
    fresh = Party.generate('client')
    assert issuer.set_keys('client', fresh.box_public, fresh.verify_public, now=2.0) is True
    new = fetch(issuer, book, 'client', 2.5, 0.5)
    assert new.verify_public == fresh.verify_public and new.serial != old.serial
    # During the overlap a gate holds both, newest first: a message signed with either key is taken.
    book.on_status(*issuer.status(5.0), now=5.0)
    assert book.candidates('client', 5.0) == [new, old]
    book.on_status(*issuer.status(12.5), now=12.5)       # overlap over: the old serial revoked
    assert old.serial in issuer.revoked and new.serial not in issuer.revoked
    assert book.candidates('client', 12.5) == [new]
    with pytest.raises(Rejected, match='unknown_party'):
        issuer.certificate('nobody', 1.0)


def test_key_files_are_replaced_whole(tmp_path):
    security.write_party(str(tmp_path), CLIENT)
    fresh = Party.generate('client')
    security.write_party(str(tmp_path), fresh)
    assert security.read_public(str(tmp_path), 'client') == (fresh.box_public, fresh.verify_public)
    assert security.read_party(str(tmp_path), 'client').verify_public == fresh.verify_public
    assert sorted(os.listdir(str(tmp_path))) == ['client.key', 'client.pub']


def test_the_revocations_file_is_read_or_refused_naming_the_problem(tmp_path):
    from aft_ftm import sec_policy
    path = tmp_path / 'revoked.yaml'
    assert sec_policy.load_revocations(str(path)) == []          # no file: nobody revoked
    path.write_text('revoked: [client2]\n')
    assert sec_policy.load_revocations(str(path)) == ['client2']
    path.write_text('')
    assert sec_policy.load_revocations(str(path)) == []
    for text in ('revoked: client2\n', 'parties: [a]\n', 'revoked: [1]\n', '[a, b]\n', 'revoked: [\n'):
        path.write_text(text)
        with pytest.raises(ConfigError) as error:
            sec_policy.load_revocations(str(path))
        assert str(path) in str(error.value)


def test_key_files_private_ones_readable_by_the_owner_only(tmp_path):
    security.write_party(str(tmp_path), SERVER)
    mode = stat.S_IMODE(os.stat(tmp_path / 'server.key').st_mode)
    assert mode == 0o600
    again = security.read_party(str(tmp_path), 'server')
    assert again.box_public == SERVER.box_public and again.verify_public == SERVER.verify_public
    assert security.read_public(str(tmp_path), 'server') == (SERVER.box_public, SERVER.verify_public)
    assert 'server' in repr(again) and json.load(open(tmp_path / 'server.key'))['box'] not in repr(again)


@pytest.mark.parametrize('content', ['not json', '{"box": "AAAA"}', '{"box": "%%%", "sign": "x"}'])
def test_malformed_key_files_are_named_and_their_content_is_not_shown(tmp_path, content):
    (tmp_path / 'server.key').write_text(content)
    with pytest.raises(ConfigError) as error:
        security.read_party(str(tmp_path), 'server')
    assert 'server.key' in str(error.value) and content not in str(error.value)


@pytest.mark.parametrize('name', ['', '../etc/passwd', 'a b'])
def test_party_names_cannot_escape_the_key_directory(tmp_path, name):
    with pytest.raises(ConfigError, match='party name'):
        security.read_party(str(tmp_path), name)


class Msg(object):
    """A request or reply's fields (the gate signs what security.header_of takes from it)."""

    def __init__(self, **fields):
        self.__dict__.update(fields)


REQUEST = Msg(origin='/proxy', id=7, client='/bank_client', service_type='aft_msgs/Account', oldest_pending=7,
              attempt=0, epoch=3, transfer=0, batch=(0, 0))
REPLY = Msg(origin='/proxy', id=7, client='/bank_client', oldest_pending=7, attempt=0, status=0, error='', epoch=3,
            batch=(0, 0))


def changed(value):
    """Another value of a header field's type."""
    if isinstance(value, (tuple, list)):
        return type(value)(v + 1 for v in value)
    return value + 1 if isinstance(value, int) else value + 'x'


@pytest.mark.parametrize('fields,message', [(security.REQUEST_FIELDS, REQUEST), (security.REPLY_FIELDS, REPLY)])
def test_every_field_that_affects_processing_is_signed(fields, message):
    """A captured message re-sent with any one field changed (attempt, epoch, client, ...) is refused:
    the replay of issue 16 changed the unsigned attempt and executed again."""
    blob = sealed(header=security.header_of(message, fields, 'server'))
    assert security.open_sealed(SERVER, CLIENT.verify_public, blob,
                                security.header_of(message, fields, 'server')) == b'deposit 10'
    for name in fields:
        value = getattr(message, name)
        other = Msg(**dict(message.__dict__, **{name: changed(value)}))
        with pytest.raises(Rejected) as error:
            security.open_sealed(SERVER, CLIENT.verify_public, blob, security.header_of(other, fields, 'server'))
        assert error.value.kind == 'tampered', name
    # and the party it is for: sealed for the server, presented as for another party
    with pytest.raises(Rejected, match='tampered'):
        security.open_sealed(SERVER, CLIENT.verify_public, blob, security.header_of(message, fields, 'client2'))


def test_the_addressee_and_sender_are_read_before_verifying_and_garbage_is_unsigned():
    blob = sealed(header=security.header_of(REPLY, security.REPLY_FIELDS, 'client2'))
    assert security.addressee_of(blob) == 'client2' and security.sender_of(blob) == 'client'
    assert security.addressee_of(sealed()) is None              # a header without 'to'
    weird = CLIENT.signing.sign(json.dumps({'party': ['a', 'list'], 'header': {}}).encode())
    for blob in (weird, CLIENT.signing.sign(b'[1, 2]'), CLIENT.signing.sign(b'{"party": "client"}')):
        with pytest.raises(Rejected, match='unsigned'):
            security.sender_of(blob)


def test_an_origin_is_bound_to_one_party_by_the_policy_or_by_its_first_signer():
    policy = security.OriginBinding({'client': ['/proxy', '/proxy?'], 'client2': ['/kiosk'], 'server': []})
    assert policy.bind('client', '/proxy') == 'client' and policy.bind('client', '/proxy2') == 'client'
    assert policy.bind('client2', '/kiosk') == 'client2' and policy.party_of('/kiosk') == 'client2'
    for party, origin in (('client2', '/proxy'), ('client', '/kiosk'), ('server', '/proxy'), ('mallory', '/proxy'),
                          ('client', '/proxy12')):
        with pytest.raises(Rejected) as error:
            policy.bind(party, origin)
        assert error.value.kind == 'spoofed_origin' and party in error.value.detail
    assert policy.party_of('/proxy') == 'client'               # refusals changed nothing
    open_binding = security.OriginBinding()
    assert open_binding.bind('client', '/proxy') == 'client'
    with pytest.raises(Rejected, match='bound to party client'):
        open_binding.bind('client2', '/proxy')
    assert open_binding.bind('client2', '/kiosk') == 'client2'


def test_the_policy_file_is_read_or_refused_naming_the_problem(tmp_path):
    from aft_ftm import sec_policy
    good = tmp_path / 'policy.yaml'
    good.write_text('parties:\n  client:\n    origins: ["/proxy", "/proxy?"]\n  server: {}\n  kiosk:\n')
    assert sec_policy.load(str(good)) == {'client': ['/proxy', '/proxy?'], 'server': [], 'kiosk': []}
    for text, words in [('parties: [client]\n', 'exactly one key, parties'),
                        ('parties: {}\nextra: 1\n', 'exactly one key, parties'),
                        ('parties:\n  client:\n    origins: proxy\n', 'origins must be a list'),
                        ('parties:\n  client:\n    origins: [proxy]\n', 'starting with /'),
                        ('parties:\n  client:\n    topics: [/a]\n', 'unknown key(s) topics'),
                        ('parties:\n  ../x: {}\n', 'not a party name'),
                        ('parties:\n  client: [/proxy]\n', 'expected a mapping'),
                        ('parties: {client: [\n', 'is not YAML')]:
        bad = tmp_path / 'bad.yaml'
        bad.write_text(text)
        with pytest.raises(ConfigError) as error:
            sec_policy.load(str(bad))
        assert str(bad) in str(error.value) and words in str(error.value), (text, str(error.value))
    with pytest.raises(ConfigError, match='cannot be read'):
        sec_policy.load(str(tmp_path / 'missing.yaml'))


def test_sec_keygen_rotates_a_partys_keys_and_refuses_the_ca_or_an_unknown_party(tmp_path):
    import subprocess
    import sys
    tool = os.path.join(os.path.dirname(__file__), '..', '..', 'catkin_ws', 'src', 'aft_ftm', 'nodes', 'sec_keygen')

    def run(*args):
        return subprocess.run([sys.executable, tool] + list(args), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              universal_newlines=True)
    assert run(str(tmp_path), 'client').returncode == 0
    before = security.read_public(str(tmp_path), 'client')
    ca = security.read_public(str(tmp_path), 'ca')
    done = run('--rotate', str(tmp_path), 'client')
    assert done.returncode == 0 and 'client: rotated' in done.stdout
    assert security.read_public(str(tmp_path), 'client') != before and security.read_public(str(tmp_path), 'ca') == ca
    for args, words in [(('--rotate', str(tmp_path), 'ca'), "CA's key is not rotated"),
                        (('--rotate', str(tmp_path), 'ghost'), 'ghost has no key')]:
        refused = run(*args)
        assert refused.returncode == 2 and words in refused.stdout


def test_a_rotation_ends_every_certificate_of_the_old_key_a_renewal_made_too():
    issuer = security.Issuer(CA, validity=100.0, overlap=10.0)
    issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public, now=0.0)
    first, _ = issuer.certificate('client', 0.0)
    renewed, _ = issuer.certificate('client', 60.0)           # past half its life: a second serial, same key
    assert renewed.serial != first.serial
    fresh = Party.generate('client')
    issuer.set_keys('client', fresh.box_public, fresh.verify_public, now=61.0)
    issuer.status(72.0)
    assert {first.serial, renewed.serial} <= issuer.revoked


def test_a_restarted_ca_keeps_its_revocations_and_its_status_stays_newer():
    issuer = security.Issuer(CA, validity=100.0)
    issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public)
    old, _ = issuer.certificate('client', 1000.0)
    issuer.bar(['client'])
    book = security.CertificateBook(CA.verify_public)
    book.on_status(*issuer.status(1001.0), now=1.0)
    saved = json.loads(json.dumps(issuer.state()))
    again = security.Issuer(CA, validity=100.0)               # the CA restarted, the party allowed again
    again.restore(saved)
    again.set_keys('client', CLIENT.box_public, CLIENT.verify_public)
    assert book.on_status(*again.status(1002.0), now=2.0) == []   # newer than before the restart
    new, _ = again.certificate('client', 1002.0)
    assert new.serial != old.serial and old.serial in again.revoked
    with pytest.raises(ValueError):
        again.restore({'revoked': 'x'})


def test_a_certificate_fetched_again_keeps_the_held_one_as_the_previous():
    issuer = security.Issuer(CA, validity=100.0)
    issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public)
    book = security.CertificateBook(CA.verify_public)
    book.on_status(*issuer.status(0.0), now=0.0)
    held = fetch(issuer, book, 'client', 0.0, 0.0)
    book.fetch_again('client')
    assert book.get('client', 0.0) is None and book.candidates('client', 0.0) == [held]
    book.fetch_again('nobody')                               # none held: nothing changes
    assert 'nobody' not in book.previous


# -- the review of the SEC mechanism: each test fails on the code before its fix -----------------------
CLIENT2 = Party.generate('client2')   # a certified insider (the policy gives it its own Proxy only)


def resigned(blob, signer, header):
    """What an insider does with a captured blob: keep its ciphertext, sign it under its own header."""
    ct = json.loads(bytes(blob)[security.SIGNATURE_BYTES:].decode())['ct']
    return signer.signing.sign(json.dumps({'party': signer.name, 'header': header, 'ct': ct},
                                          sort_keys=True).encode())


def test_a_captured_ciphertext_signed_again_by_another_party_or_under_another_header_is_refused():
    header = security.header_of(REQUEST, security.REQUEST_FIELDS, 'server')
    blob = sealed(header=header)
    mine = Msg(**dict(REQUEST.__dict__, origin='/proxy2', id=5, oldest_pending=5))
    theirs = security.header_of(mine, security.REQUEST_FIELDS, 'server')
    with pytest.raises(Rejected) as error:    # client2 re-signs the client's deposit as its own request
        security.open_sealed(SERVER, CLIENT2.verify_public, resigned(blob, CLIENT2, theirs), theirs)
    assert error.value.kind == 'tampered'
    assert 'party client2 signed a ciphertext sealed by party client' in error.value.detail
    later = Msg(**dict(REQUEST.__dict__, id=9, oldest_pending=9))
    again = security.header_of(later, security.REQUEST_FIELDS, 'server')
    with pytest.raises(Rejected) as error:    # the client's own old ciphertext under a new header
        security.open_sealed(SERVER, CLIENT.verify_public, resigned(blob, CLIENT, again), again)
    assert error.value.kind == 'tampered' and 'under another header' in error.value.detail
    # a ciphertext that binds nobody (as the code before sealed it) is refused too
    bare = nacl_sealed_box(SERVER.box_public, b'deposit 10')
    with pytest.raises(Rejected, match='names no sealer'):
        security.open_sealed(SERVER, CLIENT.verify_public, resigned(json_blob(bare), CLIENT, header), header)
    assert security.open_sealed(SERVER, CLIENT.verify_public, blob, header) == b'deposit 10'   # the control


def nacl_sealed_box(box_public, plaintext):
    import nacl.public
    return nacl.public.SealedBox(nacl.public.PublicKey(box_public)).encrypt(plaintext)


def json_blob(ciphertext):
    import base64
    return b'\0' * security.SIGNATURE_BYTES + json.dumps({'ct': base64.b64encode(ciphertext).decode()}).encode()


def test_a_request_signed_for_one_service_is_refused_by_another_and_a_reply_is_no_request():
    a = security.header_of(REQUEST, security.REQUEST_FIELDS, 'server', '/ftm_a/pxy2pro')
    blob = sealed(header=a)
    assert security.destination_of(blob) == '/ftm_a/pxy2pro'
    assert security.open_sealed(SERVER, CLIENT.verify_public, blob, a) == b'deposit 10'
    b = security.header_of(REQUEST, security.REQUEST_FIELDS, 'server', '/ftm_b/pxy2pro')
    with pytest.raises(Rejected) as error:    # copied to service B's topic: B's gate names its own
        security.open_sealed(SERVER, CLIENT.verify_public, blob, b)
    assert error.value.kind == 'misaddressed'
    assert 'signed it for /ftm_a/pxy2pro, it came to /ftm_b/pxy2pro' in error.value.detail
    reply = sealed(header=security.header_of(REPLY, security.REPLY_FIELDS, 'server', '/ftm_a/pxy2pro'))
    as_request = security.header_of(REPLY, security.REPLY_FIELDS, 'server', '/ftm_a/pxy2pro')
    as_request['dir'] = 'request'
    with pytest.raises(Rejected, match='misaddressed: party client signed it as a reply, it came as a request'):
        security.open_sealed(SERVER, CLIENT.verify_public, reply, as_request)
    # a signer that names no destination is refused too (review of SEC, session 33: it was taken
    # anywhere, and only counted): every gate signs its destination
    undestined = sealed(header=security.header_of(REQUEST, security.REQUEST_FIELDS, 'server'))
    assert security.destination_of(undestined) is None
    with pytest.raises(Rejected, match='misaddressed: party client signed it for no destination, it came to '
                                       '/ftm_b/pxy2pro'):
        security.open_sealed(SERVER, CLIENT.verify_public, undestined, b)


def test_the_batch_of_a_request_and_of_a_reply_is_signed():
    for fields, message in ((security.REQUEST_FIELDS, REQUEST), (security.REPLY_FIELDS, REPLY)):
        blob = sealed(header=security.header_of(message, fields, 'server'))
        batched = Msg(**dict(message.__dict__, batch=(2, 2)))   # changed on the way: PBR's After acts on it
        with pytest.raises(Rejected) as error:
            security.open_sealed(SERVER, CLIENT.verify_public, blob, security.header_of(batched, fields, 'server'))
        assert error.value.kind == 'tampered' and 'field(s) batch' in error.value.detail
        # as rospy gives it (a tuple) or as it was built (a list): the same header
        listed = Msg(**dict(message.__dict__, batch=[0, 0]))
        assert security.open_sealed(SERVER, CLIENT.verify_public, blob,
                                    security.header_of(listed, fields, 'server')) == b'deposit 10'


@pytest.mark.parametrize('blob', [b'\0' * 64 + b'[' * 100000, b'\0' * 64 + b'{"a":' * 100000])
def test_a_payload_nested_too_deep_is_refused_not_raised(blob):
    for read in (security.sender_of, security.addressee_of):
        with pytest.raises(Rejected) as error:
            read(blob)
        assert error.value.kind == 'malformed' and 'nested too deep' in error.value.detail
    with pytest.raises(Rejected, match='malformed'):
        security.destination_of(blob)
    deep = CLIENT.signing.sign(b'[' * 100000)           # signed by a certified party, still refused
    with pytest.raises(Rejected, match='malformed'):
        security.open_sealed(SERVER, CLIENT.verify_public, deep, HEADER)


def test_a_payload_too_large_is_refused_unread(monkeypatch):
    monkeypatch.setattr(security, 'MAX_SEALED_BYTES', 1000)
    blob = sealed(plaintext=b'x' * 2000)
    for read in (security.sender_of, lambda b: security.open_sealed(SERVER, CLIENT.verify_public, b, HEADER)):
        with pytest.raises(Rejected) as error:
            read(blob)
        assert error.value.kind == 'malformed' and 'more than a SEC message may be (1000)' in error.value.detail


def test_no_certificate_is_taken_before_the_first_status_of_the_ca():
    issuer = security.Issuer(CA, validity=100.0)
    issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public)
    cert, signature = issuer.certificate('client', 5000.0)
    issuer.bar(['client'])                                   # revoked ...
    book = security.CertificateBook(CA.verify_public)        # ... before this gate heard any status
    with pytest.raises(Rejected) as error:
        book.add('client', cert, 0.0)
    assert error.value.kind == 'ca_unreachable' and 'no certificate status from the CA' in error.value.detail
    assert book.get('client', 0.0) is None
    book.on_status(*issuer.status(5000.5), now=0.5)
    with pytest.raises(Rejected, match='is revoked'):
        book.add('client', cert, 0.5)


def restarted(issuer):
    """The CA restarted: a new Issuer from the state the old one saved (through JSON, as ca_state.json)."""
    again = security.Issuer(CA, validity=issuer.validity, overlap=issuer.overlap)
    again.restore(json.loads(json.dumps(issuer.state())))
    return again


def test_certificates_issued_before_a_restart_of_the_ca_are_revoked_after_it():
    issuer = security.Issuer(CA, validity=86400.0, overlap=10.0)
    issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public, 1000.0)
    old, _ = issuer.certificate('client', 1000.0)
    issuer.status(1000.0)
    # the operator revokes the client after a restart
    again = restarted(issuer)
    again.set_keys('client', CLIENT.box_public, CLIENT.verify_public, 1060.0)
    again.bar(['client'])
    assert old.serial in again.status(1061.0)[2]
    # the client's key rotated after a restart: the old certificate ends after the overlap
    again = restarted(issuer)
    again.set_keys('client', CLIENT.box_public, CLIENT.verify_public, 1060.0)
    fresh = Party.generate('client')
    assert again.set_keys('client', fresh.box_public, fresh.verify_public, 1070.0) is True
    assert old.serial in again.status(1200.0)[2]
    # ... or while the CA was down: the keys it certified are kept too
    again = restarted(issuer)
    assert again.set_keys('client', fresh.box_public, fresh.verify_public, 1060.0) is True
    assert old.serial in again.status(1200.0)[2]


def test_the_ca_state_forgets_expired_serials_and_names_a_corrupt_entry():
    issuer = security.Issuer(CA, validity=100.0)
    issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public, 0.0)
    first, _ = issuer.certificate('client', 0.0)
    second, _ = issuer.certificate('client', 60.0)           # renewed
    issuer.status(120.0)                                     # the first expired at 100
    assert issuer.state()['serials'] == {'client': {str(second.serial): 160.0}}
    for bad, words in [({'client': {'x': 1.0}}, "entry 'x'"), ({'client': {'5': 'soon'}}, "entry '5'"),
                       ({'client': [5]}, 'serials of'), ({'../x': {'5': 1.0}}, "'../x'"), ([], 'serials')]:
        state = dict(issuer.state(), serials=bad)
        fresh = security.Issuer(CA, validity=100.0)
        with pytest.raises(ValueError) as error:
            fresh.restore(state)
        assert words in str(error.value), (bad, str(error.value))
        assert fresh.serials == {} and fresh.revoked == set()   # nothing taken from a corrupt state
    with pytest.raises(ValueError, match='keys of'):
        security.Issuer(CA, validity=100.0).restore(dict(issuer.state(), keys={'client': ['AAAA', 'x']}))
    with pytest.raises(ValueError, match='seq'):
        security.Issuer(CA, validity=100.0).restore(dict(issuer.state(), seq='later'))
    older = {'revoked': [3], 'retiring': {}}                 # a state saved before serials were
    fresh = security.Issuer(CA, validity=100.0)
    fresh.restore(older)
    assert fresh.revoked == {3}


def test_a_ca_restarted_after_its_clock_stepped_back_publishes_statuses_the_gates_take():
    issuer = security.Issuer(CA, validity=86400.0)
    issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public, 1.7e9)
    cert, _ = issuer.certificate('client', 1.7e9)
    book = security.CertificateBook(CA.verify_public)
    for k in range(3):
        book.on_status(*issuer.status(1.7e9 + k), now=float(k))
    book.add('client', cert, 3.0)
    again = restarted(issuer)                                # its clock now 30 s behind
    again.set_keys('client', CLIENT.box_public, CLIENT.verify_public, 1.7e9 - 30)
    again.bar(['client'])
    assert book.on_status(*again.status(1.7e9 - 29), now=4.0) == ['client']   # taken: the revocation arrives
    assert book.on_status(*again.status(1.7e9 - 28), now=5.0) == []
