"""A backup whose Protocol lost stored replies takes over with every one of them (PBR, the bank).

The backup's After hands each checkpoint's replies to its Protocol over a connection inside the site.
Here that connection is reset (``ss -K``, as a kernel or a restarted node would) while the client
calls /account; the messages sent until it is connected again are lost: the Protocol stores later
checkpoints' replies, not those. Then the MASTER site is powered off. Comparing only the highest
number it stored, the Protocol used to take over at once, and a request whose reply it had lost ran
again when its Proxy sent it again (found by the simulation, loss,local); and where the last ones
were lost, it refused to take over, and nobody served. Now it counts stored checkpoints without a
gap and, short of some, asks its After for every reply it holds (~stored_replies, a connection of
its own, opened at set-up), and says so. Checked: every call answered exactly once, SLAVE's state
equals a failure-free run, the replies were asked for, the failover record is ok.
Runs in a process of its own with a master of its own; every process it starts carries the test's
AFT_TEST_TAG and is killed at the end, pass or fail."""
import os
import random

from leftovers import run_tagged

SCRIPT = r'''
import json, random, re, subprocess, sys, tempfile
import rosgraph, rospy
from aft_msgs.srv import Account, GetState
from rosgraph_msgs.msg import Log
from std_msgs.msg import String
from aft_examples.bank import Account as Model, ReplyChecker, operation
from aft_examples.ros.bank_nodes import account_caller, drive_with_faults
from aft_examples.ros.deployment import PbrDeployment, start_retrying
from aft_ftm.ros.fencing import node_api
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until

seed = int(sys.argv[1])
rng = random.Random(seed)
COUNT, LIMIT = 400, 90.0
CUT_AT = rng.randrange(60, 160)
OFF_AT = CUT_AT + rng.randrange(5, 40)
print('seed %d: cut at reply %d, MASTER off at reply %d' % (seed, CUT_AT, OFF_AT), flush=True)
log_dir = tempfile.mkdtemp(prefix='aft_stored_gap_')
core = start_master(log_dir)
deployment = PbrDeployment(log_dir, timeout=0.15, mechanism='pbr')

def stored_link_port():
    """The Protocol's local port of its connection to the After's stored replies (/slave/aft2pro_s)."""
    uri = rosgraph.Master('/checker').lookupNode('/slave/protocol')
    _, _, bus = node_api(uri, 2.0).getBusInfo('/checker')
    for _, _, direction, _, topic, _, info in bus:
        if direction == 'i' and topic == '/slave/aft2pro_s':
            return int(re.search(r'on port (\d+)', info).group(1))
    raise RuntimeError('no /slave/aft2pro_s connection: %s' % bus)

try:
    rospy.init_node('checker', disable_signals=True)
    start_retrying(deployment)
    said = []
    rospy.Subscriber('/rosout', Log, lambda m: said.append(m.msg) if m.name == '/slave/protocol' else None)
    events = []
    rospy.Subscriber('/slave/recovery/events', String, lambda m: events.append(json.loads(m.data)))
    account = rospy.ServiceProxy('/account', Account, persistent=True)
    account.wait_for_service(30)
    slave_state = rospy.ServiceProxy('/slave/bank_server/get_state', GetState, persistent=True)
    port = stored_link_port()
    checker = ReplyChecker()
    faults = {}

    def cut():
        reset = subprocess.run(['ss', '-K', '( sport = :%d or dport = :%d )' % (port, port)],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, universal_newlines=True)
        faults['cut'] = reset.stdout.count('ESTAB')

    def power_off_master():
        faults['master_site_killed'] = deployment.sites['master'].power_off()
        faults['master_site_wall'] = deployment.sites['master'].powered_off_at
    records, _ = drive_with_faults(account_caller(account), COUNT, checker, [(CUT_AT, cut), (OFF_AT, power_off_master)],
                                   LIMIT)
    if records is None:
        sys.exit('seed %d: not every call answered within %.0f s: %s; slave protocol said %s' % (
            seed, LIMIT, checker.summary(), said[-5:]))
    if not faults.get('cut') or 'master_site_wall' not in faults:
        sys.exit('seed %d: the faults were not injected: %s' % (seed, {k: v for k, v in faults.items() if k != 'records'}))
    summary = checker.summary()
    if summary != {'correct': COUNT, 'lost': 0, 'duplicated': 0, 'reordered': 0, 'errors': 0}:
        sys.exit('seed %d: not exactly once: %s; slave protocol said %s' % (seed, summary, said[-5:]))
    model, expected = Model(), Model()
    model.set_state(slave_state().state)
    for i in range(COUNT):
        expected.apply(*operation(i))
    if model.snapshot() != expected.snapshot():
        sys.exit('seed %d: SLAVE state %s differs from a failure-free run %s' % (seed, model.snapshot(), expected.snapshot()))
    if not wait_until(lambda: any('failed_site' in e for e in events), 10):
        sys.exit('seed %d: no failover record of /slave/recovery: %s' % (seed, events))
    failover = [e for e in events if 'failed_site' in e][-1]
    if not failover['ok']:
        sys.exit('seed %d: the failover failed: %s' % (seed, failover))
    wait_until(lambda: any('taken from its After' in s for s in said), 5)
    taken = [s for s in said if 'taken from its After' in s]
    print('FIGURES ' + json.dumps({'sockets_reset': faults['cut'], 'taken': taken[:1],
                                   'recovery_ms': round(failover['seconds'] * 1e3, 1)}), flush=True)
    if not taken:
        sys.exit('seed %d: the Protocol took over without asking its After for the lost replies (said: %s)'
                 % (seed, said[-8:]))
finally:
    deployment.teardown()
    core.stop()
print('ok')
'''


def test_a_backup_whose_protocol_lost_stored_replies_takes_over_with_every_one_of_them():
    seed = int(os.environ.get('AFT_SEED', random.randrange(1 << 16)))
    code, output = run_tagged(SCRIPT, args=[str(seed)], timeout=300, home_prefix='aft_stored_gap_home_')
    print(output[-2000:])
    assert code == 0 and output.rstrip().endswith('ok'), 'seed %d (AFT_SEED replays):\n%s' % (seed, output[-5000:])
