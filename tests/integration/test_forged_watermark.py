"""A forged watermark that hangs a Proxy's calls is said, never silent (PBR, the bank, no SEC).

Without SEC anyone on the graph can publish a request under a Proxy's name. One whose
``oldest_pending`` is past 2**63 raises both Protocols' watermark for that Proxy past every id it
will ever take: each of its calls is then refused as below the ids answered already, naming a first
free id the Proxy cannot take. The Proxy cannot be renumbered out of it (only restarting both
Protocols clears it: a limit under SEC's gate, which refuses the forgery). Checked here: the
Proxy raises ``ids_refused`` naming the waiting request, once, within seconds; the calls made
before the forgery were answered exactly once. Before (session 36): the Proxy dropped every refusal,
and the call waited in silence.
Runs in a process of its own with a master of its own; every process it starts carries the test's
AFT_TEST_TAG and is killed at the end, pass or fail."""
from leftovers import run_seeded

SCRIPT = r'''
import random, sys, tempfile, threading, time
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
WARM = rng.randrange(3, 30)
log_dir = tempfile.mkdtemp(prefix='aft_forged_watermark_')
core = start_master(log_dir)
deployment = PbrDeployment(log_dir, timeout=0.15, mechanism='pbr')
try:
    rospy.init_node('attacker', disable_signals=True)
    start_retrying(deployment)
    alarms = []
    rospy.Subscriber('/aft/alarms', Alarm, lambda m: alarms.append((m.source, m.kind, m.detail)))
    proxy = rospy.ServiceProxy('/account', Account, persistent=True)
    proxy.wait_for_service(30)
    call, checker = account_caller(proxy), ReplyChecker()
    for i in range(WARM):
        op = operation(i)
        checker.check(checker.expect(*op), call(*op))
    forge = rospy.Publisher('/ftm/pxy2pro', Request, queue_size=10)
    if not wait_until(lambda: forge.get_num_connections() >= 2, 10.0, 0.05):
        sys.exit('seed %d: the forged request reaches %d Protocols, not both' % (seed, forge.get_num_connections()))
    watermark = rng.choice([(1 << 64) - 1, (1 << 63) + rng.randrange(1 << 40)])
    forged_id = rng.choice([1, watermark - 1])
    forge.publish(Request(id=forged_id, origin='/proxy', client='/attacker', service_type='aft_msgs/Account',
                          oldest_pending=watermark, payload=b''))
    print('seed %d: %d calls, then a request forged under /proxy with id %d and oldest_pending %d'
          % (seed, WARM, forged_id, watermark), flush=True)
    ended = []

    def victim_call():
        try:
            ended.append(call(*operation(WARM)))
        except Exception as e:   # (the teardown cuts a call that still waits)
            ended.append(e)
    victim = threading.Thread(target=victim_call, daemon=True)
    time.sleep(0.2)   # (the forgery is on its way: the victim's call comes after it)
    victim.start()
    said = lambda: [a for a in list(alarms) if a[0] == '/proxy' and a[1] == 'ids_refused']
    if not wait_until(lambda: said(), 10.0, 0.05):
        sys.exit('seed %d: the call through /proxy waits (answered: %s) and nothing said why: %s'
                 % (seed, bool(ended), [a[:2] for a in alarms[-8:]]))
    time.sleep(1.5)   # the Proxy re-sends every 0.5 s: each refusal again, said once
    told = said()
    print('seed %d: /proxy said: %s (the call %s)' % (seed, told[0][2], 'ended' if ended else 'still waits'),
          flush=True)
    if len(told) != 1 or 'waits' not in told[0][2] or ('past 2**63' not in told[0][2]):
        sys.exit('seed %d: expected one ids_refused naming the waiting request and the id past 2**63: %s'
                 % (seed, told))
    summary = checker.summary()
    if summary != {'correct': WARM, 'lost': 0, 'duplicated': 0, 'reordered': 0, 'errors': 0}:
        sys.exit('seed %d: the calls before the forgery: %s' % (seed, summary))
finally:
    deployment.teardown()
    core.stop()
print('ok')
'''


def test_a_forged_watermark_that_hangs_a_proxys_calls_is_said():
    run_seeded(SCRIPT, home_prefix='aft_forged_watermark_home_')
