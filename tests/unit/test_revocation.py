"""One revocation for SEC and TLS (aft_ftm.revocation, `rosrun aft_ftm revoke`): a party revoked in
both layers by one command, read back with each layer's own reader; bad input changes nothing.
(What each layer's nodes do with their list is in test_security.py, test_tls.py and the TLS and SEC
integration tests.) No ROS."""
import os
import subprocess
import sys

import pytest

from aft_ftm import revocation, sec_policy, security, tls
from aft_ftm.errors import ConfigError

TOOL = os.path.join(os.path.dirname(__file__), '..', '..', 'catkin_ws', 'src', 'aft_ftm', 'nodes', 'revoke')


@pytest.fixture
def layers(tmp_path):
    sec, authority = str(tmp_path / 'keys'), str(tmp_path / 'tls' / 'authority')
    for party in ('ca', 'client', 'client2', 'server'):
        security.write_party(sec, security.Party.generate(party))
    tls.make_authority(authority)
    for party in ('master', 'client'):
        tls.issue(authority, party)
    given = {party: tls.export_party(authority, party, str(tmp_path / 'tls' / party)) for party in ('master', 'client')}
    return sec, authority, given


def snapshot(*directories):
    """Every file's bytes under directories: what 'nothing changed' compares."""
    files = {}
    for top in directories:
        for root, _, names in os.walk(top):
            for name in names:
                with open(os.path.join(root, name), 'rb') as f:
                    files[os.path.join(root, name)] = f.read()
    return files


def tls_revoked(directory, party_dir, party):
    held = tls.Revocations.of_directory(directory)
    with open(os.path.join(party_dir, tls.CRL), 'rb') as f:
        held.take(f.read())
    return held.revoked(tls.serial_of(directory, party))


def test_one_command_revokes_a_party_in_both_layers_and_keeps_what_was_revoked(layers):
    sec, authority, given = layers
    with open(os.path.join(sec, 'revoked.yaml'), 'w') as f:
        f.write('revoked: [client2]\n')
    tls.issue(authority, 'client')   # a re-issue: the replaced certificate is revoked too
    said = revocation.revoke(['client'], sec, authority, copy_to=[given['master'], given['client']])
    assert sec_policy.load_revocations(os.path.join(sec, 'revoked.yaml')) == ['client2', 'client']
    for party_dir in given.values():   # each party's nodes read the list in their own directory
        assert tls_revoked(authority, party_dir, 'client')
        assert not tls_revoked(authority, party_dir, 'master')
    held = tls.Revocations.of_directory(authority)
    with open(os.path.join(given['master'], tls.CRL), 'rb') as f:
        held.take(f.read())
    assert set(tls.issued_serials(authority)['client']) <= held.serials
    assert said[0].startswith('SEC: client revoked') and said[1].startswith('TLS: client revoked, list number 1')
    revocation.revoke(['client'], sec, authority)   # again: nothing doubled, the list numbered on
    assert sec_policy.load_revocations(os.path.join(sec, 'revoked.yaml')) == ['client2', 'client']


def test_a_party_one_layer_does_not_know_is_revoked_in_the_other_and_said(layers):
    sec, authority, given = layers
    said = revocation.revoke(['master'], sec, authority, copy_to=[given['client']])
    assert not os.path.exists(os.path.join(sec, 'revoked.yaml'))   # SEC has no party master: untouched
    assert tls_revoked(authority, given['client'], 'master')
    assert said[-1] == 'master: not a SEC party, not revoked there'
    said = revocation.revoke(['server'], sec, authority)
    assert sec_policy.load_revocations(os.path.join(sec, 'revoked.yaml')) == ['server']
    assert said[-1] == 'server: not a TLS party, not revoked there'


@pytest.mark.parametrize('case,words', [
    ('unknown', 'unknown to SEC and TLS: mallory'),
    ('malformed', 'expected exactly one key, revoked'),
    ('no copy dir', '--copy-to'),
    ('no layer', 'name the SEC keys directory'),
    ('bad name', 'is not a party name'),
    ('not an authority', 'is not a TLS authority directory'),
    ('copy without tls', 'name the TLS authority'),
    ('the ca', 'ca is the certification authority itself'),
    ('another ca', "its CA certificate is another authority's"),
    ('newer held', 'took list number 5 already'),
    ('corrupt list', "the authority's revocation list"),
    ('certificate gone', 'recorded as issued, but its current one'),
])
def test_bad_input_is_named_and_changes_nothing(layers, tmp_path, case, words):
    sec, authority, given = layers
    with open(os.path.join(sec, 'revoked.yaml'), 'w') as f:
        f.write('revoked: [client2]\n' if case != 'malformed' else 'revoked: client2\n')
    if case == 'another ca':
        other = str(tmp_path / 'other')
        tls.make_authority(other)
        tls.issue(other, 'master')
        given['other'] = tls.export_party(other, 'master', str(tmp_path / 'other_master'))
    if case == 'newer held':
        tls.remember_number(given['master'], 5)
    if case == 'corrupt list':
        tls.revoke(authority, ['master'])
        with open(os.path.join(authority, tls.CRL), 'r+b') as f:
            f.seek(60)
            f.write(b'XXXX')
    if case == 'certificate gone':
        os.remove(os.path.join(authority, 'client.tls.crt'))
    args = {'unknown': (['client', 'mallory'], sec, authority, [given['master']]),
            'the ca': (['client', 'ca'], sec, authority, []),
            'another ca': (['client'], sec, authority, [given['master'], given.get('other')]),
            'newer held': (['client'], sec, authority, [given['client'], given['master']]),
            'corrupt list': (['client'], sec, authority, []),
            'certificate gone': (['client'], sec, authority, []),
            'malformed': (['client'], sec, authority, [given['master']]),
            'no copy dir': (['client'], sec, authority, [str(tmp_path / 'nowhere')]),
            'no layer': (['client'], None, None, []),
            'bad name': (['client', '../x'], sec, authority, []),
            'not an authority': (['client'], sec, given['master'], []),
            'copy without tls': (['client'], sec, None, [given['master']])}[case]
    before = snapshot(sec, authority, *given.values())
    with pytest.raises(ConfigError, match=words.replace('-', r'\-')):
        revocation.revoke(*args)
    assert snapshot(sec, authority, *given.values()) == before


def test_the_command_says_what_it_did_and_refuses_bad_input_with_exit_2(layers):
    sec, authority, given = layers
    run = subprocess.run([sys.executable, TOOL, '--sec', sec, '--tls', authority, '--copy-to', given['master'],
                          'mallory'], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, universal_newlines=True)
    assert run.returncode == 2 and 'unknown to SEC and TLS: mallory (' in run.stdout
    assert 'nothing was revoked' in run.stdout
    run = subprocess.run([sys.executable, TOOL, '--sec', sec, '--tls', authority, '--copy-to', given['master'],
                          'client'], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, universal_newlines=True)
    assert run.returncode == 0, run.stdout
    assert 'SEC: client revoked' in run.stdout and 'copied into %s' % given['master'] in run.stdout
    assert tls_revoked(authority, given['master'], 'client')


def test_a_write_failing_part_way_says_what_was_done(layers, monkeypatch):
    sec, authority, given = layers
    with open(os.path.join(sec, 'revoked.yaml'), 'w') as f:
        f.write('revoked: []\n')
    os.chmod(os.path.join(sec, 'revoked.yaml'), 0o600)

    def disk_full(*args, **kwargs):
        raise OSError(28, 'No space left on device')
    monkeypatch.setattr(tls, 'revoke', disk_full)
    with pytest.raises(revocation.Incomplete) as raised:
        revocation.revoke(['client'], sec, authority, copy_to=[given['master']])
    assert raised.value.done == ['SEC: client revoked in %s (the CA refuses the certificates within its status '
                                 'period, 0.5 s)' % os.path.join(sec, 'revoked.yaml')]
    assert 'No space left on device' in str(raised.value)
    assert oct(os.stat(os.path.join(sec, 'revoked.yaml')).st_mode & 0o777) == oct(0o600)   # its mode kept


def test_revocations_at_once_lose_none(layers):
    import threading
    sec, authority, _ = layers
    parties = ['p%d' % i for i in range(8)]
    for party in parties:
        security.write_party(sec, security.Party.generate(party))
        tls.issue(authority, party)
    threads = [threading.Thread(target=revocation.revoke, args=([p], sec, authority)) for p in parties]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert sorted(sec_policy.load_revocations(os.path.join(sec, 'revoked.yaml'))) == parties
    held = tls.Revocations.of_directory(authority)
    with open(os.path.join(authority, tls.CRL), 'rb') as f:
        held.take(f.read())
    assert held.number == 8 and all(held.revoked(tls.serial_of(authority, p)) for p in parties)
