"""The PBR bank on emulated hosts (rosmaster, client, witness, master, slave: one network namespace
each), with fencing across hosts by the hosts' power switch. Needs root; skipped (with the reason)
where namespaces cannot be made.

- a power loss of the master host (link down first, then its processes killed) mid-run, with mutual
  TLS on every connection as `make demo-pbr` runs it: every request answered exactly once, SLAVE's
  state equal to a failure-free run, SLAVE promoted its Protocol only after the switch confirmed
  MASTER off, and no connection between the demo's own parties refused by the policy;
- a partition of the master host (its processes alive, its link down): SLAVE powers it off through
  the switch before promoting, so at most one primary ever answers; every request exactly once;
- a switch that refuses: no promotion (a request stays unanswered while MASTER is cut off), the
  alarm fence_failed, asked again; once it powers MASTER off, the promotion completes and the request
  is executed once. (A fence command that fails, ``command:false``, is in tests/unit/test_power_switch.py.)
- a 2 MB state re-joining over a slow link: in parts, with the replies going at once meanwhile (PBR),
  and in parts under LFR.

Every process and namespace is removed at the end, pass or fail (checked by name).
"""
import json
import os
import random
import re
import subprocess
import sys
import tempfile
import threading
import time

import psutil
import pytest

from aft_examples.bank import Account, account_state, operation
from aft_ftm import hosts_exec
from aft_ftm.hosts_exec import PlatformError
from aft_ftm.sites import wait_until
from reporting import report

try:
    from aft_examples.ros.deployment import start_retrying
    from aft_examples.ros.hosted import HOSTS, HostedDeployment
except ImportError as e:   # no workspace: the rostest tests say so too
    HostedDeployment = None
    IMPORT_ERROR = str(e)


@pytest.fixture
def seed():
    value = int(time.time() * 1000) % 100000
    yield value
    # printed with the test's output (shown on a failure)
    print('seed %d' % value)


def _platform_or_skip():
    if HostedDeployment is None:
        pytest.skip('aft_examples not importable: %s' % IMPORT_ERROR)
    try:
        hosts_exec.check_platform()
    except PlatformError as e:
        pytest.skip(str(e))


@pytest.fixture
def deployment(request):
    _platform_or_skip()
    made = []

    def make(**args):
        d = HostedDeployment(tempfile.mkdtemp(prefix='aft_hosts_pbr_'), **args)
        made.append(d)
        start_retrying(d)   # a detector timing out while the sites start (a loaded machine): start afresh
        made.append(d.hosts.topology.prefix)
        return d
    yield make
    for item in made:
        if isinstance(item, HostedDeployment):
            item.stop()
    for prefix in [p for p in made if isinstance(p, str)]:
        assert hosts_exec.leftovers(prefix) == [], 'namespaces or links of %s left' % prefix


def expected_state(count):
    model = Account()
    for i in range(count):
        model.apply(*operation(i))
    return model.snapshot()


def survivor_state(d, site):
    model = Account()
    model.set_state(account_state(d.server_state(site)))   # the account without its inert ballast, if any
    return model.snapshot()


def step(record, name):
    found = [s for s in record['steps'] if s['step'] == name]
    assert found, 'no step %s in %s' % (name, record['steps'])
    return found[0]


def assert_fenced_before_promotion(record, host):
    fence, promote = step(record, 'FAIL_SILENCE'), step(record, 'PROMOTE_PROTOCOL')
    assert fence['ok'] and 'power switch: %s off' % host in fence['detail'], fence
    assert promote['ok'], promote
    assert fence['start'] + fence['seconds'] <= promote['start'] + 1e-4, (fence, promote)


def demo_tls_policy():
    import os
    import rospkg
    return os.path.join(rospkg.RosPack().get_path('aft_examples'), 'config', 'tls_policy.yaml')


def test_power_loss_of_the_master_host(deployment, seed):
    rng = random.Random(seed)
    d = deployment(tls_policy=demo_tls_policy())
    count, crash_at = 300, rng.randint(60, 200)
    records, summary, crash = d.drive(count, fault_after=crash_at, fault=lambda: d.power_off('master'), rng=rng)
    assert summary == dict(correct=count, lost=0, duplicated=0, reordered=0, errors=0), (seed, summary)
    assert survivor_state(d, 'slave') == expected_state(count), seed
    record = d.last_failover('slave')
    assert_fenced_before_promotion(record, 'master')
    assert d.node_pids('master') == [] and d.hosts.state('master') == 'off'
    # the demo's parties, under its policy, are never refused (a handshake that failed and was
    # retried, under load, raises an alarm too: that is not the policy's doing)
    refused = [a for a in d.alarms() if a.get('mechanism') == 'tls' and 'may not' in a['detail']]
    assert refused == [], refused
    # each host has its power switch: nobody says a peer cannot be made silent
    assert [a for a in d.alarms() if a['kind'] == 'fence_incomplete'] == []
    waits = [r[2] - max(r[1], crash['wall']) for r in records if r[2] > crash['wall']]
    report('hosts PBR (mutual TLS): master host power loss (link down first): detected %.1f ms after it, failover %.1f ms, '
           'fencing call %.1f ms' % ((record['detected_wall'] - crash['wall']) * 1e3, max(waits) * 1e3,
                                     step(record, 'FAIL_SILENCE')['seconds'] * 1e3))


def test_partition_of_the_master_host_is_fenced_before_promotion(deployment, seed):
    rng = random.Random(seed)
    d = deployment(timeout=0.3)   # (not a detection figure: a false suspicion at 30 ms fenced a replica early)
    count, cut_at = 200, rng.randint(40, 120)

    def cut():
        if d.hosts.state('master') == 'off':   # fenced already after a false suspicion (a loaded machine)
            return 0, d.hosts.powered_off_at['master']
        processes = len(d.node_pids('master'))
        d.partition('master')
        return processes, time.time()
    records, summary, _ = d.drive(count, fault_after=cut_at, fault=cut, rng=rng)
    # The master's processes were alive behind the cut: only the switch's power-off silenced them,
    # and it came before SLAVE's Protocol was promoted: never two primaries answering.
    assert summary == dict(correct=count, lost=0, duplicated=0, reordered=0, errors=0), (seed, summary)
    assert survivor_state(d, 'slave') == expected_state(count), seed
    assert_fenced_before_promotion(d.last_failover('slave'), 'master')
    assert ('off', 'master', True) in d.switch.requests
    assert d.hosts.state('master') == 'off' and d.node_pids('master') == []


def test_replica_hosts_without_a_power_switch_are_said_impossible_to_silence(deployment):
    """Sites on other machines and no power switch: fencing can only ask the peer's nodes over XML-RPC
    to shut down, which a frozen or cut-off node never answers (and a node under TLS refuses). Not
    silent: each Recovery raises fence_incomplete once, naming the peer's nodes."""
    d = deployment(power_switch=False, timeout=0.3)   # (a false suspicion would tell it again)

    def told():
        return {a['source']: a['detail'] for a in d.alarms() if a['kind'] == 'fence_incomplete'}
    assert wait_until(lambda: set(told()) == {'/master/recovery', '/slave/recovery'}, 20.0, 0.2), told()
    for site, peer in (('master', 'slave'), ('slave', 'master')):
        detail = told()['/%s/recovery' % site]
        assert 'cannot make /%s silent' % peer in detail and '/%s/after at http://' % peer in detail, detail
        assert 'no power switch is configured' in detail and 'never answers' in detail, detail
    assert len([a for a in d.alarms() if a['kind'] == 'fence_incomplete']) == 2   # once each


def test_a_switch_that_does_not_confirm_prevents_the_promotion_until_it_does(deployment):
    # Detection at 300 ms, not 30: this test is about the switch's refusal. In CI (2 cores, loaded) the
    # master once suspected the slave falsely at 30 ms and powered it off before the partition, so
    # nobody was left to ask the switch (detection under load is measured by the detection benchmark).
    d = deployment(timeout=0.3)
    _, summary, _ = d.drive(30)
    assert summary['correct'] == 30
    pair = d.witness_pair()
    assert pair[1:] == ['master', 'slave'], 'the pair changed before the fault: %s; alarms %s' % (
        pair, [(a['source'], a['kind'], a['detail'][:120]) for a in d.alarms()][-8:])
    d.switch.refuse('the PDU is locked for maintenance')
    d.partition('master')
    call = d.driver.request(15.0, op='call', index=30, timeout=4.0)
    assert not call['answered'], 'a request was answered while the old primary may still answer: %s' % call
    fence_failed = [a for a in d.alarms() if a['kind'] == 'fence_failed']
    assert len(fence_failed) >= 2, 'not asked again: %s' % fence_failed
    assert all(a['source'] == '/slave/recovery' and 'PDU is locked' in a['detail'] for a in fence_failed), fence_failed
    record = d.last_failover('slave')
    assert not step(record, 'FAIL_SILENCE')['ok'] and not step(record, 'PROMOTE_PROTOCOL')['ok'], record
    assert d.hosts.state('master') == 'partitioned' and d.node_pids('master'), 'nothing powered master off'
    # The switch works again: its next retry powers master off, and only then is SLAVE promoted;
    # the request caught in the partition is executed once.
    d.switch.refuse(None)
    deadline = time.monotonic() + 15.0
    while survivor_state(d, 'slave') != expected_state(31):
        assert time.monotonic() < deadline, 'the promotion did not complete once the switch confirmed'
        time.sleep(0.2)
    record = d.last_failover('slave')
    assert record['late_promotion'] and step(record, 'PROMOTE_PROTOCOL')['ok'], record
    assert d.hosts.state('master') == 'off' and d.node_pids('master') == []


def _nodes_in(d, host, name):
    """pids of the processes of host whose command line names node ``name`` (``__name:=name``)."""
    found = []
    for pid in d.node_pids(host):
        try:
            if '__name:=%s' % name in psutil.Process(pid).cmdline():
                found.append(pid)
        except psutil.NoSuchProcess:
            continue
    return found


def test_a_bandwidth_drop_between_the_replica_hosts_makes_the_monitor_switch_pbr_to_lfr(deployment, seed):
    """R measured for real: the link monitors' probes cross the replicas' links; a token bucket on the
    slave host's link (800 kbit/s, below what PBR's checkpoints need) makes the monitor switch PBR to
    LFR by itself, the new nodes start on their sites' hosts, and no request is lost or run twice.
    Under mutual TLS (issue 16): the Monitoring Engine runs as the party engine, the only one that may
    suspend and rebind, and the nodes it starts speak as their sites' parties; nothing of the
    deployment's own is refused by the policy."""
    rng = random.Random(seed)
    # The limit saturates the slave's link (the switch's state transfer, the checkpoints), and the
    # heartbeats share it. In a clean-clone CI (session 50) the master's beats, sent on time, reached the
    # slave 501 ms late (dropped behind the data past the token bucket's 100 ms and resent by TCP), and
    # the 500 ms detector fenced the master in the middle of the switch. The heartbeat connections are
    # marked low delay now and the limit serves them first (aft_ftm.ros.qos, aft_ftm.hosts.plan_rate;
    # tests/integration/test_urgent_link.py); the urgent class's counters below say they were.
    d = deployment(adaptable=True, link_monitor=True, monitor=True, timeout=0.5, tls_policy=demo_tls_policy())
    d.strings('/aft/monitor/events')            # subscribed from now on

    def measured():
        models = d.strings('/aft/monitor/model', last=1)
        return models[-1]['model']['resources'].get('bandwidth') if models else None
    deadline = time.monotonic() + 30.0
    sent = 0
    while not measured():
        assert time.monotonic() < deadline, 'no bandwidth reached the monitor: %s' % d.strings('/aft/monitor/model', last=1)
        _, summary, _ = d.drive(10, first=sent)
        sent += 10
    high = measured()
    assert high > 1e6, 'the unlimited link measured %s B/s' % high
    _, summary, _ = d.drive(rng.randint(20, 60), first=sent)
    sent = summary['correct']
    d.hosts.rate('slave', 800)
    limited_at = time.monotonic()
    deadline = limited_at + 120.0

    def finished():
        return [e for e in d.strings('/aft/monitor/events') if e.get('event') in ('adapted', 'adaptation_failed')]
    while not finished():
        assert time.monotonic() < deadline, 'the monitor did not adapt: %s' % d.strings('/aft/monitor/events')
        _, summary, _ = d.drive(10, first=sent)
        sent = summary['correct'] + summary['errors']
    adapted_s = time.monotonic() - limited_at
    _, summary, _ = d.drive(30, first=sent)
    sent += 30
    done = finished()[0]
    assert done['event'] == 'adapted', done
    decision = [e for e in d.strings('/aft/monitor/events') if e.get('event') == 'decision'][0]
    assert (decision['decision']['from'], decision['decision']['to']) == (['pbr'], ['lfr']), decision
    assert 'bandwidth' in decision['decision']['reason'], decision
    assert summary == dict(correct=sent, lost=0, duplicated=0, reordered=0, errors=0), (seed, summary)
    assert survivor_state(d, 'slave') == survivor_state(d, 'master') == expected_state(sent), seed
    # The new nodes run on the hosts of the sites they joined, not on the monitor's.
    assert _nodes_in(d, 'master', 'after_lfr') and _nodes_in(d, 'slave', 'after_lfr')
    assert not _nodes_in(d, 'witness', 'after_lfr')
    for host in ('master', 'slave'):   # ... as the parties of those sites, not the engine's
        parties = {psutil.Process(pid).environ().get('AFT_TLS_PARTY') for pid in _nodes_in(d, host, 'after_lfr')}
        assert parties == {host}, (host, parties)
    refused = [a for a in d.alarms() if a.get('mechanism') == 'tls' and 'may not' in a['detail']]
    assert refused == [], refused
    low = measured()
    urgent, data = _class_packets(d.hosts, 'slave', '1:10'), _class_packets(d.hosts, 'slave', '1:20')
    assert urgent > 0 and data > 0, 'no packet of the slave\'s upload passed as urgent (%d) or as data (%d): ' \
        'the heartbeats are not marked low delay' % (urgent, data)
    report('hosts PBR -> LFR: link measured %.0f kB/s, then %.0f kB/s under an 800 kbit/s limit on the slave host; '
           'the monitor switched to LFR %.1f s after the limit (engine pause %.1f ms), %d requests exactly once; '
           'the slave\'s upload meanwhile: %d urgent packets (heartbeats), %d of data'
           % (high / 1e3, low / 1e3, adapted_s, done['report']['pause_s'] * 1e3, sent, urgent, data))


def _class_packets(hosts, name, classid):
    """The packets a class of the rate limit on host ``name``'s upload has sent (tc's counters)."""
    h = hosts.topology.host(name)
    shown = subprocess.run(['tc', '-n', h.namespace, '-s', 'class', 'show', 'dev', h.host_if], stdout=subprocess.PIPE,
                           universal_newlines=True, check=True, timeout=10).stdout
    found = re.search(r'class htb %s .*?\n\s*Sent \d+ bytes (\d+) pkt' % re.escape(classid), shown, re.S)
    assert found, 'no class %s on %s:\n%s' % (classid, h.host_if, shown)
    return int(found.group(1))


def _slave_joins(d):
    """The master After's records of the slave's joins (its ~events, subscribed by the first call)."""
    return [e for e in d.strings('/master/after/events') if e.get('event') == 'join' and e['joiner'] == 'slave']


def _slave_back_on_a_slow_link(d, sent, kbit=8000):
    """Once the slave's first join is recorded: the slave host powered off, 20 calls to the master
    alone, the host back with its link limited to kbit/s and the slave launched again (it re-joins).
    Returns (calls sent so far, joins recorded before)."""
    assert wait_until(lambda: _slave_joins(d), 10.0), 'no record of the first join: %s' % (
        d.strings('/master/after/events'),)
    before = len(_slave_joins(d))
    d.power_off('slave')
    d.drive(20, first=sent)   # the master alone
    d.hosts.power_on('slave')
    d.hosts.rate('slave', kbit)
    d.relaunch('slave', role='backup')
    return sent + 20, before


def _drive_until_the_slave_is_backup(d, sent, timeout=90.0):
    """Calls in tens until the witness names the slave the backup; returns (their records, calls sent)."""
    records, deadline = [], time.monotonic() + timeout
    while d.witness_pair()[2] != 'slave':
        assert time.monotonic() < deadline, 'slave did not re-join in %.0f s: %s; alarms %s' % (
            timeout, d.witness_pair(), [(a['kind'], a['detail']) for a in d.alarms()][-10:])
        batch, _, _ = d.drive(10, first=sent)
        records += batch
        sent += 10
    return records, sent


@pytest.mark.family('slow_link_transfer', 1)
def test_a_large_state_rejoins_over_a_slow_link_in_parts_and_no_client_waits_for_the_transfer(deployment, seed):
    """Issue 18: the slave host powered off, then back with its link limited to 8 Mbit/s, a 2 MB state:
    the re-join's state transfer takes about 2 s, twice the ack timeout, which in one message would
    exclude the joiner at every try. In parts of 64 KB (aft_ftm.transfer), each acknowledged in time,
    it joins; meanwhile replies go at once (catch-up), so no client waits for the transfer. The
    joining After is frozen for 1.5 s at a seeded moment of its start-up, transfer or catch-up (a pause
    mid-transfer costs a try: excluded with the alarm, it asks again). Every request exactly once, both
    replicas' states equal to a failure-free run's."""
    rng = random.Random(seed)
    d = deployment(ballast_bytes=2000000, chunk_bytes=65536, timeout=0.15)
    _slave_joins(d)            # subscribed from now on
    sent = rng.randint(20, 40)
    d.drive(sent)
    sent, before = _slave_back_on_a_slow_link(d, sent)
    frozen = {}

    def freeze_joiner():
        pids = _nodes_in(d, 'slave', 'after')
        frozen['at'] = time.time()
        frozen['pids'] = pids
        if pids:
            d.hosts.freeze(pids[0], 1.5).wait()
    freezer = threading.Timer(rng.uniform(3.0, 8.0), freeze_joiner)
    freezer.start()
    records, sent = _drive_until_the_slave_is_backup(d, sent)
    assert wait_until(lambda: len(_slave_joins(d)) > before, 10.0), 'no record of the re-join: %s' % (
        d.strings('/master/after/events'),)
    join = _slave_joins(d)[-1]
    freezer.join(10.0)
    assert frozen.get('pids'), 'the joining After was not found to freeze: %s' % frozen
    assert join['parts'] >= 30 and join['state_bytes'] > 2000000, join
    assert join['acknowledged_s'] > 1.0, 'the transfer took %.2f s: the link did not make it longer than the ack ' \
        'timeout, so this test proves nothing' % join['acknowledged_s']
    # Calls answered while the transfer went: held replies would have waited for all of it. (From its
    # acknowledgment on they are held again, until the joiner applied what it missed meanwhile.)
    start, end = join['sent_wall'], join['sent_wall'] + join['acknowledged_s']
    during = [r[2] - r[1] for r in records if start <= r[2] <= end]
    assert len(during) >= 20 and max(during) < join['acknowledged_s'] / 2, (len(during), max(during, default=None),
                                                                              join)
    after = [r[2] - r[1] for r in records if r[2] > end]
    _, summary, _ = d.drive(20, first=sent)   # the pair again: every reply held for the slave's acknowledgment
    sent += 20
    assert summary == dict(correct=sent, lost=0, duplicated=0, reordered=0, errors=0), (seed, summary)
    assert survivor_state(d, 'master') == expected_state(sent), seed
    # The slave holds it too (re-joined again by itself if the freeze came after its admission).
    assert wait_until(lambda: d.witness_pair()[2] == 'slave' and survivor_state(d, 'slave') == expected_state(sent),
                      60.0), (seed, d.witness_pair())
    excluded = [a['detail'] for a in d.alarms() if a['kind'] == 'alone']
    report('hosts PBR: a 2.0 MB state re-joined over an 8 Mbit/s link in %d parts, acknowledged %.2f s after it was '
           'sent (ack timeout 1 s), %d calls answered meanwhile, the longest in %.1f ms (then, until admitted, the '
           'longest %.1f ms); the joiner frozen 1.5 s %.2f s before that transfer, %d exclusions (alone) in the run '
           '(seed %d)' % (join['parts'], join['acknowledged_s'], len(during), max(during) * 1e3,
                          max(after, default=0.0) * 1e3, join['sent_wall'] - frozen['at'], len(excluded), seed))


@pytest.mark.family('slow_link_transfer', 1)
def test_lfr_a_large_state_rejoins_over_a_slow_link_in_parts(deployment, seed):
    """Issue 18, LFR's re-join: the follower host powered off, then back with its link limited to
    2 Mbit/s, a 3 MB state. The transfer goes in parts of 64 KB (aft_ftm.transfer), at most 4 in
    flight, each acknowledged: it takes far longer than the ack timeout (1 s), which counts from the
    last part acknowledged. (In one message, rospy's synchronous write of it holds the leader until
    the link has taken it all, however long, and the timeout starts only then.) LFR's leader holds
    its Protocol while it transfers, so clients wait for the transfer. It takes longer than the
    Protocol's suspension lease too (10 s), which the leader renews for the transfer: had the
    Protocol resumed by itself, requests would run that the transferred state misses, and the
    follower would diverge. Every request exactly once, both replicas' states equal to a failure-free
    run's."""
    rng = random.Random(seed)
    d = deployment(mechanism='lfr', ballast_bytes=3000000, chunk_bytes=65536, timeout=0.15)
    _slave_joins(d)            # subscribed from now on
    sent = rng.randint(10, 30)
    d.drive(sent)
    sent, before = _slave_back_on_a_slow_link(d, sent, kbit=2000)
    records, sent = _drive_until_the_slave_is_backup(d, sent)
    assert wait_until(lambda: len(_slave_joins(d)) > before, 10.0), 'no record of the re-join: %s' % (
        d.strings('/master/after/events'),)
    join = _slave_joins(d)[-1]
    assert join['parts'] >= 45 and join['state_bytes'] > 3000000, join
    assert join['acknowledged_s'] > 10.0, 'the transfer took %.2f s: the link did not make it longer than the ' \
        'Protocol\'s lease, so this test proves less than it says' % join['acknowledged_s']
    _, summary, _ = d.drive(20, first=sent)   # the pair again: every reply waits for the follower
    sent += 20
    assert summary == dict(correct=sent, lost=0, duplicated=0, reordered=0, errors=0), (seed, summary)
    assert survivor_state(d, 'master') == expected_state(sent), seed
    d.hosts.unrate('slave')   # its state read through the driver: seconds at the slow link's rate
    assert wait_until(lambda: survivor_state(d, 'slave') == expected_state(sent), 10.0), seed
    waits = [r[2] - r[1] for r in records]
    failed = [a['detail'] for a in d.alarms() if a['kind'] == 'join_failed']
    report('hosts LFR: a 3.0 MB state re-joined over a 2 Mbit/s link in %d parts, acknowledged %.2f s after it was '
           'sent (ack timeout 1 s, Protocol lease 10 s), admitted after %.2f s; the longest client wait meanwhile '
           '%.2f s; %d failed joins before (seed %d)' % (join['parts'], join['acknowledged_s'], join['admitted_s'],
                                       max(waits, default=0.0), len(failed), seed))


def _link_bytes(d, host, direction='rx'):
    """Bytes host's link has received ('rx') or sent ('tx') so far (its interface's counter, read in
    its namespace)."""
    h = d.hosts.topology.host(host)
    out = subprocess.run(['ip', '-n', h.namespace, '-j', '-s', 'link', 'show', 'dev', h.host_if],
                         stdout=subprocess.PIPE, check=True, timeout=10).stdout
    return json.loads(out)[0]['stats64'][direction]['bytes']


def _received_bytes(d, host):
    return _link_bytes(d, host, 'rx')


@pytest.mark.family('slow_link_transfer', 1)
def test_lfr_a_joiner_cut_off_mid_transfer_holds_the_leader_only_for_the_ack_timeout(deployment, seed):
    """LFR's leader suspends its Protocol while it transfers its state to a joiner. The joiner's host
    is cut off (link down, processes alive) for 5 s once a seeded part of its 2 MB transfer arrived over
    its 8 Mbit/s link. In parts, the leader gives up 1 s (the ack timeout) after the last part
    acknowledged, raises join_failed and serves alone: the clients' calls meanwhile wait far less than
    the cut. (In one message, rospy's write of the transfer blocks until the link takes it, holding the
    leader, and the clients, for the whole cut.) Healed, the joiner asks again and joins; every request
    exactly once, both states equal to a failure-free run's."""
    rng = random.Random(seed)
    d = deployment(mechanism='lfr', ballast_bytes=2000000, chunk_bytes=65536, timeout=0.15)
    _slave_joins(d)            # subscribed from now on
    sent = rng.randint(10, 30)
    d.drive(sent)
    sent, before = _slave_back_on_a_slow_link(d, sent)
    start, sent_start = _received_bytes(d, 'slave'), _link_bytes(d, 'master', 'tx')
    into = rng.randint(300000, 1200000)
    # The joiner's own start-up (its nodes registering, their handshakes and parameters, from the
    # rosmaster host) brings its link 0.3 MB and more: counted alone, it once let the cut come before
    # the transfer began (CI, seed 28979). The master host sends nothing that large but the transfer.
    assert wait_until(lambda: _received_bytes(d, 'slave') - start > into and
                      _link_bytes(d, 'master', 'tx') - sent_start > into, 60.0, 0.01), \
        'the transfer to the joiner did not start within 60 s: %d bytes received, %d sent by the master' % (
            _received_bytes(d, 'slave') - start, _link_bytes(d, 'master', 'tx') - sent_start)
    d.hosts.partition('slave')
    cut = time.monotonic()
    records, summary, _ = d.drive(5, first=sent)   # they wait for the leader to give the transfer up
    sent += 5
    waits = [r[2] - r[1] for r in records]
    time.sleep(max(0.0, cut + 5.0 - time.monotonic()))
    alarms = d.alarms()
    d.hosts.heal('slave')
    assert max(waits) < 3.5, 'calls waited %.2f s during a 5 s cut: the leader was held by the joiner (seed %d)' % (
        max(waits), seed)
    failed = [a['detail'] for a in alarms if a['kind'] == 'join_failed']
    assert any('part' in f for f in failed), (seed, [(a['kind'], a['detail']) for a in alarms])
    _, sent = _drive_until_the_slave_is_backup(d, sent)
    _, summary, _ = d.drive(10, first=sent)
    sent += 10
    assert summary == dict(correct=sent, lost=0, duplicated=0, reordered=0, errors=0), (seed, summary)
    assert survivor_state(d, 'master') == expected_state(sent), seed
    d.hosts.unrate('slave')   # its state read through the driver: seconds at the slow link's rate
    assert wait_until(lambda: survivor_state(d, 'slave') == expected_state(sent), 10.0), seed
    report('hosts LFR: the joiner cut off for 5 s %.1f MB into its 2 MB transfer; calls meanwhile waited at most '
           '%.2f s; %s; it re-joined once healed (seed %d)' % (into / 1e6, max(waits), failed[-1][:120], seed))


LISTENER = r'''
import sys, rospy
from aft_msgs.msg import Reply
rospy.init_node('proxy2_standin', disable_signals=True)
heard = []
def on(reply):
    if not heard:
        print('heard', flush=True)
    heard.append(1)
rospy.Subscriber(sys.argv[1], Reply, on, tcp_nodelay=True)
rospy.spin()
'''


def test_a_client_hosts_power_loss_leaves_the_other_clients_served(deployment, seed):
    """Every Proxy subscribes to the one replies topic. A client host that loses power sends no FIN or
    RST: a plain write to its Proxy blocks once its socket's buffers fill (about 20 replies), and the
    Protocol, under its lock, held every other client with it for the kernel's retransmission time
    (about 15 minutes: the drive below timed out after 90 s). The Protocol's replies now spill into a
    buffer per Proxy connection when that Proxy does not read (aft_ftm.ros.spillover); the kernel's
    limit on unacknowledged data (AFT_TCP_USER_TIMEOUT, 10 s) then ends the dead connection. Here a
    second client host (a stand-in for its Proxy, subscribed to the replies) is powered off while the
    client calls: every call is answered exactly once, none waiting more than 1 s."""
    rng = random.Random(seed)
    hosts = hosts_exec.Hosts(list(HOSTS) + ['client2']).__enter__()
    try:
        d = deployment(hosts=hosts, timeout=0.3)   # (the replicas' detection is not what is measured)
        listener = hosts.run_in('client2', [sys.executable, '-c', LISTENER, '/ftm/pro2pxy'],
                                env=dict(os.environ, ROS_MASTER_URI=d.master_uri), stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL)
        heard = threading.Event()
        threading.Thread(target=lambda: listener.stdout.readline() and heard.set(), daemon=True).start()
        # The stand-in hears the replies: it is connected. Its start (a Python process importing rospy,
        # registering, connecting) took longer than 400 calls once on a loaded machine: bounded in time.
        first, end = 0, time.monotonic() + 60.0
        while not heard.is_set() and time.monotonic() < end:
            d.drive(20, first=first)
            first += 20
        assert heard.is_set(), 'the stand-in on client2 heard no reply within 60 s (%d calls)' % first
        count, off_at = 600, rng.randint(50, 300)
        records, summary, fault = d.drive(count, first=first, fault_after=off_at, fault=lambda: d.power_off('client2'),
                                          rng=rng, timeout=90.0)
        # (the summary counts every call of the deployment's client, those before too)
        assert summary == dict(correct=first + count, lost=0, duplicated=0, reordered=0, errors=0), (seed, summary)
        waits = [r[2] - max(r[1], fault['wall']) for r in records if r[2] > fault['wall']]
        assert waits and max(waits) < 1.0, (seed, max(waits or [None]))
        report('hosts PBR: a second client host powered off mid-run: the longest wait of the other client %.1f ms'
               % (max(waits) * 1e3))
    finally:
        hosts.close()
