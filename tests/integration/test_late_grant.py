"""A witness grant that comes after its call timed out still fences the failed site's launcher.

MASTER's whole site freezes (every process SIGSTOPped: its launcher too) while the witness is frozen
as well. SLAVE's Recovery asks the witness for the next epoch; the call times out (1 s), and a retry
is due half a second later. The witness is resumed in between: it grants the PROMOTE it had queued
and publishes the configuration, which SLAVE's Recovery takes as a late promotion (late_promotion).
Its fail-silence must kill MASTER's launcher with the rest: left stopped, the launcher is one
SIGCONT away from starting MASTER's nodes again (a respawn, a node it had not started yet) beside the
new primary. Before (session 36) the promotion carried no launcher pid (the failure it followed was
the configuration, not the heartbeat's report): only the nodes learned by pid were killed. Checked:
the late promotion happened, MASTER's launcher is gone within seconds, and every call was answered
exactly once by SLAVE. Runs in a process of its own with a master of its own; every process it
starts carries the test's AFT_TEST_TAG and is killed at the end, pass or fail. AFT_SEED replays a run."""
from leftovers import run_seeded

SCRIPT = r"""
import json, random, signal, sys, tempfile, time
import psutil, rosgraph, rospy
from std_msgs.msg import String
from aft_msgs.msg import Alarm, Configuration
from aft_msgs.srv import Account
from aft_examples.bank import ReplyChecker
from aft_examples.ros.bank_nodes import account_caller, drive_with_faults
from aft_examples.ros.deployment import PbrDeployment, start_retrying
from aft_ftm.ros.fencing import node_api
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import process_tree, wait_until

seed = int(sys.argv[1])
rng = random.Random(seed)
AT, COUNT, LIMIT = rng.randrange(50, 300), 800, 90.0
print('seed %d: MASTER and the witness frozen at reply %d' % (seed, AT), flush=True)
log_dir = tempfile.mkdtemp(prefix='aft_late_grant_')
core = start_master(log_dir)
# Detection at 300 ms: the point here is not detection speed, and under the suite's load a 30 ms detector
# has suspected a healthy peer before a test's own fault (issue 15; README, Tests).
deployment = PbrDeployment(log_dir, timeout=0.3)
alarms, configurations, attempts, frozen = [], [], [], []


def fail(what):
    sys.exit('seed %d: %s; configurations %s; alarms %s' % (seed, what, configurations[-6:], alarms[-8:]))


def on_event(msg):
    record = json.loads(msg.data)
    if record.get('failed_site') and any(not s['ok'] and 'unreachable' in s['detail'] for s in record.get('steps', [])):
        attempts.append(time.monotonic())


def stop(procs):
    for proc in procs:
        try:
            proc.send_signal(signal.SIGSTOP)
            frozen.append(proc)
        except psutil.Error:
            pass


try:
    rospy.init_node('checker', disable_signals=True)
    start_retrying(deployment)
    rospy.Subscriber('/aft/alarms', Alarm, lambda m: alarms.append((m.source, m.kind, m.detail)))
    rospy.Subscriber('/aft/witness/configuration', Configuration,
                     lambda m: configurations.append((m.epoch, m.primary, m.backup)))
    rospy.Subscriber('/slave/recovery/events', String, on_event)
    account = rospy.ServiceProxy('/account', Account, persistent=True)
    account.wait_for_service(30)
    if not wait_until(lambda: any(c[2] == 'slave' for c in configurations), 60, 0.05):
        fail('SLAVE never became the backup')
    master = rosgraph.Master('/checker')
    witness = psutil.Process(node_api(master.lookupNode('/aft/witness'), 2.0).getPid('/checker')[2])
    launcher = psutil.Process(deployment.sites['master'].pid)
    checker = ReplyChecker()
    resumed = {}

    def freeze():
        stop([witness])
        stop([launcher] + process_tree(launcher.pid)[1:])   # the launcher first: it starts nothing meanwhile
        # The witness is resumed once SLAVE's first PROMOTE timed out, before its retry (0.5 s later).
        if not wait_until(lambda: attempts, 10.0, 0.01):
            return
        time.sleep(rng.uniform(0.0, 0.2))
        witness.send_signal(signal.SIGCONT)
        resumed['at'] = time.monotonic()
    records, _ = drive_with_faults(account_caller(account), COUNT, checker, [(AT, freeze)], LIMIT)
    if not attempts:
        fail('SLAVE\'s Recovery never found the witness unreachable: nothing tested')
    if not any(s == '/slave/recovery' and k == 'late_promotion' for s, k, _ in alarms):
        fail('SLAVE did not take over by the late grant (the retry came first?): nothing tested')
    summary = checker.summary()
    if records is None or any(summary[k] for k in ('lost', 'duplicated', 'reordered', 'errors')):
        fail('not every call answered exactly once within %.0f s: %s' % (LIMIT, summary))
    if not wait_until(lambda: not launcher.is_running() or launcher.status() == psutil.STATUS_ZOMBIE, 5.0, 0.05):
        fail('MASTER\'s launcher (pid %d) is still there, stopped, %.1f s after the late promotion: one SIGCONT '
             'starts its nodes again' % (launcher.pid, time.monotonic() - resumed['at']))
    print('RESULT %d calls once each; the witness resumed %.0f ms after SLAVE\'s PROMOTE timed out; SLAVE took '
          'over by the late grant and killed MASTER\'s launcher' % (summary['correct'],
                                                                   (resumed['at'] - attempts[0]) * 1e3), flush=True)
finally:
    for proc in frozen:
        try:
            proc.send_signal(signal.SIGCONT)
        except psutil.Error:
            pass
    deployment.teardown()
    core.stop()
print('ok')
"""


def test_a_witness_grant_that_came_after_its_call_timed_out_still_fences_the_failed_sites_launcher():
    run_seeded(SCRIPT, home_prefix='aft_late_grant_home_')
