"""The SEC gate's own decisions (aft_ftm.ros.sec_nodes.SecGateNode), on a gate built without ROS: its
ports, the CA and the clock are fakes. No ROS master."""
import collections
import threading

import pytest
import rospy

from aft_ftm import health, security
from aft_ftm.protocol import Role
from aft_ftm.recovery import SiteRole
from aft_ftm.ros import sec_nodes
from aft_ftm.security import Party, Rejected

CA, SERVER, CLIENT = (Party.generate(n) for n in ('ca', 'server', 'client'))


class FakePorts(object):
    TOPICS = {'requests_in': '/ftm/pxy2pro', 'requests_out': '/master/sec2pro', 'replies_in': '/master/pro2sec',
              'replies_out': '/ftm/pro2pxy'}

    def __init__(self, listeners=1):
        self.published = []
        self.listeners = listeners

    def topic(self, name):
        return self.TOPICS[name]

    def connections(self, name):
        return self.listeners

    def publish(self, name, msg):
        self.published.append((name, msg))
        return True


class KeptLog(object):
    """A replay log that works (aft_ftm.replay_log.ReplayLog's face to the diagnostics)."""
    path, broken = '/var/aft/replay.log', None


def gate(side='server', tls=False, ask_fresh=False):
    """A SecGateNode as __init__ leaves it, without reading parameters or key files. Unless ask_fresh, a
    server gate takes every origin as having proved fresh already (the tests of other decisions)."""
    node = sec_nodes.SecGateNode.__new__(sec_nodes.SecGateNode)
    node.side, node.me, node.role, node.tls = side, SERVER, Role.PRIMARY, tls
    node.book = security.CertificateBook(CA.verify_public)
    node.lock, node.sent, node.rejected, node.policy = threading.Lock(), {}, 0, 'policy.yaml'
    node.unsealed, node.challenges, node.not_for_me = {}, {}, 0
    node.freshness = security.Freshness(ask=ask_fresh)
    node.destination, node.ports = '/ftm/pxy2pro', FakePorts()
    node.runs, node.nonces = security.ProxyRuns(), security.ReplyNonces()
    node.quota = security.PartyQuota()
    node.replay_log, node.restored, node.earlier_told = None, 0, collections.OrderedDict()
    node.site_role, node.witness = SiteRole(''), ''
    node.floors_learned, node.floors_asked, node.floors_missing, node.floor_calls = 0, None, None, {}
    return node


@pytest.fixture(autouse=True)
def no_ros_clock(monkeypatch):
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))


def test_a_gate_without_tls_says_its_plaintext_side_is_open_in_an_alarm_and_its_diagnostics():
    open_gate = gate(tls=False)
    report = open_gate._health()
    assert report.level == health.Level.WARN
    assert 'no TLS: its plaintext side is open to every node of the graph (/master/sec2pro, /master/pro2sec)' \
        in report.message and report.value('tls') == 'off'
    open_gate._tell_without_tls(0.0)
    (port, raised), = open_gate.ports.published
    assert (port, raised.mechanism, raised.kind) == ('alarms', 'tls', 'sec_without_tls')
    assert '/master/sec2pro, /master/pro2sec' in raised.detail and 'mutual TLS' in raised.detail
    # not a SEC alarm: the change model would take it for an attack
    from aft_ftm import change_model
    assert change_model.observed_fault(raised.mechanism, raised.kind) is None
    client = gate(side='client', tls=False)
    assert '(/ftm/pxy2pro, /ftm/pro2pxy)' in client._health().message   # the Proxy's side
    closed = gate(tls=True)
    closed.replay_log = KeptLog()
    assert closed._health().level == health.Level.OK and closed._health().value('tls') == 'on'


def test_a_gate_asks_the_ca_for_no_certificate_before_its_first_status():
    early = gate()
    early._ask_ca = lambda party: pytest.fail('the CA was asked before any status came')
    with pytest.raises(Rejected) as error:
        early._peer('client')
    assert error.value.kind == 'ca_unreachable' and 'no status from the CA' in error.value.detail


def test_a_proxy_started_again_with_its_clock_behind_is_told_sealed_where_to_number_from_not_left_hanging():
    """Review of stop 38: behind a SEC gate, a Proxy started again under its name with ids below its
    predecessor's was refused as a replay for ever (every call hung); the Protocol's STALE_ID never
    reached it. The gate refuses it (the replay alarm still) and tells its party, sealed, the ids to use."""
    from aft_msgs.msg import Reply, Request
    server = gate()
    server.origins, server.replays = security.OriginBinding(None), security.ReplayGuard()
    server._peer = lambda party: (CLIENT.box_public, CLIENT.verify_public)
    server._open = lambda party, blob, header: b'plaintext'

    def request(rid):
        msg = Request(id=rid, origin='/proxy', client='/c', service_type='aft_msgs/Account', oldest_pending=rid)
        msg.payload = security.seal(CLIENT, SERVER.box_public, security.header_of(
            msg, security.REQUEST_FIELDS, 'server', '/ftm/pxy2pro'), b'deposit')
        return msg
    server._on_request(request(5000))
    server._on_request(request(5001))
    assert [name for name, _ in server.ports.published] == ['requests_out', 'requests_out']
    server._on_request(request(40))                                # started again, its clock behind
    (_, raised), (port, told) = server.ports.published[2:]
    assert (raised.kind, port, told.status, told.id) == ('replay', 'replies_out', Reply.STALE_ID, 40)
    assert told.oldest_pending == 5002                             # above every id verified from /proxy
    security.open_sealed(CLIENT, SERVER.verify_public, told.payload, security.header_of(
        told, security.REPLY_FIELDS, 'client', '/ftm/pxy2pro'))   # sealed for its party, signed by the server


def reply_gates():
    """A server's gate that verified a request of /proxy (party client), and that client's gate."""
    server = gate()
    server.origins = security.OriginBinding(None)
    server.origins.bind('client', '/proxy')
    server._peer = lambda party: (CLIENT.box_public, CLIENT.verify_public)
    client = gate(side='client')
    client.me, client.server_party, client.not_for_me = CLIENT, 'server', 0
    return server, client


def test_a_replys_error_text_is_sealed_with_its_payload_and_restored_by_its_clients_gate():
    """Review of SEC (session 33): the error of a reply went in clear beside its ciphered payload, and
    a server's error names the client's data ("cannot withdraw 999999 from a balance of 4342"): any
    subscriber read other clients' balances."""
    from aft_msgs.msg import Reply
    server, client = reply_gates()
    server.nonces.note('/proxy', 7, client.runs.nonce_for('/proxy', 7, 7), 7)   # request 7 came through the gate
    client.sent[('/proxy', 7)] = None
    error = 'service cannot process request: cannot withdraw 999999 from a balance of 4342'
    server._on_reply(Reply(id=7, origin='/proxy', client='/c', status=Reply.ERROR, error=error, payload=b'resp'))
    (port, wire), = server.ports.published
    assert port == 'replies_out' and wire.error == sec_nodes.SEALED_ERROR and b'4342' not in bytes(wire.payload)
    client._open = lambda party, blob, header: security.open_sealed(CLIENT, SERVER.verify_public, blob, header)
    client._on_reply(wire)
    (port, restored), = client.ports.published
    assert (port, restored.error, bytes(restored.payload), restored.status) == ('replies_out', error, b'resp',
                                                                                Reply.ERROR)
    # a reply with no error says none on the wire either
    server.ports.published.clear()
    server._on_reply(Reply(id=8, origin='/proxy', client='/c', status=Reply.OK, payload=b'ok'))
    assert server.ports.published[0][1].error == ''
    with pytest.raises(Rejected, match='malformed'):
        security.unframe_error(security.ERROR_FRAME + b'\x00\x00\x00\x09abc')


def test_an_old_sealed_reply_is_refused_for_an_id_a_proxy_started_again_asks_again():
    """Review of SEC (session 33): replies were not tied to their request. A Proxy started again with its
    clock behind uses ids again; an attacker who captured the sealed reply of such an id from the earlier
    run replayed it, and the new call took the old answer. Each run of a client's gate now signs a nonce
    into its requests, the server's gate seals each reply with the nonce its request came with, and the
    client's gate refuses a reply naming another run's for an id it waits for."""
    from aft_msgs.msg import Reply, Request
    server = gate()
    server.origins, server.replays = security.OriginBinding(None), security.ReplayGuard()
    server._peer = lambda party: (CLIENT.box_public, CLIENT.verify_public)
    server._open = lambda party, blob, header: security.open_sealed(SERVER, CLIENT.verify_public, blob, header)

    def client_gate():
        client = gate(side='client')
        client.me, client.server_party, client.not_for_me = CLIENT, 'server', 0
        client._peer = lambda party: (SERVER.box_public, SERVER.verify_public)
        client._open = lambda party, blob, header: security.open_sealed(CLIENT, SERVER.verify_public, blob, header)
        return client

    def through(client, rid, answer):
        """A request of the Proxy through its gate and the server's, answered: the sealed reply on the wire."""
        client.ports.published.clear()
        client._on_request(Request(id=rid, origin='/proxy', client='/c', service_type='aft_msgs/Account',
                                   oldest_pending=rid, payload=b'deposit'))
        (_, sealed), = client.ports.published
        server.ports.published.clear()
        server._on_request(sealed)
        (_, plain), = server.ports.published
        assert bytes(plain.payload) == b'deposit'
        server.ports.published.clear()
        server._on_reply(Reply(id=rid, origin='/proxy', client='/c', status=Reply.OK, payload=answer))
        (_, wire), = server.ports.published
        return wire

    first = client_gate()
    captured = through(first, 9000, b'balance 10')
    first.ports.published.clear()
    first._on_reply(captured)
    (port, taken), = first.ports.published
    assert (port, bytes(taken.payload)) == ('replies_out', b'balance 10')   # its own run's reply: taken

    again = client_gate()                       # the Proxy and its gate started again, its clock behind:
    assert again.runs.nonce_for('/proxy', 9000, 9000) != first.runs.current('/proxy')   # id 9000 used again
    server.replays = security.ReplayGuard()     # (a promoted backup's gate: it never saw the first run)
    fresh = through(again, 9000, b'balance 25')
    again.ports.published.clear()
    again._on_reply(captured)                   # the attacker's replay comes first
    (port, raised), = again.ports.published
    assert (port, raised.mechanism, raised.kind) == ('alarms', 'sec', 'replay'), raised
    assert '/proxy/9000' in raised.detail and 'earlier run' in raised.detail
    again.ports.published.clear()
    again._on_reply(fresh)                      # ... and the right answer is still taken
    (port, taken), = again.ports.published
    assert (port, bytes(taken.payload)) == ('replies_out', b'balance 25')
    # An old reply for an id this run does not wait for is passed over, as another party's: its Proxy
    # has nothing waiting for it.
    again.ports.published.clear()
    again._on_reply(captured)
    assert again.ports.published == [] and again.not_for_me == 1
    # A reply that names no nonce (a request that named none: not a client gate's) is refused too.
    server.nonces = security.ReplyNonces()
    again._on_request(Request(id=9100, origin='/proxy', client='/c', service_type='aft_msgs/Account',
                              oldest_pending=9100, payload=b'deposit'))
    server.ports.published.clear()
    server._on_reply(Reply(id=9100, origin='/proxy', client='/c', status=Reply.OK, payload=b'forged'))
    (_, unbound), = server.ports.published
    again.ports.published.clear()
    again._on_reply(unbound)
    (port, raised), = again.ports.published
    assert (port, raised.mechanism, raised.kind) == ('alarms', 'sec', 'replay') and 'for no run' in raised.detail


def test_the_server_gate_forgets_a_requests_nonce_once_its_proxy_has_its_answer():
    nonces = security.ReplyNonces(per_origin=3)
    for rid in (10, 11, 12):
        nonces.note('/p', rid, 'n%d' % rid, oldest_pending=10)
    assert [nonces.of('/p', rid) for rid in (10, 11, 12)] == ['n10', 'n11', 'n12']
    nonces.note('/p', 13, 'n13', oldest_pending=12)           # 10 and 11 answered
    assert [nonces.of('/p', rid) for rid in (10, 11, 12, 13)] == [None, None, 'n12', 'n13']
    for rid in (14, 15):
        nonces.note('/p', rid, 'n%d' % rid, oldest_pending=12)
    assert sorted(nonces.by_origin['/p']) == [13, 14, 15]     # bounded: the lowest goes first
    nonces.note('/q', 1, None, oldest_pending=0)               # a request that names no nonce: none kept
    assert nonces.of('/q', 1) is None


def test_a_proxy_started_again_alone_behind_the_same_gate_gets_a_new_run_and_old_replies_are_refused():
    """Review of session 34 (of its own fix): the nonce was the gate's, so a Proxy started again alone (its
    gate running on) kept it, and the old reply for a reused id was still taken. A request whose id is below
    an oldest_pending its Proxy sent before starts a new run; calls of one run published out of order do not."""
    from aft_msgs.msg import Reply, Request
    runs = security.ProxyRuns()
    first = runs.nonce_for('/proxy', 9000, 9000)
    assert runs.nonce_for('/proxy', 9002, 9001) == first
    assert runs.nonce_for('/proxy', 9001, 9000) == first        # built before 9001's answer, published after
    assert runs.nonce_for('/proxy', 9003, 9003) == first
    second = runs.nonce_for('/proxy', 9001, 9001)               # below 9003: the Proxy started again, behind
    assert second != first and runs.current('/proxy') == second
    assert runs.nonce_for('/other', 5, 5) not in (first, second)   # each Proxy its own run

    server = gate()
    server.origins, server.replays = security.OriginBinding(None), security.ReplayGuard()
    server._peer = lambda party: (CLIENT.box_public, CLIENT.verify_public)
    server._open = lambda party, blob, header: security.open_sealed(SERVER, CLIENT.verify_public, blob, header)
    client = gate(side='client')
    client.me, client.server_party, client.not_for_me = CLIENT, 'server', 0
    client._peer = lambda party: (SERVER.box_public, SERVER.verify_public)
    client._open = lambda party, blob, header: security.open_sealed(CLIENT, SERVER.verify_public, blob, header)

    def call(rid, answer):
        client.ports.published.clear()
        client._on_request(Request(id=rid, origin='/proxy', client='/c', service_type='aft_msgs/Account',
                                   oldest_pending=rid, payload=b'deposit'))
        (_, sealed), = client.ports.published
        server.ports.published.clear()
        server.replays = security.ReplayGuard()   # (the backup's gate, which never saw the first run)
        server._on_request(sealed)
        server.ports.published.clear()
        server._on_reply(Reply(id=rid, origin='/proxy', client='/c', status=Reply.OK, payload=answer))
        (_, wire), = server.ports.published
        return wire
    captured = call(9000, b'old')
    client._on_reply(captured)
    call(9001, b'next')                             # the first run goes on ...
    fresh = call(9000, b'new')                      # ... then its Proxy starts again alone, id 9000 again
    client.ports.published.clear()
    client._on_reply(captured)
    (port, raised), = client.ports.published
    assert (port, raised.kind) == ('alarms', 'replay'), raised
    client.ports.published.clear()
    client._on_reply(fresh)
    (port, taken), = client.ports.published
    assert (port, bytes(taken.payload)) == ('replies_out', b'new')


def test_a_slow_calls_nonce_is_kept_while_thousands_of_later_calls_come_and_go():
    """Review of session 34 (of its own fix): the bound evicted the lowest id, a slow call's, at once again
    after each re-send: its reply was refused for good."""
    nonces = security.ReplyNonces(per_origin=8)
    nonces.note('/p', 10, 'slow', oldest_pending=10)
    for rid in range(11, 30):
        nonces.note('/p', rid, 'n', oldest_pending=10)
    assert nonces.of('/p', 10) is None                        # noted longest ago: gone ...
    nonces.note('/p', 10, 'slow', oldest_pending=10)          # ... the Proxy's re-send notes it again
    assert nonces.of('/p', 10) == 'slow' and len(nonces.by_origin['/p']) == 8


def test_an_insider_flooding_ids_it_never_confirms_is_held_at_its_quota_and_the_other_clients_are_served():
    """Issue 16, Limits of session 33: the Protocol's reply cache is shared, and at its bound refuses
    every new request, of every client. A certified insider sending ids it never confirms, from one
    origin or from one-shot ones, filled it (100 000 entries in 1.7 s) and denied service to all. Now
    its gate holds it at its quota: dropped, one alarm, the diagnostics say so; the honest party's
    calls go through all along; the insider's own calls pass again once it confirms its older ones."""
    from aft_msgs.msg import Request
    server = gate()
    server.origins, server.replays = security.OriginBinding(None), security.ReplayGuard()
    now = [0.0]
    server.quota = security.PartyQuota(limit=20, clock=lambda: now[0])
    insider = Party.generate('insider')
    keys = {'client': CLIENT, 'insider': insider}
    server._peer = lambda party: (keys[party].box_public, keys[party].verify_public)
    server._open = lambda party, blob, header: b'plaintext'

    def request(party, origin, rid, oldest):
        msg = Request(id=rid, origin=origin, client='/c', service_type='aft_msgs/Account', oldest_pending=oldest)
        msg.payload = security.seal(keys[party], SERVER.box_public, security.header_of(
            msg, security.REQUEST_FIELDS, 'server', '/ftm/pxy2pro'), b'deposit')
        return msg

    def forwarded():
        return [(m.origin, m.id) for name, m in server.ports.published if name == 'requests_out']

    def alarms():
        return [m for name, m in server.ports.published if name == 'alarms']
    for i in range(15):                                      # one origin that never confirms
        server._on_request(request('insider', '/evil', 1000 + i, 1000))
    for i in range(200):                                     # and one-shot origins
        server._on_request(request('insider', '/evil%d' % i, 7, 7))
        server._on_request(request('client', '/proxy', 100 + i, 100 + i))   # the honest client, confirming as it goes
    assert len([o for o, _ in forwarded() if o.startswith('/evil')]) == 20
    assert [(o, i) for o, i in forwarded() if o == '/proxy'] == [('/proxy', 100 + i) for i in range(200)]
    (told,) = alarms()
    assert (told.mechanism, told.kind) == ('sec', 'party_quota') and 'party insider has 20 requests outstanding' \
        in told.detail
    report = server._health()
    assert report.level == health.Level.WARN and 'insider' in report.message and report.value('at_quota') == 'insider'
    assert server.rejected == 195
    # the 195 refused one-shot origins left nothing behind: no binding, no floor, no watermark
    assert sorted(server.origins.bound) == sorted(server.quota.floors) == sorted(
        ['/evil', '/proxy'] + ['/evil%d' % i for i in range(5)])
    assert len(server.replays.watermarks) == 7
    # a re-send of a counted id passes (its Proxy waits for it); the insider confirming its calls has room again
    server._on_request(request('insider', '/evil', 1003, 1000))
    assert forwarded()[-1] == ('/evil', 1003)
    server._on_request(request('insider', '/evil', 1015, 1015))   # /evil confirms its 15: 5 held, this one counted
    assert forwarded()[-1] == ('/evil', 1015) and server.quota.count['insider'] == 6
    assert server.quota.at_quota() == []
    now[0] = 11.0
    for i in range(15):                                      # at its quota again (14 fit), 11 s on: told again
        server._on_request(request('insider', '/evil', 1016 + i, 1015))
    assert [a.kind for a in alarms()] == ['party_quota', 'party_quota']


@pytest.mark.parametrize('seed', range(20))
def test_a_partys_count_is_what_its_proxies_have_not_confirmed_under_random_traffic(seed):
    """Property: whatever the order of requests, re-sends, late copies and confirmations, a party's
    count is the number of distinct ids of its origins at or above the highest oldest_pending admitted
    from them, never above its limit; an origin with nothing outstanding is forgotten (the origins
    tracked are bounded); a refused request changes nothing (its floor neither: review of session 35);
    a party's refusal never depends on another party's traffic."""
    import random
    rng = random.Random(seed)
    quota = security.PartyQuota(limit=rng.randint(1, 12))
    model = {}      # origin -> (party, highest oldest_pending admitted, set of ids counted)
    origins = {'/a%d' % i: 'a' for i in range(3)}
    origins.update({'/b%d' % i: 'b' for i in range(3)})
    for _ in range(400):
        origin = rng.choice(sorted(origins))
        party = origins[origin]
        _, floor, ids = model.get(origin, (party, 0, set()))
        oldest = floor + rng.choice([0, 0, 0, 1, 2]) if rng.random() < 0.9 else max(0, floor - 1)
        rid = oldest + rng.randint(-1, 6)
        new_floor = max(floor, oldest)
        kept = {i for i in ids if i >= new_floor}
        fresh = rid >= new_floor and rid not in kept
        others = sum(len(v[2]) for o, v in model.items() if v[0] == party and o != origin)
        expect_refused = fresh and others + len(kept) + fresh > quota.limit
        try:
            quota.admit(party, origin, rid, oldest)
            refused = False
        except Rejected as e:
            assert e.kind == 'party_quota'
            refused = True
        assert refused == expect_refused, 'seed %d' % seed
        if not refused:
            ids = kept | ({rid} if fresh else set())
            if ids:
                model[origin] = (party, new_floor, ids)
            else:   # nothing outstanding: forgotten (an origin costs nothing once its calls are confirmed)
                model.pop(origin, None)
        for p in 'ab':
            held = sum(len(v[2]) for v in model.values() if v[0] == p)
            assert quota.count[p] == held <= quota.limit, 'seed %d: party %s' % (seed, p)
            assert sum(1 for v in model.values() if v[0] == p) <= quota.limit   # origins tracked, bounded
        assert {o: v[1] for o, v in model.items()} == quota.floors, 'seed %d' % seed


def test_a_refused_request_moves_no_floor_so_ids_below_it_cannot_pass_uncounted():
    """Review of session 35: a request refused at the quota still raised its origin's floor to its
    oldest_pending; neither the replay guard nor the Protocol ever saw it, so every id below that
    floor then passed uncounted (503 forwarded against a quota of 3), and filled the cache again."""
    from aft_msgs.msg import Request
    server = gate()
    server.origins, server.replays = security.OriginBinding(None), security.ReplayGuard()
    server.quota = security.PartyQuota(limit=3)
    server._peer = lambda party: (CLIENT.box_public, CLIENT.verify_public)
    server._open = lambda party, blob, header: b'plaintext'

    def send(origin, rid, oldest):
        msg = Request(id=rid, origin=origin, client='/c', service_type='aft_msgs/Account', oldest_pending=oldest)
        msg.payload = security.seal(CLIENT, SERVER.box_public, security.header_of(
            msg, security.REQUEST_FIELDS, 'server', '/ftm/pxy2pro'), b'deposit')
        server._on_request(msg)
    send('/x', 1, 0)
    send('/x', 2, 0)
    send('/b', 10 ** 9, 0)
    send('/b', 10 ** 9 + 1, 10 ** 9)     # refused: changes nothing
    for i in range(1, 500):
        send('/b', i, 0)                  # below the refused request's oldest_pending
    forwarded = [m for name, m in server.ports.published if name == 'requests_out']
    assert len(forwarded) == 3 and server.quota.count['client'] == 3 and server.quota.floors['/b'] == 0
    zero = security.PartyQuota(limit=0)   # no quota: nothing tracked at all
    for i in range(100):
        zero.admit('p', '/o%d' % i, 5, 0)
    assert zero.floors == {} and zero.ids == {} and not zero.count


def test_a_party_at_its_quota_is_told_again_only_after_it_had_room_and_some_seconds_passed():
    """Review of session 35: with a small quota, confirming one call and sending one more raised a new
    party_quota alarm every other request. A party is told again only once it had room and ``retell``
    seconds passed since it was last told."""
    now = [0.0]
    quota = security.PartyQuota(limit=2, clock=lambda: now[0], retell=10.0)
    quota.admit('p', '/o', 1, 1)
    quota.admit('p', '/o', 2, 1)

    def refused(rid, oldest):
        with pytest.raises(Rejected) as error:
            quota.admit('p', '/o', rid, oldest)
        return error.value.first
    assert refused(3, 1) is True and refused(4, 1) is False
    told = []
    for c in range(10, 100, 10):              # every 3 s: both confirmed (room), two more, one refused
        now[0] += 3.0
        quota.admit('p', '/o', c, c)
        quota.admit('p', '/o', c + 1, c)
        assert quota.at_quota() == []
        if refused(c + 2, c):
            told.append(now[0])
        assert quota.at_quota() == ['p']
    assert told == [12.0, 24.0]


def test_a_request_too_large_to_seal_is_answered_not_executed_by_the_clients_gate(monkeypatch):
    """Review of session 41: a call whose sealed request exceeded what a server gate takes (64 MiB) went
    on, was refused unread there with no reply, and its Proxy sent it again every half second for ever,
    refusing every other call meanwhile. The client's gate answers it NOT_EXECUTED at once, alarmed."""
    from aft_msgs.msg import Reply, Request
    from aft_ftm import change_model
    client = gate(side='client')
    client.me, client.server_party = CLIENT, 'server'
    client._peer = lambda party: (SERVER.box_public, SERVER.verify_public)
    monkeypatch.setattr(security, 'MAX_SEALED_BYTES', 4096)   # the bound, small: the same path
    small = Request(id=1, origin='/proxy', client='/c', service_type='aft_msgs/Account', oldest_pending=1, epoch=3,
                    payload=b'x' * 1000)
    client._on_request(small)
    assert [name for name, _ in client.ports.published] == ['requests_out']
    client.ports.published.clear()
    big = Request(id=2, origin='/proxy', client='/c', service_type='aft_msgs/Account', oldest_pending=1, epoch=3,
                  attempt=4, payload=b'x' * 4096)
    client._on_request(big)
    (_, raised), (port, told) = client.ports.published
    assert (raised.mechanism, raised.kind, port) == ('proxy', 'request_too_large', 'replies_out')
    assert (told.id, told.origin, told.status, told.epoch, told.attempt) == (2, '/proxy', Reply.NOT_EXECUTED, 3, 4)
    assert 'more than a SEC message may be (4096): not sent, nothing executed' in told.error
    assert ('/proxy', 2) not in client.sent and change_model.observed_fault(raised.mechanism, raised.kind) is None


def test_a_forged_message_does_not_evict_a_held_certificate_while_the_ca_is_unreachable(monkeypatch):
    """Review of session 41: a message with a bad signature claiming a party dropped the certificate held
    for it before anything was verified; with the CA unreachable, every genuine message of that party
    was then refused ca_unreachable. The held certificate stays; the forgery alone is refused."""
    from aft_msgs.msg import Request
    issuer = security.Issuer(CA, validity=1000.0)
    issuer.set_keys('client', CLIENT.box_public, CLIENT.verify_public)
    server = gate()
    server.previous_me, server.refetched, server.ca_verify = None, {}, CA.verify_public
    server.book.on_status(*issuer.status(0.0), now=0.0)
    cert, signature = issuer.certificate('client', 0.0)
    server.book.add('client', security.check_certificate(CA.verify_public, 'client', cert.box_public,
                                                         cert.verify_public, cert.serial, cert.not_after,
                                                         signature), 0.0)
    monkeypatch.setattr(sec_nodes.time, 'monotonic', lambda: 1.0)
    asked = []

    def unreachable(party):
        asked.append(party)
        raise Rejected('ca_unreachable', 'the CA did not answer')
    server._ask_ca = unreachable

    def sealed(signer, rid):
        msg = Request(id=rid, origin='/proxy', client='/c', service_type='aft_msgs/Account', oldest_pending=rid)
        header = security.header_of(msg, security.REQUEST_FIELDS, 'server', '/ftm/pxy2pro')
        return security.seal(signer, SERVER.box_public, header, b'deposit'), header
    forger = Party.generate('client')   # claims to be client, with a key of its own
    blob, header = sealed(forger, 1)
    with pytest.raises(Rejected) as refused:
        server._open('client', blob, header)
    assert refused.value.kind == 'bad_signature' and asked == ['client']   # asked again; the CA silent
    blob, header = sealed(CLIENT, 2)
    assert server._open('client', blob, header) == b'deposit' and asked == ['client']   # the held one serves


def test_a_reply_too_large_to_seal_becomes_a_sealed_error_saying_the_request_was_executed(monkeypatch):
    """Review of session 41: a reply larger sealed than a client's gate takes was refused there unread;
    its Proxy asked again every half second for ever, the Protocol's cache answering the same. The
    server's gate seals an ERROR instead, saying the request was executed, and alarms."""
    from aft_msgs.msg import Reply
    from aft_ftm import change_model
    server, client = reply_gates()
    server.nonces.note('/proxy', 7, client.runs.nonce_for('/proxy', 7, 7), 7)
    client.sent[('/proxy', 7)] = None
    monkeypatch.setattr(security, 'MAX_SEALED_BYTES', 4096)
    server._on_reply(Reply(id=7, origin='/proxy', client='/c', status=Reply.OK, payload=b'x' * 4096, epoch=2))
    (_, raised), (port, wire) = server.ports.published
    assert (raised.mechanism, raised.kind, port, wire.status) == ('server', 'reply_too_large', 'replies_out', Reply.ERROR)
    assert len(bytes(wire.payload)) < 4096 and change_model.observed_fault(raised.mechanism, raised.kind) is None
    client._open = lambda party, blob, header: security.open_sealed(CLIENT, SERVER.verify_public, blob, header)
    client._on_reply(wire)
    (port, told), = client.ports.published
    assert (port, told.status, told.id, told.epoch) == ('replies_out', Reply.ERROR, 7, 2)
    assert 'the request was executed; its answer cannot be carried' in told.error


def logged_gate(path):
    """A server gate whose replay floors are in the log at path, started as a gate starts (setup reads it)."""
    from aft_ftm import replay_log
    server = gate()
    server.origins, server.replays = security.OriginBinding(None), security.ReplayGuard()
    server._peer = lambda party: (CLIENT.box_public, CLIENT.verify_public)
    server._open = lambda party, blob, header: security.open_sealed(SERVER, CLIENT.verify_public, blob, header)
    server.replay_log = replay_log.ReplayLog(str(path))
    server.replays.restore(server.replay_log.open())
    return server


def sealed_request(rid, oldest, origin='/proxy'):
    from aft_msgs.msg import Request
    msg = Request(id=rid, origin=origin, client='/c', service_type='aft_msgs/Account', oldest_pending=oldest)
    header = security.header_of(msg, security.REQUEST_FIELDS, 'server', '/ftm/pxy2pro')
    msg.payload = security.seal(CLIENT, SERVER.box_public, header, b'deposit 50')
    return msg


def test_a_gate_started_again_refuses_every_request_an_earlier_run_let_through_and_serves_the_next(tmp_path):
    """Issue 16: replay protection lived in the gate's memory; a deployment started again (a lone primary,
    both sites) executed every captured request again. The floors are on disk before a request goes on."""
    from aft_msgs.msg import Reply
    path = tmp_path / 'replay' / 'master.sec_gate.log'
    first = logged_gate(path)
    captured = [sealed_request(7000 + i, 7000 + i) for i in range(5)]   # a client calling one at a time
    for request in captured:
        first._on_request(request)
    assert [name for name, _ in first.ports.published] == ['requests_out'] * 5
    first.replay_log.close()                                            # the whole site powered off

    again = logged_gate(path)
    for request in captured:                                            # the attacker replays all of them
        again._on_request(request)
    published = again.ports.published
    assert [m for name, m in published if name == 'requests_out'] == [], 'a replay went on to the Protocol'
    raised = [m for name, m in published if name == 'alarms']
    assert [a.kind for a in raised] == ['replay'] * 4 + ['earlier_run']
    told = [m for name, m in published if name == 'replies_out']
    assert [t.status for t in told] == [Reply.STALE_ID] * 4 + [Reply.ERROR]   # answered ids: told to renumber
    assert all(t.oldest_pending == 7005 for t in told[:4])
    # 7004 was the last call: only the next request's watermark would have confirmed its reply. It may
    # have executed: never executed again, never told to renumber; this site serves, so the call ends,
    # "outcome unknown" (sealed: the wire says only that there is an error), alarmed once however often
    # it is sent again.
    header = security.header_of(told[4], security.REPLY_FIELDS, 'client', '/ftm/pxy2pro')
    assert security.nonce_of(told[4].payload) is None                  # (its request named none)
    text, _ = security.unframe_error(security.open_sealed(CLIENT, SERVER.verify_public, told[4].payload, header))
    assert text.startswith('outcome unknown: request /proxy/7004 was let through by an earlier run'), text
    again.ports.published.clear()
    again._on_request(captured[-1])
    assert [(n, m.status) for n, m in again.ports.published] == [('replies_out', Reply.ERROR)]
    assert again.rejected == 6
    again.ports.published.clear()
    again._on_request(sealed_request(7005, 7005))                       # the client's next call goes on
    (port, plain), = again.ports.published
    assert (port, plain.id, bytes(plain.payload)) == ('requests_out', 7005, b'deposit 50')
    assert again._health().value('replay_log') == str(path)
    again.replay_log.close()


def test_a_backup_started_again_refuses_an_earlier_runs_request_without_answering_it(tmp_path):
    """A site that re-joins meets a call still in flight from before it stopped: its primary answers it. The
    backup's gate refuses it (alarm) and says nothing, not "outcome unknown" before the primary's answer."""
    path = tmp_path / 'slave.sec_gate.log'
    first = logged_gate(path)
    first._on_request(sealed_request(10, 10))
    first.replay_log.close()
    backup = logged_gate(path)
    backup.site_role, backup.witness = SiteRole('slave'), '/aft/witness/request'
    backup._on_request(sealed_request(10, 10))
    assert [(n, m.kind) for n, m in backup.ports.published] == [('alarms', 'earlier_run')]   # no configuration yet
    backup.site_role.on_configuration(5, 'master', 'slave')
    backup._on_request(sealed_request(10, 10))
    assert [n for n, _ in backup.ports.published] == ['alarms']
    backup.site_role.on_configuration(6, 'slave', '')                  # its primary failed: it serves alone
    backup._on_request(sealed_request(10, 10))
    assert [n for n, _ in backup.ports.published] == ['alarms', 'replies_out']
    backup.replay_log.close()


def test_a_request_whose_floors_cannot_be_written_is_not_let_through_and_the_site_fail_stops(tmp_path, monkeypatch):
    """A log that fails a write refused every request for ever with no failover (review of session 44): the
    site now fail-stops, once, so that its peer takes over; alone (the only copy of the state) it stays."""
    import os
    from aft_ftm import change_model
    server = logged_gate(tmp_path / 'r.log')
    server.site_role, server.fail_stopped = SiteRole('master'), False
    server.site_role.on_configuration(5, 'master', '')                 # alone first
    server._on_request(sealed_request(10, 10))
    monkeypatch.setattr(os, 'fdatasync', lambda fd: (_ for _ in ()).throw(OSError(28, 'No space left on device')))
    server.ports.published.clear()
    server._on_request(sealed_request(11, 11))
    (port, raised), = server.ports.published
    assert (port, raised.kind) == ('alarms', 'replay_log') and 'No space left' in raised.detail
    assert change_model.observed_fault('sec', 'replay_log') is None     # the disk's fault, not an attack
    report = server._health()
    assert report.level == health.Level.ERROR and 'every request is refused' in report.message
    server.site_role.on_configuration(6, 'master', 'slave')            # a backup joined: it can take over
    for rid in (12, 13):
        server._on_request(sealed_request(rid, rid))
    kinds = [(n, getattr(m, 'kind', None) or getattr(m, 'site', None)) for n, m in server.ports.published[1:]]
    assert kinds == [('alarms', 'replay_log'), ('fail_stop', 'master'), ('alarms', 'fail_stop'),
                     ('alarms', 'replay_log')], kinds                   # nothing let through; one fail-stop
    server.replay_log.close()


def test_a_gate_without_a_replay_log_says_its_floors_are_in_memory_only():
    server = gate(tls=True)
    report = server._health()
    assert report.level == health.Level.WARN and 'replay floors in memory only' in report.message
    assert report.value('replay_log') == 'none'
    assert gate(side='client', tls=True)._health().level == health.Level.OK


# -- the peer gate's floors, at a join ----------------------------------------------------------------
KEYS = {'client': CLIENT, 'server': SERVER}


def paired_gate(path, site):
    """A logged server gate of site that opens what the client and its own party (the peer gate) sealed."""
    server = logged_gate(path)
    server._open = lambda party, blob, header: security.open_sealed(SERVER, KEYS[party].verify_public, blob, header)
    server.site_role, server.fail_stopped = SiteRole(site), False
    server.FLOOR_RETRY = 0.0
    return server


class Asked(object):
    """rospy.ServiceProxy's stand-in: each call answered by answer(nonce), the services asked kept."""

    def __init__(self, answer):
        self.answer, self.services = answer, []

    def __call__(self, service, cls):
        self.services.append(service)
        return lambda nonce: self.answer(nonce)


def served_by(peer):
    return lambda nonce: peer._serve_floors(type('Req', (), {'nonce': nonce})())


def test_a_site_back_from_down_learns_its_peers_floors_and_refuses_replays_of_what_it_missed(tmp_path, monkeypatch):
    """Issue 16, "replay protection across a re-integration": a site's gate records what it sees while it runs.
    SLAVE was down while a Proxy made 20 calls through MASTER, then the Proxy fell silent; an attacker who
    captured them replays them to SLAVE once paired again. Before, SLAVE's gate let every one through (only
    the Protocol behind it, within its reply cache, stood in the way); now SLAVE asks MASTER's gate for its
    floors at the join and refuses them, alarmed, and keeps the floors on its own log."""
    master = paired_gate(tmp_path / 'master.log', 'master')
    slave = paired_gate(tmp_path / 'slave.log', 'slave')
    captured = [sealed_request(100 + i, 100 + i) for i in range(20)]
    for request in captured:
        master._on_request(request)
    control = paired_gate(tmp_path / 'control.log', 'slave')   # the gate as it was: no floors asked
    control._on_request(captured[3])
    assert [n for n, _ in control.ports.published] == ['requests_out']   # the gap this closes
    control.replay_log.close()

    asked = Asked(served_by(master))
    monkeypatch.setattr(rospy, 'ServiceProxy', asked)
    monkeypatch.setattr(rospy, 'get_name', lambda: '/slave/sec_gate')
    slave._pull_floors('master')
    assert asked.services == ['/master/sec_gate/replay_floors']
    assert slave.floors_learned == 1 and slave._health().value('replay_floors_learned') == '1'
    for request in captured[:-1]:
        slave._on_request(request)
    published = slave.ports.published
    assert [m for n, m in published if n == 'requests_out'] == [], 'a replay passed the re-joined gate'
    assert [m.kind for n, m in published if n == 'alarms'] == ['replay'] * 19
    # the last call may still be in flight at MASTER: not a replay, it passes (the Protocol drops a copy)
    slave.ports.published.clear()
    slave._on_request(captured[-1])
    assert [n for n, _ in slave.ports.published] == ['requests_out']
    slave.replay_log.close()
    from aft_ftm import replay_log
    again = replay_log.ReplayLog(str(tmp_path / 'slave.log'))
    assert again.open()['/proxy'][0] == 119                            # on SLAVE's own log: it holds restarted
    again.close()
    master.replay_log.close()


def test_learned_floors_only_rise_and_never_make_a_call_in_flight_an_earlier_run():
    guard = security.ReplayGuard()
    guard.advance('/p', 50, 60)
    assert guard.learn({'/p': 40, '/q': 7, '/r': 0}) == ['/q']
    assert guard.floors('/p') == (50, 60) and guard.floors('/q') == (7, 0) and guard.earlier == {}
    guard.check('/q', 7)                                                # in flight at the peer: passes
    with pytest.raises(Rejected) as e:
        guard.check('/q', 6)
    assert e.value.kind == 'replay'


@pytest.mark.parametrize('answer, kind', [
    ('signed by another party', 'bad_signature'),
    ('an old answer, another nonce', 'tampered'),
    ('not a list of pairs', 'malformed'),
])
def test_a_forged_or_replayed_floors_answer_is_refused_alarmed_and_changes_nothing(tmp_path, monkeypatch, answer, kind):
    """An attacker who registers /master/sec_gate/replay_floors (ROS 1 lets any node) answers with floors
    that would make SLAVE refuse every honest call: refused, with the refusal's alarm, then
    floors_unavailable once the tries are spent; SLAVE's floors and log unchanged."""
    slave = paired_gate(tmp_path / 'slave.log', 'slave')
    slave.FLOOR_TRIES = 2
    huge = {'/proxy': 2 ** 40}
    forged = {'signed by another party': lambda nonce: security.seal(CLIENT, SERVER.box_public,
                                                                     security.floors_header('server', nonce),
                                                                     b'[["/proxy", 1099511627776]]'),
              'an old answer, another nonce': lambda nonce: security.seal_floors(SERVER, huge, 'an-old-nonce'),
              'not a list of pairs': lambda nonce: security.seal(SERVER, SERVER.box_public,
                                                                 security.floors_header('server', nonce),
                                                                 b'{"/proxy": 1099511627776}')}[answer]
    monkeypatch.setattr(rospy, 'ServiceProxy', Asked(lambda nonce: type('R', (), {'sealed': forged(nonce)})()))
    monkeypatch.setattr(rospy, 'get_name', lambda: '/slave/sec_gate')
    slave._pull_floors('master')
    kinds = [m.kind for n, m in slave.ports.published if n == 'alarms']
    assert kinds == [kind, kind, 'floors_unavailable'], kinds
    assert slave.replays.watermarks == {} and slave.floors_learned == 0
    slave._on_request(sealed_request(5, 5))                           # an honest call still passes
    assert [n for n, _ in slave.ports.published][-1] == 'requests_out'
    slave.replay_log.close()


def test_a_peer_gate_that_does_not_answer_raises_floors_unavailable_and_a_warn_not_an_attack(tmp_path, monkeypatch):
    from aft_ftm import change_model
    slave = paired_gate(tmp_path / 'slave.log', 'slave')
    slave.FLOOR_TRIES = 3

    def gone(nonce):
        raise rospy.ServiceException('unable to connect to service: [Errno 111] Connection refused')
    monkeypatch.setattr(rospy, 'ServiceProxy', Asked(gone))
    monkeypatch.setattr(rospy, 'get_name', lambda: '/slave/sec_gate')
    slave._pull_floors('master')
    (port, raised), = slave.ports.published
    assert (port, raised.kind) == ('alarms', 'floors_unavailable') and 'Connection refused' in raised.detail
    assert change_model.observed_fault('sec', 'floors_unavailable') is None
    report = slave._health()
    assert report.level == health.Level.WARN and "the replay floors of master's gate not learned" in report.message
    slave.replay_log.close()


def test_each_pairing_of_the_site_asks_its_peer_once_and_nothing_else_asks():
    server = gate()
    server.site_role = SiteRole('slave')
    asked = []
    done = threading.Event()
    server._pull_floors = lambda peer, **_: (asked.append(peer), done.set())
    for configuration in [(3, 'master', ''), (4, 'master', 'other'), (5, 'master', 'slave'), (5, 'master', 'slave'),
                          (6, 'slave', ''), (7, 'slave', 'master')]:
        done.clear()
        server._on_configuration(*configuration)
        done.wait(0.5 if configuration[0] in (5, 7) else 0.05)
    assert asked == ['master', 'master']                              # epochs 5 and 7, once each


def test_a_peer_gate_paused_through_the_join_is_asked_again_and_its_floors_learned_once_it_answers(tmp_path,
                                                                                                    monkeypatch):
    """Issue 16: MASTER's gate paused (SIGSTOP, a GC pause, a loaded board) for longer than SLAVE's first
    tries at the join. Before, SLAVE raised floors_unavailable and never asked again in that pairing: every
    replay of what it missed passed its gate until the next failover. Now it asks again, FLOOR_LATER s apart,
    learns the floors once MASTER answers, refuses the replays and its WARN clears; one alarm, not one per ask."""
    master = paired_gate(tmp_path / 'master.log', 'master')
    slave = paired_gate(tmp_path / 'slave.log', 'slave')
    slave.FLOOR_TRIES, slave.FLOOR_LATER, slave.FLOOR_LATER_MAX = 2, 0.001, 0.004
    captured = [sealed_request(100 + i, 100 + i) for i in range(5)]
    for request in captured:
        master._on_request(request)
    paused = {'asks': 0}

    def answer(nonce):
        paused['asks'] += 1
        if paused['asks'] <= 6:
            raise rospy.ROSException('timeout exceeded while waiting for service /master/sec_gate/replay_floors')
        return served_by(master)(nonce)
    monkeypatch.setattr(rospy, 'ServiceProxy', Asked(answer))
    monkeypatch.setattr(rospy, 'get_name', lambda: '/slave/sec_gate')
    slave.floors_asked = (5, 'master')
    slave._follow_floors(5, 'master')
    assert paused['asks'] == 7 and slave.floors_learned == 1 and slave.floors_missing is None
    assert [m.kind for n, m in slave.ports.published if n == 'alarms'] == ['floors_unavailable']
    assert 'replay floors' not in slave._health().message and slave._health().value('replay_floors_learned') == '1'
    slave.ports.published.clear()
    slave._on_request(captured[0])
    assert [m.kind for n, m in slave.ports.published if n == 'alarms'] == ['replay']
    slave.replay_log.close()
    master.replay_log.close()


def test_a_silent_peer_is_asked_again_only_while_its_pairing_lasts(tmp_path, monkeypatch):
    """The asking ends with the pairing (a later configuration asks for itself): bounded, no thread per
    configuration left asking a peer that is no longer the peer."""
    slave = paired_gate(tmp_path / 'slave.log', 'slave')
    slave.FLOOR_TRIES, slave.FLOOR_LATER, slave.FLOOR_LATER_MAX = 1, 0.001, 0.001
    asks = []

    def gone(nonce):
        asks.append(nonce)
        if len(asks) == 4:
            slave._on_configuration(*ending)   # the witness's next configuration, meanwhile
        raise rospy.ServiceException('unable to connect to service: [Errno 111] Connection refused')
    monkeypatch.setattr(rospy, 'ServiceProxy', Asked(gone))
    monkeypatch.setattr(rospy, 'get_name', lambda: '/slave/sec_gate')
    for ending in [(6, 'slave', ''), (6, 'master', '')]:   # SLAVE alone, promoted; SLAVE excluded
        asks.clear()
        slave.ports.published.clear()
        slave.floors_asked = (5, 'master')
        slave._follow_floors(5, 'master')
        assert len(asks) == 4 and slave.floors_learned == 0 and slave.floors_asked == (6, None), ending
        assert [m.kind for n, m in slave.ports.published if n == 'alarms'] == ['floors_unavailable']
        assert "the replay floors of master's gate not learned" in slave._health().message
    slave.replay_log.close()


def test_an_ask_still_unanswered_is_not_doubled_and_an_old_pairings_failure_never_sticks(tmp_path, monkeypatch):
    """rospy's call has no timeout: each ask of a paused peer leaves its thread blocked until the peer
    answers. Asking again meanwhile would pile threads up, one per ask for as long as the pairing lasts.
    And a failure of an older pairing's ask, seen after a later pairing learned its floors, must not put
    the WARN back."""
    slave = paired_gate(tmp_path / 'slave.log', 'slave')
    slave.FLOOR_TRIES, slave.FLOOR_TIMEOUT = 3, 0.05
    release, calls = threading.Event(), []

    def paused(nonce):
        calls.append(nonce)
        release.wait(5.0)
        raise rospy.ServiceException('unable to connect to service: [Errno 111] Connection refused')
    monkeypatch.setattr(rospy, 'ServiceProxy', Asked(paused))
    monkeypatch.setattr(rospy, 'get_name', lambda: '/slave/sec_gate')
    slave.floors_asked = (5, 'master')
    assert slave._pull_floors('master', pairing=(5, 'master')) is False
    assert len(calls) == 1 and slave.floors_missing == ('master', 'an earlier ask still unanswered')
    slave.floors_asked = (6, 'other')     # another peer is asked all the same
    assert slave._pull_floors('other', tries=1, pairing=(6, 'other')) is False and len(calls) == 2
    release.set()
    assert slave.floor_calls['master'].wait(2.0) and slave.floor_calls['other'].wait(2.0)
    slave.floors_asked, slave.floors_missing = (7, 'other'), None   # a later pairing, its floors learned
    assert slave._pull_floors('master', pairing=(5, 'master')) is False
    assert slave.floors_missing is None and "not learned" not in slave._health().message
    slave.replay_log.close()


def freshness_pair(restored=None):
    """A server gate that asks every origin to prove itself fresh (floors restored from an earlier run,
    if given), and a client gate of party client: both real, their keys real, their ports fakes."""
    server = gate(ask_fresh=True)
    server.origins, server.replays = security.OriginBinding(None), security.ReplayGuard()
    server.replays.restore(restored or {})
    server._peer = lambda party: (CLIENT.box_public, CLIENT.verify_public)
    server._open = lambda party, blob, header: security.open_sealed(SERVER, CLIENT.verify_public, blob, header)
    client = gate(side='client')
    client.me, client.server_party = CLIENT, 'server'
    client._peer = lambda party: (SERVER.box_public, SERVER.verify_public)
    client._open = lambda party, blob, header: security.open_sealed(CLIENT, SERVER.verify_public, blob, header)
    return server, client


def sealed_by(client, rid, oldest_pending, payload=b'deposit 50'):
    """What the client gate publishes for the Proxy's request rid."""
    from aft_msgs.msg import Request
    client.ports.published.clear()
    client._on_request(Request(id=rid, origin='/proxy', client='/c', service_type='aft_msgs/Account',
                               oldest_pending=oldest_pending, payload=payload))
    (port, sealed), = client.ports.published
    assert port == 'requests_out'
    return sealed


def test_replays_taken_before_an_origins_next_request_are_now_asked_to_prove_they_are_fresh_and_never_pass():
    """Issue 16, left since session 44: a server gate whose floors are behind (its replay log lost, or its
    site down while the peer served and first to serve after the whole service started again) took every
    replay of what it missed until the origin's next real request raised its watermark. Seeded: a Proxy
    sent ids 1..n through the peer while this gate knew floors up to k only; the attacker replays ids
    k..n in a random order before and after the Proxy's next call. None passes; the Proxy's call does, at
    the cost of one challenge round trip; every replay after it is refused as a replay, with its alarm."""
    import random
    from aft_msgs.msg import Reply
    seed = random.randrange(1 << 30)
    rng = random.Random(seed)
    k, n = rng.randint(1, 20), rng.randint(25, 60)
    server, client = freshness_pair(restored={'/proxy': (k, k)})
    captured = {rid: sealed_by(client, rid, rid) for rid in range(k + 1, n + 1)}   # sent through the peer's gate
    client.sent.clear()
    client.unsealed.clear()
    control, _ = freshness_pair(restored={'/proxy': (k, k)})   # the code before: nobody asked to prove it
    control.freshness = security.Freshness(ask=False)
    control._on_request(captured[n])
    assert [port for port, _ in control.ports.published] == ['requests_out'], 'the control: the replay passed'
    before = rng.sample(sorted(captured), rng.randint(0, len(captured)))
    server.ports.published.clear()
    for rid in before:
        server._on_request(captured[rid])
    assert not [m for port, m in server.ports.published if port == 'requests_out'], 'seed %d: a replay passed' % seed
    challenges = [m for port, m in server.ports.published if port == 'replies_out']
    assert len(challenges) == len(before) and all(m.status == Reply.CHALLENGE for m in challenges), seed
    for challenge in challenges:    # the client gate, which has none of them pending, re-sends nothing
        client.ports.published.clear()
        client._on_reply(challenge)
        assert client.ports.published == [], seed

    # The Proxy's next call (id n + 1, every id below answered). Its gate heard the challenge already if a
    # replay drew one (sealed for it: only it can read the nonce), and the call names it at once; else the
    # call is asked once, its gate seals it again naming the challenge (the Proxy sees nothing), and taken.
    server.ports.published.clear()
    server._on_request(sealed_by(client, n + 1, n + 1))
    if not before:
        (port, asked), = server.ports.published
        assert (port, asked.status) == ('replies_out', Reply.CHALLENGE), seed
        client.ports.published.clear()
        client._on_reply(asked)
        (port, again), = client.ports.published
        assert port == 'requests_out' and security.challenge_of(again.payload) is not None, seed
        server.ports.published.clear()
        server._on_request(again)
    (port, passed), = server.ports.published
    assert (port, passed.id, bytes(passed.payload)) == ('requests_out', n + 1, b'deposit 50'), seed
    assert server.replays.floors('/proxy')[0] == n + 1 and '/proxy' in server.freshness.confirmed

    # Every replay now: refused as a replay, with its alarm; nothing goes on.
    after = rng.sample(sorted(captured), rng.randint(1, len(captured)))
    server.ports.published.clear()
    for rid in after:
        server._on_request(captured[rid])
    assert not [m for port, m in server.ports.published if port == 'requests_out'], 'seed %d' % seed
    kinds = [m.kind for port, m in server.ports.published if port == 'alarms']
    assert kinds == ['replay'] * len(after), (seed, kinds)
    # The origin's later calls pass at once (no challenge), and a replayed challenged copy goes no further.
    server.ports.published.clear()
    server._on_request(sealed_by(client, n + 2, n + 2))
    assert [port for port, _ in server.ports.published] == ['requests_out'], seed


def test_a_challenge_is_sealed_for_the_party_that_signed_and_a_forged_or_odd_one_changes_nothing():
    from aft_msgs.msg import Reply
    server, client = freshness_pair()
    server.ports.published.clear()
    server._on_request(sealed_by(client, 7, 7))
    (_, asked), = server.ports.published
    assert asked.status == Reply.CHALLENGE and asked.error == ''
    # Another party (here the server's own key) cannot read the nonce: sealed for the client.
    with pytest.raises(Rejected):
        security.open_sealed(SERVER, SERVER.verify_public, asked.payload, security.header_of(
            asked, security.REPLY_FIELDS, 'client', '/ftm/pxy2pro'))
    # A challenge signed by another key than the server's: refused with its alarm, nothing sent again.
    forger = Party.generate('server')
    forged = Reply(id=7, origin='/proxy', client='/c', oldest_pending=7, status=Reply.CHALLENGE)
    header = security.header_of(forged, security.REPLY_FIELDS, 'client', '/ftm/pxy2pro')
    header['nonce'] = client.runs.current('/proxy')
    forged.payload = security.seal(forger, CLIENT.box_public, header, security.frame_error('', b'00ff'))
    client.ports.published.clear()
    client._on_reply(forged)
    (port, raised), = client.ports.published
    assert (port, raised.kind) == ('alarms', 'bad_signature')
    # A genuine challenge whose nonce is not one: malformed, nothing sent again.
    odd = Reply(id=7, origin='/proxy', client='/c', oldest_pending=7, status=Reply.CHALLENGE)
    odd.payload = server._seal_reply(odd, CLIENT.box_public, 'client', client.runs.current('/proxy'), '',
                                     b'not a nonce!')
    client.ports.published.clear()
    client._on_reply(odd)
    (port, raised), = client.ports.published
    assert (port, raised.kind) == ('alarms', 'malformed') and client.challenges == {}
    # A request naming a challenge it was not asked (a guess): asked again, not taken.
    client.challenges['/proxy'] = '00' * 16
    server.ports.published.clear()
    server._on_request(sealed_by(client, 8, 8))
    (port, asked_again), = server.ports.published
    assert (port, asked_again.status) == ('replies_out', Reply.CHALLENGE)


def test_two_server_gates_each_ask_once_and_both_take_the_origin_after_one_round_each():
    """PBR and LFR: both sites' gates see a Proxy's requests; each asks with its own nonce. The client gate
    answers each; every later request passes both without a challenge."""
    from aft_msgs.msg import Reply
    first, client = freshness_pair()
    second, _ = freshness_pair()
    sealed = sealed_by(client, 100, 100)
    for server in (first, second):
        server.ports.published.clear()
        server._on_request(sealed)
    resent = []
    for server in (first, second):
        (_, asked), = server.ports.published
        assert asked.status == Reply.CHALLENGE
        client.ports.published.clear()
        client._on_reply(asked)
        resent += [m for _, m in client.ports.published]
    assert len(resent) == 2
    # The first gate takes the copy naming its nonce, then the other as a re-send (the Protocol behind
    # drops a re-send's copy); the second is asked again by the first copy, and takes the one naming its own.
    for server, taken in ((first, [100, 100]), (second, [100])):
        server.ports.published.clear()
        for copy in resent:
            server._on_request(copy)
        assert [m.id for port, m in server.ports.published if port == 'requests_out'] == taken
    for server in (first, second):
        server.ports.published.clear()
        server._on_request(sealed_by(client, 101, 101))
        assert [port for port, _ in server.ports.published] == ['requests_out']


def test_an_origin_that_never_proves_fresh_is_said_once_and_is_no_attack_for_the_change_model(monkeypatch):
    from aft_ftm import change_model
    fresh = security.Freshness()
    assert fresh.check('/proxy', None, now=10.0) is not None
    assert fresh.unanswered(now=14.0, wait=5.0) == []
    assert fresh.unanswered(now=15.5, wait=5.0) == [('/proxy', 5.5)]
    assert fresh.unanswered(now=30.0, wait=5.0) == []          # once
    nonce = fresh.check('/proxy', 'a guess', now=31.0)
    assert fresh.check('/proxy', nonce, now=31.0) is None and '/proxy' in fresh.asked   # answered, not yet let through
    fresh.confirm('/proxy')
    assert fresh.asked == {} and fresh.confirmed == {'/proxy': nonce}
    assert fresh.check('/proxy', None, now=32.0) is None        # confirmed for the rest of the run
    bounded = security.Freshness(limit=3)
    for i in range(10):
        bounded.check('/p%d' % i, None, now=0.0)
    assert list(bounded.asked) == ['/p7', '/p8', '/p9']
    assert security.Freshness(ask=False).check('/proxy', None, now=0.0) is None
    assert change_model.observed_fault('sec', 'unanswered_challenge') is None

    server, _ = freshness_pair()
    server.freshness.check('/proxy', None, now=0.0)
    ticks = iter([False, True])
    monkeypatch.setattr(sec_nodes.rospy, 'is_shutdown', lambda: next(ticks))
    monkeypatch.setattr(sec_nodes.rospy, 'get_name', lambda: '/master/sec_gate')
    monkeypatch.setattr(sec_nodes.time, 'sleep', lambda s: None)
    server._watch_challenges()
    (port, raised), = server.ports.published
    assert (port, raised.mechanism, raised.kind) == ('alarms', 'sec', 'unanswered_challenge')
    assert '/proxy' in raised.detail and '/master/sec_gate' in raised.detail


def answered_through(server, client, sealed):
    """sealed delivered to server; if challenged, the client gate answers and its copy is delivered:
    what the server published last."""
    from aft_msgs.msg import Reply
    server.ports.published.clear()
    server._on_request(sealed)
    out = list(server.ports.published)
    if len(out) == 1 and out[0][1].status == Reply.CHALLENGE:
        client.ports.published.clear()
        client._on_reply(out[0][1])
        (port, again), = client.ports.published
        assert port == 'requests_out'
        server.ports.published.clear()
        server._on_request(again)
        out = list(server.ports.published)
    return out


def test_an_origin_is_fresh_only_once_its_request_is_let_through_not_when_the_quota_refuses_it():
    from aft_msgs.msg import Reply
    """Review of session 48 (of its own change): the origin was confirmed before the party's quota refused
    the request that answered; its watermark stayed behind, and once the party had room a replay passed
    without a challenge. A flood of one-shot origins at the quota filled the confirmed set too."""
    k = 5
    server, client = freshness_pair(restored={'/proxy': (k, k)})
    captured = sealed_by(client, 7, 7)                                 # answered through the peer meanwhile
    client.sent.clear()
    client.unsealed.clear()
    server.quota = security.PartyQuota(limit=2)
    server.quota.admit('client', '/other', 1, 1)                       # the party at its quota
    server.quota.admit('client', '/other', 2, 1)
    out = answered_through(server, client, sealed_by(client, 11, 11))
    assert [getattr(m, 'kind', None) for _, m in out] == ['party_quota'] and server.freshness.confirmed == {}
    server.quota.admit('client', '/other', 3, 3)                       # room again
    server.ports.published.clear()
    server._on_request(captured)                                       # the replay: asked, not let through
    assert [m.status for port, m in server.ports.published] == [Reply.CHALLENGE]
    for i in range(50):                                                # one-shot origins at the quota
        server.quota = security.PartyQuota(limit=1)
        server.quota.admit('client', '/held', 1, 1)
        answered_through(server, client, sealed_by_origin(client, '/oneshot%d' % i))
    assert len(server.freshness.confirmed) == 0


def sealed_by_origin(client, origin, rid=1):
    from aft_msgs.msg import Request
    client.ports.published.clear()
    client._on_request(Request(id=rid, origin=origin, client='/c', service_type='aft_msgs/Account',
                               oldest_pending=rid, payload=b'deposit 1'))
    (_, sealed), = client.ports.published
    return sealed


def test_a_challenge_for_a_request_answered_meanwhile_is_not_sealed_again_nor_a_new_run():
    """Review of session 48: the re-seal went through the Proxy's numbering; with the request answered and
    the Proxy's next call out meanwhile, the older id started a new run, and the reply to the pending call
    was refused as a replay. Sealed again only if still pending, with its run's nonce."""
    server, client = freshness_pair()
    r10 = sealed_by(client, 10, 10)
    server.ports.published.clear()
    server._on_request(r10)
    (_, challenge), = server.ports.published
    run = client.runs.current('/proxy')
    real_peer = client._peer

    def peer(party):   # the other threads run here: 10 answered, the Proxy's next call sent
        client._peer = real_peer
        client.sent.pop(('/proxy', 10))
        client.unsealed.pop(('/proxy', 10))
        sealed_by(client, 11, 11)
        return real_peer(party)
    client._peer = peer
    client.ports.published.clear()
    client._on_reply(challenge)
    assert [m.id for _, m in client.ports.published] == [11]        # the next call only; 10 not sealed again
    assert client.runs.current('/proxy') == run
    assert ('/proxy', 10) not in client.sent and ('/proxy', 11) in client.sent
    # The next call names the challenge its gate heard (same run): let through at once.
    r11 = client.sent[('/proxy', 11)]
    assert security.nonce_of(r11.payload) == run and security.challenge_of(r11.payload) is not None
    server.ports.published.clear()
    server._on_request(r11)
    assert [(port, m.id) for port, m in server.ports.published] == [('requests_out', 11)]


def test_a_request_that_could_not_be_sealed_again_with_a_challenge_is_refused_before_it_goes(monkeypatch):
    from aft_msgs.msg import Reply
    """Review of session 48: a request that fit sealed, sealed again with a challenge, did not; the Proxy
    was told "nothing executed" though a gate that had taken it already let it through. A request now
    goes only with room for a challenge."""
    server, client = freshness_pair()
    size = len(sealed_by(client, 1, 1, payload=b'x' * 3000).payload)
    monkeypatch.setattr(security, 'MAX_SEALED_BYTES', size + sec_nodes.CHALLENGE_ROOM - 1)
    client.ports.published.clear()
    from aft_msgs.msg import Request
    client._on_request(Request(id=2, origin='/proxy', client='/c', service_type='aft_msgs/Account',
                               oldest_pending=2, payload=b'x' * 3000))
    assert [(port, getattr(m, 'status', None)) for port, m in client.ports.published] == \
        [('alarms', None), ('replies_out', Reply.NOT_EXECUTED)]
