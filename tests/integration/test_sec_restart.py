"""Replay protection that survives a restart of the whole deployment (issue 16; SEC, PBR, the bank).

Before, SEC's replay floors lived in the gates' memory: the bank deployment started again (both
replica sites and the client site, the same keys) executed every request an attacker had captured
from the earlier run. The gates now keep them on disk (aft_ftm.replay_log) before a request goes on.
A seeded number of calls is made and every sealed request on /ftm/pxy2pro captured; every process is
powered off at once; the deployment is started again with the same keys; the captured requests are
published again in a random order, some twice. Checked: each is refused by both server gates with an
alarm (``replay`` below the watermark, ``earlier_run`` for the last call), nothing of them executes
(the new client's first call finds a blank account), and the client's calls are answered right.

The same with both gates' replay logs removed before the start again (lost): nothing says the captured
requests are replays, and each gate asks the first request of each origin to prove itself fresh
(security.Freshness); a replay cannot, and each gate says so (``unanswered_challenge``).

The third test: a site down while a Proxy called through its peer, then re-joined. Its gate recorded
only what it saw while it ran; at the join it asks the peer's gate for its floors (security.seal_floors).
Runs in a process of its own with a master of its own; every process it starts carries the test's
AFT_TEST_TAG and is killed at the end, pass or fail."""
import pytest
from leftovers import run_seeded

# Both scripts begin so: the seed, a master of their own, a log directory
PROLOGUE = r'''
import os, random, sys, tempfile, time
import rospy
from diagnostic_msgs.msg import DiagnosticArray
from aft_msgs.msg import Alarm, Request
from aft_msgs.srv import Account
from aft_examples.bank import ReplyChecker, operation
from aft_examples.ros.bank_nodes import account_caller
from aft_examples.ros.deployment import PbrDeployment, start_retrying, witness_status
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until

seed = int(sys.argv[1])
rng = random.Random(seed)
log_dir = tempfile.mkdtemp(prefix='aft_sec_restart_')
core = start_master(log_dir)


def calls_captured(count, what):
    """count calls of the bank's client, every sealed request of /proxy captured on /ftm/pxy2pro: (its
    persistent proxy, caller, checker, {id: request}); exits naming ``what`` unless all are right."""
    captured = {}
    capture = rospy.Subscriber('/ftm/pxy2pro', Request,
                               lambda m: captured.setdefault(m.id, m) if m.origin == '/proxy' else None)
    proxy = rospy.ServiceProxy('/account', Account, persistent=True)
    proxy.wait_for_service(30)
    # The capture connected to the Proxy before the first call (CI, seed 51318: the first of 13 requests
    # went out while the connection was being made, 12 captured)
    if not wait_until(lambda: capture.get_num_connections() >= 1, 10.0, 0.05):
        sys.exit('seed %d: %s: the capture never connected to the Proxy' % (seed, what))
    call, checker = account_caller(proxy), ReplyChecker()
    for i in range(count):
        op = operation(i)
        checker.check(checker.expect(*op), call(*op))
    if checker.summary()['correct'] != count or not wait_until(lambda: len(captured) == count, 5.0, 0.05):
        sys.exit('seed %d: %s: %s, %d requests captured' % (seed, what, checker.summary(), len(captured)))
    capture.unregister()
    return proxy, call, checker, captured


started = []   # the deployments of the script, torn down at its end


def first_run(calls):
    """A SEC bank deployment: calls answered and captured, then every site powered off at once:
    (its keys directory, {id: request})."""
    first = PbrDeployment(os.path.join(log_dir, 'first'), timeout=0.15, sec=True)
    started.append(first)
    start_retrying(first)
    proxy, _, _, captured = calls_captured(calls, 'the first run')
    proxy.close()
    first.teardown()
    return first.keys_dir, captured


def started_again(keys_dir):
    """The deployment started again with the same keys: (the alarms heard from then on, a publisher on the
    Proxy's request topic both server gates hear)."""
    again = PbrDeployment(os.path.join(log_dir, 'again'), timeout=0.15, sec=True, keys_from=keys_dir)
    started.append(again)
    start_retrying(again)
    alarms = []
    rospy.Subscriber('/aft/alarms', Alarm, lambda m: alarms.append((m.source, m.kind, m.detail)))
    replay = rospy.Publisher('/ftm/pxy2pro', Request, queue_size=100)
    if not wait_until(lambda: replay.get_num_connections() >= 2, 10.0, 0.05):
        sys.exit('seed %d: the replays reach %d server gates, not both' % (seed, replay.get_num_connections()))
    time.sleep(0.5)   # (the alarms' subscription heard by the gates)
    return alarms, replay


def publish_again(replay, captured):
    """Every captured request published again, in a random order, some twice: the ids, sorted."""
    ids = sorted(captured)
    order = ids + rng.sample(ids, rng.randrange(len(ids)))
    rng.shuffle(order)
    for rid in order:
        replay.publish(captured[rid])
        time.sleep(rng.choice([0.0, 0.01, 0.05]))
    print('seed %d: %d captured requests published again (%d copies)' % (seed, len(ids), len(order)), flush=True)
    return ids


def blank_account_calls():
    """A few calls of a new client: their summary, or exit unless the account was blank (a replay executed:
    the first reply counts it) and every call right."""
    proxy = rospy.ServiceProxy('/account', Account, persistent=True)
    proxy.wait_for_service(30)
    call, fresh = account_caller(proxy), ReplyChecker()
    for i in range(rng.randrange(3, 8)):
        op = operation(i)
        fresh.check(fresh.expect(*op), call(*op))
    summary = fresh.summary()
    if summary['correct'] == 0 or summary != dict(summary, lost=0, duplicated=0, reordered=0, errors=0):
        sys.exit('seed %d: after the replays the account is not blank: %s' % (seed, summary))
    return summary
'''

SCRIPT = PROLOGUE + r'''
CALLS = rng.randrange(3, 15)
try:
    rospy.init_node('attacker', disable_signals=True)
    keys_dir, captured = first_run(CALLS)
    print('seed %d: %d calls answered and captured; the deployment powered off' % (seed, CALLS), flush=True)
    alarms, replay = started_again(keys_dir)
    ids = publish_again(replay, captured)

    def refused_by(gate):
        return {int(d.split('/proxy/')[1].split()[0]): k for s, k, d in list(alarms)
                if s == gate and k in ('replay', 'earlier_run') and '/proxy/' in d}
    for gate in ('/master/sec_gate', '/slave/sec_gate'):
        if not wait_until(lambda: set(refused_by(gate)) == set(ids), 10.0, 0.05):
            sys.exit('seed %d: %s refused %s of the ids %s; alarms: %s'
                     % (seed, gate, sorted(refused_by(gate)), ids, [a[:2] for a in alarms[-10:]]))
        kinds = refused_by(gate)
        if kinds[ids[-1]] != 'earlier_run' or any(kinds[i] != 'replay' for i in ids[:-1]):
            sys.exit('seed %d: %s refused them as %s (expected replay below the last call, earlier_run for it)'
                     % (seed, gate, kinds))
    summary = blank_account_calls()
    print('seed %d: both gates refused every replay (%d replay, 1 earlier_run); the new calls: %s'
          % (seed, len(ids) - 1, summary), flush=True)
finally:
    for deployment in reversed(started):
        deployment.teardown()
    core.stop()
print('ok')
'''


@pytest.mark.family('sec_restart', 1)
def test_captured_requests_are_refused_by_a_deployment_started_again_with_the_same_keys():
    run_seeded(SCRIPT, home_prefix='aft_sec_restart_home_')


REJOIN = PROLOGUE + r'''
CALLS = rng.randrange(4, 15)
PAUSED = sys.argv[2] == 'paused'
d = PbrDeployment(log_dir, timeout=0.15, sec=True)
try:
    rospy.init_node('attacker', disable_signals=True)
    start_retrying(d)
    alarms, learned = [], {}
    rospy.Subscriber('/aft/alarms', Alarm, lambda m: alarms.append((m.source, m.kind, m.detail)))

    def on_diagnostics(array):
        for status in array.status:
            if status.name.endswith('sec_gate'):
                learned.update({status.name.split(': ')[-1]: int(v.value) for v in status.values   # ('aft_ftm: NODE')
                                if v.key == 'replay_floors_learned'})
    rospy.Subscriber('/diagnostics', DiagnosticArray, on_diagnostics)
    d.sites['slave'].power_off()                       # SLAVE down; the client calls through MASTER alone
    if not wait_until(lambda: getattr(witness_status(d.witness_service), 'backup', None) == '', 20.0, 0.05):
        sys.exit('seed %d: SLAVE was not excluded: %s' % (seed, witness_status(d.witness_service)))
    proxy, call, checker, captured = calls_captured(CALLS, 'calls through MASTER alone')
    print('seed %d: %d calls through MASTER alone, captured; SLAVE relaunched' % (seed, CALLS), flush=True)
    gate = None
    if PAUSED:   # MASTER's gate paused through the join, past SLAVE's first tries at its floors
        import psutil, rosgraph, signal
        from aft_ftm.ros.fencing import node_api
        gate = psutil.Process(node_api(rosgraph.Master('/attacker').lookupNode('/master/sec_gate'), 2.0)
                              .getPid('/attacker')[2])
        gate.send_signal(signal.SIGSTOP)
    d.relaunch('slave', role='backup')                 # the Proxy stays silent from here on
    if not wait_until(lambda: getattr(witness_status(d.witness_service), 'backup', None) == 'slave', 60.0, 0.1):
        sys.exit('seed %d: SLAVE did not re-join: %s' % (seed, witness_status(d.witness_service)))
    if gate is not None:
        if not wait_until(lambda: any(a[:2] == ('/slave/sec_gate', 'floors_unavailable') for a in alarms), 40.0, 0.1):
            sys.exit('seed %d: MASTER\'s gate paused, SLAVE said nothing: alarms %s' % (seed, [a[:2] for a in alarms]))
        time.sleep(rng.uniform(0.0, 3.0))
        gate.send_signal(signal.SIGCONT)
        print('seed %d: MASTER\'s gate resumed after SLAVE\'s floors_unavailable' % seed, flush=True)
    if not wait_until(lambda: learned.get('/slave/sec_gate', 0) >= 1, 20.0 if gate is None else 40.0, 0.1):
        sys.exit('seed %d: SLAVE\'s gate learned no floors from MASTER\'s: %s; alarms %s'
                 % (seed, learned, [a[:2] for a in alarms[-8:]]))
    replay = rospy.Publisher('/ftm/pxy2pro', Request, queue_size=100)
    if not wait_until(lambda: replay.get_num_connections() >= 2, 10.0, 0.05):
        sys.exit('seed %d: the replays reach %d server gates, not both' % (seed, replay.get_num_connections()))
    time.sleep(0.5)
    ids = sorted(captured)[:-1]                        # (the last call is not below a watermark yet)

    def refused_by(gate):
        return {int(dd.split('/proxy/')[1].split()[0]) for s, k, dd in list(alarms)
                if s == gate and k == 'replay' and '/proxy/' in dd}

    def replay_all(gates):
        for rid in rng.sample(ids, len(ids)):
            replay.publish(captured[rid])
            time.sleep(rng.choice([0.0, 0.01, 0.05]))
        for gate in gates:
            if not wait_until(lambda: refused_by(gate) >= set(ids), 10.0, 0.05):
                sys.exit('seed %d: %s refused %s of the ids %s; alarms %s'
                         % (seed, gate, sorted(refused_by(gate)), ids, [a[:2] for a in alarms[-10:]]))
    replay_all(('/master/sec_gate', '/slave/sec_gate'))
    print('seed %d: both gates refused the %d replays (SLAVE by the floors it learned)' % (seed, len(ids)), flush=True)
    d.sites['master'].power_off()                      # SLAVE takes over: the replays again, then the client
    if not wait_until(lambda: getattr(witness_status(d.witness_service), 'primary', None) == 'slave', 20.0, 0.05):
        sys.exit('seed %d: SLAVE did not take over: %s' % (seed, witness_status(d.witness_service)))
    alarms[:] = [a for a in alarms if a[0] != '/slave/sec_gate']
    replay_all(('/slave/sec_gate',))
    for i in range(CALLS, CALLS + rng.randrange(3, 8)):
        op = operation(i)
        checker.check(checker.expect(*op), call(*op))   # a replay executed: the balance is off
    summary = checker.summary()
    if summary != dict(summary, lost=0, duplicated=0, reordered=0, errors=0) or summary['correct'] < CALLS + 3:
        sys.exit('seed %d: after the failover and the replays: %s' % (seed, summary))
    print('seed %d: SLAVE, primary, refused them again; the client: %s' % (seed, summary), flush=True)
finally:
    d.teardown()
    core.stop()
print('ok')
'''


LOST_LOG = PROLOGUE + r'''
import glob, shutil
CALLS = rng.randrange(3, 15)
try:
    rospy.init_node('attacker', disable_signals=True)
    keys_dir, captured = first_run(CALLS)
    logs = glob.glob(os.path.join(keys_dir, 'replay', '*.log'))
    if len(logs) < 2:
        sys.exit('seed %d: the first run left %s, not both server gates\' replay logs' % (seed, logs))
    shutil.rmtree(os.path.join(keys_dir, 'replay'))   # lost: the floors of the first run are gone
    print('seed %d: %d calls answered and captured; powered off; the replay logs removed' % (seed, CALLS), flush=True)
    alarms, replay = started_again(keys_dir)
    publish_again(replay, captured)
    # Nothing says they are replays (no floors): each gate asks /proxy to prove itself fresh, nobody can,
    # and after the challenge's wait each gate says so.
    told = lambda: {s for s, k, d in list(alarms) if k == 'unanswered_challenge' and '/proxy' in d}
    if not wait_until(lambda: told() >= {'/master/sec_gate', '/slave/sec_gate'}, 15.0, 0.1):
        sys.exit('seed %d: unanswered_challenge from %s only; alarms %s' % (seed, told(), [a[:2] for a in alarms[-10:]]))
    summary = blank_account_calls()
    print('seed %d: with the replay logs lost, no replay executed; both gates said unanswered_challenge; the new '
          'calls: %s' % (seed, summary), flush=True)
finally:
    for deployment in reversed(started):
        deployment.teardown()
    core.stop()
print('ok')
'''


@pytest.mark.family('sec_restart', 1)
def test_captured_requests_are_refused_by_a_deployment_started_again_that_lost_its_replay_logs():
    """Before session 48 a lost log looked like a first start: every captured request executed again. Each
    origin's first request in a gate's run now proves itself fresh (security.Freshness): a replay cannot."""
    run_seeded(LOST_LOG, home_prefix='aft_sec_lostlog_home_')


@pytest.mark.family('sec_rejoin', 1)
@pytest.mark.parametrize('peer', ['answering', 'paused'])
def test_a_site_rejoined_after_calls_it_missed_refuses_their_replays_as_a_backup_and_as_primary(peer):
    """paused: MASTER's gate SIGSTOPped from before SLAVE's relaunch until SLAVE said floors_unavailable
    (its first tries spent), then a drawn 0-3 s: SLAVE asks again while the pairing lasts, learns the
    floors, and refuses the replays all the same (before session 46 it never asked again: they passed)."""
    run_seeded(REJOIN, args=[peer], home_prefix='aft_sec_rejoin_home_')
