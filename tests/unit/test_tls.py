"""Mutual TLS's pure parts (aft_ftm.tls): the policy, the first bytes, certificates and contexts
(two parties shaking hands over a socket pair, a stranger's certificate refused). No ROS."""
import os
import socket
import ssl
import struct
import threading

import pytest

from aft_ftm import tls
from aft_ftm.errors import ConfigError

POLICY = {'plaintext': ['/rosout', '/account'], 'readable': ['/sensors/*'],
          'parties': {'master': {'publish': ['/ftm/checkpoints/master'], 'subscribe': ['*'], 'serve': ['/master/*'],
                                 'call': ['/aft/witness/*']},
                      'client': {'subscribe': ['/ftm/pro2pxy']}}}


@pytest.mark.parametrize('party,action,name,allowed', [
    ('master', 'publish', '/ftm/checkpoints/master', True),
    ('master', 'publish', '/ftm/checkpoints/slave', False),
    ('client', 'publish', '/ftm/checkpoints/master', False),
    ('client', 'subscribe', '/ftm/pro2pxy', True),
    ('client', 'call', '/master/set_role', False),
    ('master', 'serve', '/master/protocol/set_role', True),
    ('mallory', 'call', '/aft/witness/request', False),     # certified, but in no policy
    (None, 'call', '/aft/witness/request', False),          # no certificate
    (None, 'subscribe', '/rosout', True),                   # plaintext names
    (None, 'call', '/account', True),
    ('client', 'call', '/account', True),                   # a plaintext name is open to a certified peer too
    (None, 'subscribe', '/sensors/laser_0', True),          # readable: a recorder without TLS listens
    (None, 'publish', '/sensors/laser_0', False),           # but may not speak on it
    ('client', 'publish', '/sensors/laser_0', False),       # nor may a party the policy does not name
    (None, 'subscribe', '/ftm/pro2pxy', False),
])
def test_the_policy_allows_each_party_what_it_names_and_nothing_else(party, action, name, allowed):
    why = tls.Permissions.parse(POLICY).allows(party, action, name)
    assert (why is None) == allowed, why


@pytest.mark.parametrize('data,words', [
    ([], 'expected the keys parties'),
    ({'parties': {}, 'other': 1}, 'expected the keys parties'),
    ({'parties': {'a': {'publish': '/x'}}}, 'publish must be a list'),
    ({'parties': {'a': {'write': ['/x']}}}, 'unknown key(s) write'),
    ({'parties': {'a': ['/x']}}, 'expected a mapping'),
    ({'parties': {}, 'plaintext': '/rosout'}, 'plaintext must be a list'),
    ({'parties': {}, 'readable': [3]}, 'readable must be a list'),
    ({'parties': {'a': {'nodes': []}}}, 'nodes is empty'),
    ({'parties': {'a': {'nodes': '/a/*'}}}, 'nodes must be a list'),
])
def test_a_malformed_policy_is_refused_naming_the_problem(data, words):
    with pytest.raises(ConfigError) as error:
        tls.Permissions.parse(data, 'policy.yaml')
    assert 'policy.yaml' in str(error.value) and words in str(error.value)


@pytest.mark.parametrize('party,callerid,allowed', [
    ('master', '/master/tr_before', True),
    ('master', '/slave/tr_before', False),     # a site naming itself as a node of the other
    ('master', '/monitor', False),
    ('master', '', False),                     # no caller id at all
    ('client', '/anything', True),             # a party without nodes is not bound to names
    (None, '/master/tr_before', True),         # nor is a peer without TLS (plaintext names only)
])
def test_a_party_with_nodes_may_call_itself_only_by_their_names(party, callerid, allowed):
    policy = dict(POLICY, parties=dict(POLICY['parties'], master=dict(POLICY['parties']['master'],
                                                                       nodes=['/master/*'])))
    why = tls.Permissions.parse(policy).names_node(party, callerid)
    assert (why is None) == allowed, why
    if not allowed:
        assert party in why and (callerid or '(none)') in why


def test_a_tls_hello_is_told_from_a_tcpros_header():
    assert tls.looks_like_tls(bytes([0x16, 0x03, 0x01, 0x02, 0x00, 0x01]))     # a ClientHello of 512 bytes
    for length in (0, 150, 790, 4000, 66326, 2 ** 20):
        for first_field in (5, 40, 300):
            header = struct.pack('<I', length) + struct.pack('<I', first_field)
            assert not tls.looks_like_tls(header[:tls.PEEK]) or (66326 <= length and 256 <= first_field < 512), \
                (length, first_field)
    assert not tls.looks_like_tls(struct.pack('<I', 790) + b'\x05\x00')      # 16 03 00 00: not TLS
    assert not tls.looks_like_tls(bytes([0x16, 0x03, 0x01, 0x00, 0x00, 0x01]))  # an empty record
    assert not tls.looks_like_tls(b'PO') and not tls.looks_like_tls(b'POST /RPC2')


def _shake(server_context, client_context):
    """Handshake over a socket pair; (party the server saw, party the client saw) or the error."""
    a, b = socket.socketpair()
    seen = {}

    def serve():
        try:
            s = server_context.wrap_socket(a, server_side=True)
            seen['server'] = tls.party_of(s.getpeercert())
            s.sendall(b'x')
        except (ssl.SSLError, OSError) as e:
            seen['server_error'] = e
            a.close()
    thread = threading.Thread(target=serve)
    thread.start()
    try:
        c = client_context.wrap_socket(b)
        c.recv(1)
        seen['client'] = tls.party_of(c.getpeercert())
    except (ssl.SSLError, OSError) as e:
        seen['client_error'] = e
    thread.join(5)
    b.close()
    return seen


def test_two_certified_parties_name_each_other_and_a_strangers_certificate_is_refused(tmp_path):
    home, elsewhere = str(tmp_path / 'home'), str(tmp_path / 'elsewhere')
    tls.make_authority(home)
    tls.make_authority(elsewhere)
    for party in ('master', 'client'):
        tls.issue(home, party)
    tls.issue(elsewhere, 'master')                          # same name, another CA
    server, _ = tls.contexts(home, 'master')
    _, client = tls.contexts(home, 'client')
    assert _shake(server, client) == {'server': 'client', 'client': 'master'}
    _, stranger = tls.contexts(elsewhere, 'master')
    seen = _shake(server, stranger)
    assert 'server' not in seen and 'client' not in seen, seen
    with pytest.raises(ConfigError, match='ghost'):
        tls.contexts(home, 'ghost')
    with pytest.raises(ConfigError):
        tls.issue(home, 'ca')


def test_a_party_is_given_its_own_files_and_the_cas_certificate_only(tmp_path):
    authority = str(tmp_path / 'authority')
    tls.make_authority(authority)
    tls.issue(authority, 'master')
    tls.issue(authority, 'slave')
    given = tls.export_party(authority, 'master', str(tmp_path / 'master'))
    import os
    assert sorted(os.listdir(given)) == ['ca.tls.crt', 'master.tls.crt', 'master.tls.key']
    assert oct(os.stat(given).st_mode & 0o777) == oct(0o700)
    assert oct(os.stat(os.path.join(given, 'master.tls.key')).st_mode & 0o777) == oct(0o600)
    server, client = tls.contexts(given, 'master')          # enough to speak TLS as master
    with pytest.raises(ConfigError):
        tls.contexts(given, 'slave')                         # and nothing more


def test_a_revocation_list_revokes_only_what_the_ca_signed_and_never_goes_back(tmp_path):
    import os
    home, elsewhere = str(tmp_path / 'home'), str(tmp_path / 'elsewhere')
    tls.make_authority(home)
    tls.make_authority(elsewhere)
    for party in ('master', 'client'):
        tls.issue(home, party)
    tls.issue(elsewhere, 'client')
    held = tls.Revocations.of_directory(home)
    path, number = tls.revoke(home, ['client'])
    with open(path, 'rb') as f:
        first = f.read()
    client = tls.serial_of(home, 'client')
    assert number == 1 and held.take(first) == {client} and held.revoked(client)
    assert not held.revoked(tls.serial_of(home, 'master'))
    assert held.take(first) == frozenset()                   # the same list again: nothing new
    _, number = tls.revoke(home, ['master'])
    with open(path, 'rb') as f:
        second = f.read()
    assert number == 2 and held.take(second) == {tls.serial_of(home, 'master')} and held.revoked(client)
    with pytest.raises(ConfigError, match='older than the one held'):
        held.take(first)                                     # a replayed old list takes nothing back
    assert held.revoked(tls.serial_of(home, 'master')) and held.number == 2
    tls.revoke(elsewhere, ['client'])                        # a list of another CA
    with open(os.path.join(elsewhere, tls.CRL), 'rb') as f:
        with pytest.raises(ConfigError, match='not signed by the CA'):
            held.take(f.read())
    with pytest.raises(ConfigError, match='cannot be read'):
        held.take(second[:-40])                              # cut short
    altered = bytearray(second)
    altered[len(altered) // 2] ^= 0x01                       # one bit changed
    with pytest.raises(ConfigError):
        held.take(bytes(altered))
    assert held.number == 2 and held.serials == {client, tls.serial_of(home, 'master')}
    given = tls.export_party(home, 'client', str(tmp_path / 'client'))
    assert tls.CRL in os.listdir(given)                      # a party is given the list too


def test_a_peer_certificate_names_its_serial_and_end():
    serial, end = tls.serial_and_end({'serialNumber': '1F', 'notAfter': 'Jan  5 09:34:43 2031 GMT'})
    import calendar
    assert serial == 31 and end == calendar.timegm((2031, 1, 5, 9, 34, 43))
    assert tls.serial_and_end({}) == (0, None)


def test_the_highest_list_number_taken_is_kept_and_never_lowered(tmp_path):
    directory = str(tmp_path)
    assert tls.held_number(directory) is None
    tls.remember_number(directory, 3)
    tls.remember_number(directory, 2)                        # an older list: the number stays
    assert tls.held_number(directory) == 3
    with open(tmp_path / tls.HELD, 'w') as f:
        f.write('{"number": "x"}')
    with pytest.raises(ConfigError, match='must be an integer'):
        tls.held_number(directory)


def test_a_serial_is_read_as_alarms_print_it(tmp_path):
    home = str(tmp_path)
    tls.make_authority(home)
    tls.issue(home, 'client')
    serial = tls.serial_of(home, 'client')
    _, number = tls.revoke(home, serials=['%x' % serial])   # as an alarm names it
    held = tls.Revocations.of_directory(home)
    with open(tmp_path / tls.CRL, 'rb') as f:
        held.take(f.read())
    assert number == 1 and held.revoked(serial) and held.next_update is not None
    with pytest.raises(ConfigError, match='hexadecimal'):
        tls.revoke(home, serials=['not-a-serial'])


def test_a_party_resumes_no_session_its_certificate_is_judged_at_every_connection(tmp_path):
    tls.make_authority(str(tmp_path))
    tls.issue(str(tmp_path), 'master')
    server, _ = tls.contexts(str(tmp_path), 'master')
    assert server.num_tickets == 0


def test_an_outbound_connection_closed_before_its_header_came_is_not_judged(monkeypatch):
    """rospy's read_header returns without reading when the connection was closed meanwhile (its peer
    died: the car's demo, a board powered off). Nothing was said, so the TLS layer refuses nothing and
    raises no alarm; it once took that for a car node "named (none)" that its party may not run."""
    import types
    from aft_ftm.ros import tls_transport
    refused = []
    monkeypatch.setattr(tls_transport, '_refused', lambda *args: refused.append(args))
    policy = tls.Permissions.parse({'parties': {'car': {'nodes': ['/car/*']}}})
    monkeypatch.setitem(tls_transport._STATE, 'permissions', policy)
    closed = types.SimpleNamespace(tls_party='car', header=None, socket=None, dest_address=('10.0.0.1', 1))
    tls_transport._check_caller(closed)
    assert refused == []
    lying = types.SimpleNamespace(tls_party='car', header={'callerid': '/intruder', 'topic': '/t'}, socket=object(),
                                  dest_address=('10.0.0.1', 1), close=lambda: None)
    with pytest.raises(Exception, match='refused by the TLS policy'):
        tls_transport._check_caller(lying)
    assert refused and 'may not run a node named /intruder' in refused[0][2]


def test_revoking_a_party_revokes_the_certificates_a_re_issue_replaced_too(tmp_path):
    """tls_keygen DIR client twice (a rotation: the old key suspected), then --revoke client: the old
    certificate is revoked, not only the new one; --revoke-replaced revokes the old one only."""
    import os
    import subprocess
    import sys
    tool = os.path.join(os.path.dirname(__file__), '..', '..', 'catkin_ws', 'src', 'aft_ftm', 'nodes', 'tls_keygen')

    def run(*args):
        done = subprocess.run([sys.executable, tool] + list(args), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              universal_newlines=True)
        assert done.returncode == 0, done.stdout
        return done.stdout

    def revoked(directory):
        held = tls.Revocations.of_directory(directory)
        with open(os.path.join(directory, tls.CRL), 'rb') as f:
            held.take(f.read())
        return held
    for case in ('revoke', 'revoke-replaced'):
        home = str(tmp_path / case)
        run(home, 'client', 'master')
        old = tls.serial_of(home, 'client')
        run(home, 'client')                                  # re-issued: a rotation
        new = tls.serial_of(home, 'client')
        out = run(home, '--' + case, 'client')
        held = revoked(home)
        assert old != new and held.revoked(old), out
        assert held.revoked(new) == (case == 'revoke'), out
        assert not held.revoked(tls.serial_of(home, 'master'))
        assert tls.issued_serials(home)['client'] == [old, new]
    # a certificate issued before the record was kept is recorded when a re-issue replaces it
    home = str(tmp_path / 'older')
    tls.make_authority(home)
    tls.issue(home, 'client')
    old = tls.serial_of(home, 'client')
    os.remove(os.path.join(home, tls.ISSUED))
    tls.issue(home, 'client')
    tls.revoke(home, ['client'], replaced_only=True)
    assert revoked(home).revoked(old) and not revoked(home).revoked(tls.serial_of(home, 'client'))
    with open(os.path.join(home, tls.ISSUED), 'w') as f:
        f.write('{"client": ["zz"]}')
    with pytest.raises(ConfigError) as error:
        tls.revoke(home, ['client'])
    assert tls.ISSUED in str(error.value) and "party 'client'" in str(error.value)


BANK_POLICY = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                           'catkin_ws', 'src', 'aft_examples', 'config', 'tls_policy.yaml')


@pytest.mark.parametrize('party,name,allowed', [
    # what each party's nodes read in the demo (the ROS master's lists of a running SEC + TLS pair)
    ('client', '/ftm/pro2pxy', True), ('client', '/sec_plain/pro2pxy', True), ('client', '/aft/ca/status', True),
    ('master', '/ftm/checkpoints/slave', True), ('master', '/slave/fail_stop', True),
    ('master', '/aft/witness/configuration', True), ('slave', '/master/failures', True),
    ('operator', '/aft/alarms', True), ('operator', '/master/recovery/events', True),
    ('operator', '/aft/monitor/model', True), ('operator', '/ftm/heartbeat/master', True),
    # ... and never a site's checkpoints (the state and every client's replies), the requests on their
    # way, nor a site's plain side (deciphered requests and replies): the client and operator parties
    # read every topic before (review of session 41)
    ('client', '/ftm/checkpoints/master', False), ('client', '/ftm/pxy2pro', False),
    ('client', '/master/sec2pro', False), ('client', '/slave/pro2sec', False), ('client', '/master/pro2bfr', False),
    ('client', '/slave/aft2pro', False), ('client', '/ftm/join/master', False),
    ('operator', '/ftm/checkpoints/slave', False), ('operator', '/ftm/pxy2pro', False),
    ('operator', '/ftm/pro2pxy', False), ('operator', '/master/pro2sec', False),
    # an application client reads nothing: not the replies of its Proxy's other callers
    ('app', '/sec_plain/pro2pxy', False), ('app', '/ftm/pro2pxy', False), ('app', '/aft/alarms', False),
    ('operator', '/sec_plain/pxy2pro', False), ('master', '/sec_plain/pro2pxy', False),
])
def test_the_bank_policy_lets_each_party_read_what_it_needs_and_no_other_clients_data(party, name, allowed):
    why = tls.Permissions.load(BANK_POLICY).allows(party, 'subscribe', name)
    assert (why is None) == allowed, why


@pytest.mark.parametrize('party,action,allowed', [
    ('client', 'serve', True), ('app', 'call', True), ('operator', 'call', True),
    # an application client only calls it: registered at the master as /account, it answers nobody
    ('app', 'serve', False), ('client', 'call', False),
    # /account is not in clear: a process without a certificate can neither call it nor answer it (it
    # registered /account at the master and the client called it), nor can a party trusted with nothing
    (None, 'call', False), (None, 'serve', False), ('client2', 'serve', False), ('client2', 'call', False),
    ('master', 'serve', False), ('operator', 'serve', False),
])
def test_the_banks_own_interface_is_served_by_the_client_site_to_certified_callers_only(party, action, allowed):
    why = tls.Permissions.load(BANK_POLICY).allows(party, action, '/account')
    assert (why is None) == allowed, why


@pytest.mark.parametrize('party,action,name,allowed', [
    # the engine (adapt, the Monitoring Engine) suspends, rebinds, resumes and promotes the sites' nodes,
    # those it launched included ...
    ('engine', 'call', '/master/protocol/suspend', True), ('engine', 'call', '/slave/tr/protocol/rebind', True),
    ('engine', 'call', '/master/after/resume', True), ('engine', 'call', '/slave/recovery/set_promote', True),
    ('engine', 'subscribe', '/aft/monitor/bandwidth', True), ('engine', 'subscribe', '/ftm/heartbeat/slave', True),
    ('engine', 'publish', '/aft/monitor/events', True),
    # ... and nothing else: no state written, no checkpoint read, no replies, no Proxy rebound
    ('engine', 'call', '/master/bank_server/set_state', False), ('engine', 'call', '/account', False),
    ('engine', 'subscribe', '/ftm/checkpoints/master', False), ('engine', 'subscribe', '/ftm/pro2pxy', False),
    ('engine', 'call', '/proxy/rebind', False), ('engine', 'call', '/aft/witness/request', False),
    # nobody else suspends or rebinds: not the operator who drives the demo, not a site's peer (a site's
    # own nodes may call its own services: the site is trusted with itself)
    ('operator', 'call', '/master/protocol/suspend', False), ('operator', 'call', '/slave/proceed/rebind', False),
    ('client2', 'call', '/master/protocol/suspend', False), ('client', 'call', '/slave/protocol/resume', False),
    ('slave', 'call', '/master/protocol/suspend', False), ('master', 'call', '/master/protocol/suspend', True),
    # the engine reads the heartbeats, not a topic a rebind named like one (review of session 43: '*'
    # crosses '/', and a site may publish /ftm/*/master)
    ('engine', 'subscribe', '/ftm/heartbeat/x/master', False),
    # what the Monitoring Engine is told: the bandwidth by the sites' link monitors, the declared faults
    # and the application's characteristics by the operator; its decisions by nobody else
    ('master', 'publish', '/aft/monitor/bandwidth', True), ('master', 'publish', '/aft/monitor/declare_faults', False),
    ('operator', 'publish', '/aft/monitor/declare_faults', True), ('operator', 'publish', '/aft/monitor/application', True),
    ('operator', 'publish', '/aft/monitor/events', False), ('slave', 'publish', '/aft/monitor/model', False),
])
def test_the_bank_policy_lets_the_engine_alone_change_the_mechanisms(party, action, name, allowed):
    """Issue 16: adaptations under TLS were not supported: no party could suspend or rebind a node, so
    every adapt was refused. The party engine now may, and no other but the site itself."""
    why = tls.Permissions.load(BANK_POLICY).allows(party, action, name)
    assert (why is None) == allowed, why


def test_the_engine_s_nodes_are_its_own_and_a_guard_s_fail_stop_is_its_site_s():
    """The engine's party runs the adapt command and the Monitoring Engine; a launched node's guard
    tells its site to fail-stop with the site's party, named outside the site's namespace (whose nodes
    the peer's fence stops before the guard's alarm is out)."""
    policy = tls.Permissions.load(BANK_POLICY)
    assert policy.names_node('engine', '/aft_adapt_123_456') is None and policy.names_node('engine', '/aft/monitor') is None
    assert policy.names_node('operator', '/aft_adapt_123_456') is not None
    assert policy.names_node('master', '/fail_site_master_1_2') is None
    assert policy.names_node('slave', '/fail_site_master_1_2') is not None
    assert policy.allows('master', 'publish', '/master/fail_stop') is None


def test_a_node_takes_its_partys_new_key_and_certificate_once_they_load_and_says_if_they_never_do(tmp_path,
                                                                                                    monkeypatch):
    """A rotation without a restart (aft_ftm.ros.tls_transport._rotate): a key and a certificate of
    different issues (one copied, the other not yet) change nothing and are tried again, said only
    past ROTATION_GRACE; once the pair loads, new connections use it. A pair of another CA or of
    another party is refused at once (review of session 42: loading checks neither)."""
    import shutil
    from aft_ftm.ros import tls_transport
    home = str(tmp_path / 'home')
    tls.make_authority(home)
    tls.issue(home, 'master')
    given = tls.export_party(home, 'master', str(tmp_path / 'master'))
    server, client = tls.contexts(given, 'master')
    first = tls.serial_of(given, 'master')
    state = dict(server=server, client=client, party='master', directory=given, own_serial=first,
                 revocations=tls.Revocations.of_directory(home),
                 files_seen=tls_transport._files_stat(given, 'master'))
    monkeypatch.setattr(tls_transport, '_STATE', state)
    raised = []
    monkeypatch.setattr(tls_transport, '_alarm', lambda kind, detail: raised.append((kind, detail)))
    tls.issue(home, 'master')   # issued again: its new key copied first, the certificate not yet
    key, crt = tls.certificate_files(home, 'master')
    shutil.copyfile(key, os.path.join(given, os.path.basename(key)))
    files = tls_transport._files_stat(given, 'master')
    assert files != state['files_seen']
    tls_transport._rotate(files, 100.0)
    assert state['server'] is server and state['own_serial'] == first and raised == []
    tls_transport._rotate(files, 100.0 + tls_transport.ROTATION_GRACE + 0.1)
    assert [k for k, _ in raised] == ['rotation_failed'] and state['server'] is server
    shutil.copyfile(crt, os.path.join(given, os.path.basename(crt)))   # the certificate follows
    files = tls_transport._files_stat(given, 'master')
    tls_transport._rotate(files, 200.0)
    assert state['server'] is not server and state['own_serial'] == tls.serial_of(home, 'master') != first
    assert state['files_seen'] == files and len(raised) == 1 and 'rotation_failing_since' not in state
    # whole pairs that load but are wrong: refused at once, the pair in use kept
    rotated = state['server']
    other = str(tmp_path / 'other')
    tls.make_authority(other)
    tls.issue(other, 'master')
    tls.issue(home, 'client')
    for source, party, words in ((other, 'master', 'not signed by this CA'), (home, 'client', 'not party master')):
        for mine, theirs in zip(tls.certificate_files(given, 'master'), tls.certificate_files(source, party)):
            shutil.copyfile(theirs, mine)
        files = tls_transport._files_stat(given, 'master')
        tls_transport._rotate(files, 300.0)
        assert raised[-1][0] == 'rotation_refused' and words in raised[-1][1], raised[-1]
        assert state['server'] is rotated and state['files_seen'] == files


def test_a_cut_the_watcher_explains_hurries_the_subscription_keeper(tmp_path, monkeypatch):
    """A rotation without a pause (session 43): when this node's replaced certificate is revoked (its
    peers cut the connections made with it), or its watcher cuts a peer's revoked certificate, the
    subscription keeper is hurried: the cut subscriptions are made again at once, not after its 5 s
    grace. A revocation of nobody this node knows hurries nothing."""
    import collections
    import shutil
    import socket
    import time
    from aft_ftm.ros import subscription_keeper, tls_transport
    home = str(tmp_path / 'home')
    tls.make_authority(home)
    tls.issue(home, 'master')
    first = tls.serial_of(home, 'master')
    tls.issue(home, 'master')   # rotated: the first certificate replaced
    given = tls.export_party(home, 'master', str(tmp_path / 'master'))
    hurried, raised = [], []
    monkeypatch.setattr(subscription_keeper, 'hurry', hurried.append)
    monkeypatch.setattr(tls_transport, '_alarm', lambda kind, detail: raised.append(kind))
    monkeypatch.setattr(tls_transport, '_LIVE', __import__('weakref').WeakKeyDictionary())
    state = dict(directory=given, party='master', files_seen=tls_transport._files_stat(given, 'master'),
                 crl=os.path.join(given, tls.CRL), crl_seen=None, revocations=tls.Revocations.of_directory(given),
                 own_serial=tls.serial_of(given, 'master'), replaced_serials=collections.deque([first], maxlen=16))
    monkeypatch.setattr(tls_transport, '_STATE', state)

    def crl_reaches_the_node():
        shutil.copyfile(os.path.join(home, tls.CRL), state['crl'])
        state['crl_seen'] = None
        tls_transport._look_once(time.time())
    tls.issue(home, 'other')
    tls.revoke(home, ['other'])   # nobody this node knows
    crl_reaches_the_node()
    assert hurried == [] and raised == []
    tls.revoke(home, ['master'], replaced_only=True)   # this node's replaced certificate
    crl_reaches_the_node()
    assert hurried == [tls_transport.HURRY_WINDOW] and raised == []
    # a live connection of a peer whose certificate is revoked: cut, and the keeper hurried
    tls.issue(home, 'slave')
    peer = tls.serial_of(home, 'slave')
    mine, theirs = socket.socketpair()
    tls_transport._LIVE[mine] = ('slave', peer, None)
    tls.revoke(home, ['slave'])
    crl_reaches_the_node()
    assert raised == ['certificate_revoked'] and hurried == [tls_transport.HURRY_WINDOW] * 2
    assert theirs.recv(10) == b''   # cut
    mine.close(), theirs.close()


def test_a_certificate_ending_soon_is_said_before_it_ends_and_never_from_its_first_second():
    day = 86400.0
    month = (0.0, 30 * day)   # tls_keygen's default: 30 days
    assert tls.ending_notice('master', 0xab, *month, now=day) is None
    assert tls.ending_notice('master', 0xab, *month, now=30 * day - 6.5 * day) is None   # min(7 days, 6 days)
    kind, detail = tls.ending_notice('master', 0xab, *month, now=30 * day - 5.5 * day)
    assert kind == 'own_certificate_ending'
    assert 'party master, serial ab' in detail and 'ends in 5.5 days' in detail and 'tls_keygen DIR master' in detail
    kind, detail = tls.ending_notice('master', 0xab, *month, now=30 * day + 1)
    assert kind == 'own_certificate_expired' and 'every peer refuses it' in detail
    short = (1000.0, 1100.0)   # a certificate of 100 s: said in its last 20
    assert tls.ending_notice('m', 1, *short, now=1010.0) is None
    assert tls.ending_notice('m', 1, *short, now=1085.0)[1].count('ends in 15 s') == 1


def test_a_nodes_own_certificate_ending_then_ended_is_an_alarm_once_each_and_a_rotation_is_judged_afresh(
        tmp_path, monkeypatch):
    """Certificates are not renewed by themselves: before, the first sign of one ending was every
    peer refusing the node."""
    import datetime
    import time
    from aft_ftm.ros import tls_transport
    home = str(tmp_path / 'home')
    tls.make_authority(home)
    tls.issue(home, 'master', lifetime=datetime.timedelta(seconds=100))
    given = tls.export_party(home, 'master', str(tmp_path / 'master'))
    raised = []
    monkeypatch.setattr(tls_transport, '_alarm', lambda kind, detail: raised.append(kind))
    monkeypatch.setattr(tls_transport, '_LIVE', __import__('weakref').WeakKeyDictionary())
    state = dict(directory=given, party='master', files_seen=tls_transport._files_stat(given, 'master'),
                 crl=os.path.join(given, tls.CRL), crl_seen=None, revocations=tls.Revocations.of_directory(given),
                 own_serial=tls.serial_of(given, 'master'), own_span=tls.span_of(given, 'master'))
    monkeypatch.setattr(tls_transport, '_STATE', state)
    begins, ends = state['own_span']
    assert abs(ends - time.time() - 100) < 5 and begins <= time.time()   # (begins backdated: clock skew)
    tls_transport._look_once(begins + 10)
    assert raised == []
    for _ in range(3):
        tls_transport._look_once(ends - 5)
    assert raised == ['own_certificate_ending']   # once, not every 0.25 s
    tls_transport._look_once(ends + 1)
    tls_transport._look_once(ends + 2)
    assert raised == ['own_certificate_ending', 'own_certificate_expired']
    # a rotation: the new certificate (a month) is judged afresh, and says nothing while it is young
    tls.issue(home, 'master')
    tls.export_party(home, 'master', given)
    tls_transport._look_once(time.time())
    assert state['own_serial'] == tls.serial_of(given, 'master') and state['own_span'][1] - ends > 20 * 86400
    assert raised == ['own_certificate_ending', 'own_certificate_expired']
