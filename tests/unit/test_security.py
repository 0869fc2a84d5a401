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


def test_certificates_bind_a_name_to_its_keys():
    signature = security.certify(CA, 'server', SERVER.box_public, SERVER.verify_public)
    security.check_certificate(CA.verify_public, 'server', SERVER.box_public, SERVER.verify_public, signature)
    for name, box, verify in [('client', SERVER.box_public, SERVER.verify_public),      # another name
                              ('server', MALLORY.box_public, SERVER.verify_public)]:    # another key
        with pytest.raises(Rejected, match='bad_certificate'):
            security.check_certificate(CA.verify_public, name, box, verify, signature)
    forged = security.certify(MALLORY, 'server', MALLORY.box_public, MALLORY.verify_public)
    with pytest.raises(Rejected, match='not signed by the CA'):
        security.check_certificate(CA.verify_public, 'server', MALLORY.box_public, MALLORY.verify_public, forged)


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
              attempt=0, epoch=3, transfer=0)
REPLY = Msg(origin='/proxy', id=7, client='/bank_client', oldest_pending=7, attempt=0, status=0, error='', epoch=3)


@pytest.mark.parametrize('fields,message', [(security.REQUEST_FIELDS, REQUEST), (security.REPLY_FIELDS, REPLY)])
def test_every_field_that_affects_processing_is_signed(fields, message):
    """A captured message re-sent with any one field changed (attempt, epoch, client, ...) is refused:
    the replay of issue 16 changed the unsigned attempt and executed again."""
    blob = sealed(header=security.header_of(message, fields, 'server'))
    assert security.open_sealed(SERVER, CLIENT.verify_public, blob,
                                security.header_of(message, fields, 'server')) == b'deposit 10'
    for name in fields:
        value = getattr(message, name)
        changed = Msg(**dict(message.__dict__, **{name: value + 1 if isinstance(value, int) else value + 'x'}))
        with pytest.raises(Rejected) as error:
            security.open_sealed(SERVER, CLIENT.verify_public, blob, security.header_of(changed, fields, 'server'))
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
