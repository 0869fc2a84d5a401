"""Replay protection that survives a restart of the whole deployment (issue 16; SEC, PBR, the bank).

Before, SEC's replay floors lived in the gates' memory: the bank deployment started again (both
replica sites and the client site, the same keys) executed every request an attacker had captured
from the earlier run. The gates now keep them on disk (aft_ftm.replay_log) before a request goes on.
A seeded number of calls is made and every sealed request on /ftm/pxy2pro captured; every process is
powered off at once; the deployment is started again with the same keys; the captured requests are
published again in a random order, some twice. Checked: each is refused by both server gates with an
alarm (``replay`` below the watermark, ``earlier_run`` for the last call), nothing of them executes
(the new client's first call finds a blank account), and the client's calls are answered right.
Runs in a process of its own with a master of its own; every process it starts carries the test's
AFT_TEST_TAG and is killed at the end, pass or fail."""
from leftovers import run_seeded

SCRIPT = r'''
import os, random, sys, tempfile, time
import rospy
from aft_msgs.msg import Alarm, Request
from aft_msgs.srv import Account
from aft_examples.bank import ReplyChecker, operation
from aft_examples.ros.bank_nodes import account_caller
from aft_examples.ros.deployment import PbrDeployment, start_retrying
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until

seed = int(sys.argv[1])
rng = random.Random(seed)
CALLS = rng.randrange(3, 15)
log_dir = tempfile.mkdtemp(prefix='aft_sec_restart_')
core = start_master(log_dir)
first = PbrDeployment(os.path.join(log_dir, 'first'), timeout=0.15, sec=True)
again = None
try:
    rospy.init_node('attacker', disable_signals=True)
    start_retrying(first)
    captured = {}
    capture = rospy.Subscriber('/ftm/pxy2pro', Request,
                               lambda m: captured.setdefault(m.id, m) if m.origin == '/proxy' else None)
    proxy = rospy.ServiceProxy('/account', Account, persistent=True)
    proxy.wait_for_service(30)
    call, checker = account_caller(proxy), ReplyChecker()
    for i in range(CALLS):
        op = operation(i)
        checker.check(checker.expect(*op), call(*op))
    if checker.summary()['correct'] != CALLS or not wait_until(lambda: len(captured) == CALLS, 5.0, 0.05):
        sys.exit('seed %d: the first run: %s, %d requests captured' % (seed, checker.summary(), len(captured)))
    capture.unregister()
    proxy.close()
    first.teardown()                                   # every site powered off at once
    print('seed %d: %d calls answered and captured; the deployment powered off' % (seed, CALLS), flush=True)

    again = PbrDeployment(os.path.join(log_dir, 'again'), timeout=0.15, sec=True, keys_from=first.keys_dir)
    start_retrying(again)
    alarms = []
    rospy.Subscriber('/aft/alarms', Alarm, lambda m: alarms.append((m.source, m.kind, m.detail)))
    replay = rospy.Publisher('/ftm/pxy2pro', Request, queue_size=100)
    if not wait_until(lambda: replay.get_num_connections() >= 2, 10.0, 0.05):
        sys.exit('seed %d: the replays reach %d server gates, not both' % (seed, replay.get_num_connections()))
    time.sleep(0.5)   # (the alarms' subscription heard by the gates)
    ids = sorted(captured)
    order = ids + rng.sample(ids, rng.randrange(len(ids)))
    rng.shuffle(order)
    for rid in order:
        replay.publish(captured[rid])
        time.sleep(rng.choice([0.0, 0.01, 0.05]))
    print('seed %d: %d captured requests published again (%d copies)' % (seed, len(ids), len(order)), flush=True)

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
    proxy = rospy.ServiceProxy('/account', Account, persistent=True)
    proxy.wait_for_service(30)
    call, fresh = account_caller(proxy), ReplyChecker()
    for i in range(rng.randrange(3, 8)):
        op = operation(i)
        fresh.check(fresh.expect(*op), call(*op))       # a replay executed: the first reply counts it
    summary = fresh.summary()
    if summary['correct'] == 0 or summary != dict(summary, lost=0, duplicated=0, reordered=0, errors=0):
        sys.exit('seed %d: after the replays the account is not blank: %s' % (seed, summary))
    print('seed %d: both gates refused every replay (%d replay, 1 earlier_run); the new calls: %s'
          % (seed, len(ids) - 1, summary), flush=True)
finally:
    for deployment in (again, first):
        if deployment is not None:
            deployment.teardown()
    core.stop()
print('ok')
'''


def test_captured_requests_are_refused_by_a_deployment_started_again_with_the_same_keys():
    run_seeded(SCRIPT, home_prefix='aft_sec_restart_home_')
