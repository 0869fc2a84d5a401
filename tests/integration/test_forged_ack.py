"""A forged checkpoint acknowledgment never releases a reply the backup does not hold (PBR, the bank).

Without TLS anyone on the graph can subscribe to the primary After's checkpoints and publish on the
topic of its acknowledgments. Here SLAVE's After is frozen (SIGSTOP: it holds nothing new and
acknowledges nothing), and an attacker node acknowledges every checkpoint MASTER's After publishes,
at once, with the right sequence number, epoch and addressee. A reply released on such an ack is
answered while only MASTER holds its effect: a power loss of MASTER then loses it, silently.

Checked: the first call made during the freeze is answered only once SLAVE's ack could be overdue
(0.5 s at least; the ack timeout is 1 s) and MASTER says it went on alone (``alone``), MASTER's After
raised ``stray_ack`` naming the attacker, and every call is answered exactly once.
Before: MASTER released each reply on the forged ack, within milliseconds, with no alarm.
Runs in a process of its own with a master of its own; every process it starts carries the test's
AFT_TEST_TAG and is killed at the end, pass or fail."""
from leftovers import run_seeded

SCRIPT = r'''
import os, random, signal, sys, tempfile, threading, time
import rosgraph, rospy
from aft_msgs.msg import Alarm, Checkpoint, CheckpointAck
from aft_msgs.srv import Account
from aft_examples.bank import ReplyChecker, operation
from aft_examples.ros.bank_nodes import account_caller
from aft_examples.ros.deployment import PbrDeployment, start_retrying
from aft_ftm.ros.fencing import node_api
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until

seed = int(sys.argv[1])
rng = random.Random(seed)
WARM = rng.randrange(5, 40)   # calls before the freeze
log_dir = tempfile.mkdtemp(prefix='aft_forged_ack_')
core = start_master(log_dir)
deployment = PbrDeployment(log_dir, timeout=0.15, mechanism='pbr')
frozen = []

def topic_of(node, publishes, msg_type, word):
    """The topic of msg_type, named with word, that node publishes (or subscribes to), from the ROS master."""
    master = rosgraph.Master('/checker')
    pubs, subs, _ = master.getSystemState()
    types = dict(master.getTopicTypes())
    found = [t for t, nodes in (pubs if publishes else subs) if node in nodes and types.get(t) == msg_type and word in t]
    if len(found) != 1:
        sys.exit('seed %d: %s %s %s on %s, not one topic' % (seed, node, 'publishes' if publishes else 'hears',
                                                           msg_type, found))
    return found[0]

try:
    rospy.init_node('attacker', disable_signals=True)
    start_retrying(deployment)
    alarms = []
    rospy.Subscriber('/aft/alarms', Alarm, lambda m: alarms.append((time.monotonic(), m.source, m.kind, m.detail)))
    proxy = rospy.ServiceProxy('/account', Account, persistent=True)
    proxy.wait_for_service(30)
    call, checker = account_caller(proxy), ReplyChecker()

    def one(i):
        op = operation(i)
        expected = checker.expect(*op)
        checker.check(expected, call(*op))
    for i in range(WARM):
        one(i)
    acks = rospy.Publisher(topic_of('/master/after', False, 'aft_msgs/CheckpointAck', 'ack'), CheckpointAck, queue_size=100)
    forged = []

    def acknowledge(cp):   # every checkpoint of MASTER's After, acknowledged as SLAVE's After would
        if cp.sender == '/master/after':
            acks.publish(CheckpointAck(seq=cp.seq, ok=True, epoch=cp.epoch, to=cp.sender))
            forged.append(cp.seq)
    rospy.Subscriber(topic_of('/master/after', True, 'aft_msgs/Checkpoint', 'checkpoints'), Checkpoint, acknowledge)
    if not wait_until(lambda: acks.get_num_connections() > 0, 10.0, 0.05):
        sys.exit('seed %d: the forged acks reach nobody' % seed)
    pid = node_api(rosgraph.Master('/checker').lookupNode('/slave/after'), 2.0).getPid('/checker')[2]
    time.sleep(0.3)   # the attacker's subscription to the checkpoints is heard (publishers take ~100 ms)
    os.kill(pid, signal.SIGSTOP)
    frozen.append(pid)
    frozen_at = time.monotonic()
    one(WARM)
    answered_at = time.monotonic()
    print('seed %d: SLAVE\'s After frozen after %d calls; the next answered in %.3f s; %d checkpoints acknowledged '
          'by the attacker' % (seed, WARM, answered_at - frozen_at, len(forged)), flush=True)
    if not forged:
        sys.exit('seed %d: the attacker saw no checkpoint to acknowledge' % seed)
    # Released on a forged ack, it comes in milliseconds; released by MASTER going on alone, once SLAVE's
    # ack is overdue (~ack_timeout, 1 s), with MASTER's `alone` alarm (on another topic: it may reach
    # this node just after the reply).
    if answered_at - frozen_at < 0.5:
        sys.exit('seed %d: the call was answered %.3f s into the freeze of SLAVE\'s After, before its ack could '
                 'be overdue: released on a forged ack. Alarms: %s' % (seed, answered_at - frozen_at,
                                                                      [a[1:3] for a in alarms[-6:]]))
    if not wait_until(lambda: any(s == '/master/after' and k == 'alone' for _, s, k, _ in list(alarms)), 5.0, 0.05):
        sys.exit('seed %d: the call was answered %.3f s into the freeze, and MASTER never said it went on alone: '
                 '%s' % (seed, answered_at - frozen_at, [a[1:3] for a in alarms[-6:]]))
    if not wait_until(lambda: any(s == '/master/after' and k == 'stray_ack' and '/attacker' in d
                                  for _, s, k, d in list(alarms)), 5.0, 0.05):
        sys.exit('seed %d: no stray_ack alarm from /master/after naming the attacker: %s' % (
            seed, [a[1:3] for a in alarms[-6:]]))
    for i in range(WARM + 1, WARM + 20):   # alone, MASTER serves on: every call once
        one(i)
    summary = checker.summary()
    if summary != {'correct': WARM + 20, 'lost': 0, 'duplicated': 0, 'reordered': 0, 'errors': 0}:
        sys.exit('seed %d: not exactly once: %s' % (seed, summary))
finally:
    for pid in frozen:
        try:
            os.kill(pid, signal.SIGCONT)
        except OSError:
            pass
    deployment.teardown()
    core.stop()
print('ok')
'''


def test_a_forged_ack_never_releases_a_reply_the_backup_does_not_hold():
    run_seeded(SCRIPT, home_prefix='aft_forged_ack_home_')
