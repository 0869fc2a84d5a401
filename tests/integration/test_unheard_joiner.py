"""A replica site whose crash detector is silent is never admitted as the backup, even though its After
still joins; once its detector beats again, it is admitted (PBR and LFR, the bank).

The case from a campaign under load: a site stopping (its server died, its detector announced its
fail-stop) could not be fenced (the witness had just been relaunched), and its After, still running,
was admitted three times in a second, each time declared failed 30 ms later by the new monitor. Here
SLAVE's crash detector is frozen (SIGSTOP) for a drawn 3-5 s while clients call. The sites' power
switch is a fence agent that never confirms (``command:/bin/false``), so MASTER's Recovery cannot
fail-silence SLAVE, and SLAVE's After re-joins MASTER while its detector is silent. Properties:
- no configuration of the witness names SLAVE as the backup while its detector is frozen, and the
  refusal is said (``not admitted``);
- SLAVE is the backup again within 30 s of the thaw;
- every call answered exactly once, in order;
- MASTER's Recovery says it could not fence SLAVE (recovery_incomplete), not that nobody may serve.
Runs in a process of its own with a master of its own; every process it starts carries the test's
AFT_TEST_TAG and is killed at the end, pass or fail. AFT_SEED replays a run."""
import pytest
from leftovers import run_seeded

SCRIPT = r"""
import contextlib, random, sys, tempfile, threading, time
import psutil, rosgraph, rospy
from aft_msgs.msg import Alarm, Configuration
from aft_msgs.srv import Account
from aft_examples.bank import ReplyChecker
from aft_examples.ros.bank_nodes import account_caller, drive_with_faults
from aft_examples.ros.deployment import PbrDeployment, start_retrying
from aft_ftm.ros.fencing import node_api
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until

seed, mechanism = int(sys.argv[1]), sys.argv[2]
rng = random.Random(seed)
FREEZE_S, FREEZE_AT, COUNT, LIMIT = rng.uniform(3.0, 5.0), rng.randrange(100, 300), 2500, 90.0
print('seed %d: %s, /slave/crash_detector frozen %.2f s at reply %d' % (seed, mechanism, FREEZE_S, FREEZE_AT),
      flush=True)
log_dir = tempfile.mkdtemp(prefix='aft_unheard_joiner_')
core = start_master(log_dir)
# Detection at 300 ms: the point here is not detection speed, and under the suite's load a 30 ms detector
# has suspected a healthy peer before a test's own fault (issue 15; README, Tests).
deployment = PbrDeployment(log_dir, mechanism=mechanism, power_switch='command:/bin/false', timeout=0.3)
frozen, marks = [], {}


def thaw():
    for process in frozen:
        with contextlib.suppress(psutil.NoSuchProcess):
            process.resume()
    marks.setdefault('thawed', time.time())


def fail(what):
    sys.exit('seed %d (%s): %s; configurations %s; alarms %s' % (seed, mechanism, what, configurations[-6:],
                                                                 alarms[-8:]))


try:
    rospy.init_node('checker', disable_signals=True)
    start_retrying(deployment)
    alarms, configurations = [], []
    rospy.Subscriber('/aft/alarms', Alarm, lambda m: alarms.append('%s %s: %s' % (m.source, m.kind, m.detail)))
    rospy.Subscriber('/aft/witness/configuration', Configuration,
                     lambda m: configurations.append((m.stamp.to_sec(), m.epoch, m.primary, m.backup)))
    account = rospy.ServiceProxy('/account', Account, persistent=True)
    account.wait_for_service(30)
    if not wait_until(lambda: any(c[3] == 'slave' for c in configurations), 60, 0.05):
        fail('SLAVE never became the backup')
    detector = node_api(rosgraph.Master('/checker').lookupNode('/slave/crash_detector'), 2.0).getPid('/checker')[2]
    checker = ReplyChecker()

    def freeze():
        frozen.append(psutil.Process(detector))
        frozen[0].suspend()
        marks['frozen'] = time.time()
        timer = threading.Timer(FREEZE_S, thaw)
        timer.daemon = True
        timer.start()
    records, _ = drive_with_faults(account_caller(account), COUNT, checker, [(FREEZE_AT, freeze)], LIMIT)
    if 'frozen' not in marks:
        fail('the calls ended before the freeze')
    wait_until(lambda: 'thawed' in marks, FREEZE_S + 10, 0.05)
    summary = checker.summary()
    if records is None or any(summary[k] for k in ('lost', 'duplicated', 'reordered', 'errors')):
        fail('not every call answered exactly once within %.0f s: %s' % (LIMIT, summary))
    # The configuration in force when the detector froze named SLAVE; any later one naming it before the
    # thaw admitted a site whose detector was silent.
    admitted = [c for c in configurations if marks['frozen'] < c[0] < marks['thawed'] and c[3] == 'slave']
    if admitted:
        fail('SLAVE admitted as the backup while its crash detector was frozen: %s' % admitted)
    refused = [a for a in alarms if 'hears no beat of site slave' in a]   # the gate's own words
    if not refused:
        fail('SLAVE\'s After never tried to join while its detector was frozen, or the refusal was silent')
    # SLAVE could not be fenced, and MASTER serves on alone: said so, and never as "nobody may serve".
    if not any(a.startswith('/master/recovery recovery_incomplete') for a in alarms):
        fail('MASTER could not fence SLAVE, and its Recovery did not say so')
    if any(a.startswith('/master/recovery promotion_failed') for a in alarms):
        fail('MASTER serves alone, yet its Recovery said nobody may serve')
    if not wait_until(lambda: any(c[0] > marks['thawed'] and c[3] == 'slave' for c in configurations), 30, 0.05):
        fail('SLAVE not admitted again within 30 s of the thaw')
    back = min(c[0] for c in configurations if c[0] > marks['thawed'] and c[3] == 'slave') - marks['thawed']
    print('RESULT %s: %d calls once each; %d refusals while frozen (%s); admitted %.2f s after the thaw'
          % (mechanism, summary['correct'], len(refused), refused[0][:200], back), flush=True)
finally:
    thaw()
    deployment.teardown()
    core.stop()
print('ok')
"""


@pytest.mark.family('unheard_joiner', 1)
@pytest.mark.parametrize('mechanism', ['pbr', 'lfr'])
def test_a_site_whose_detector_is_silent_is_not_admitted_until_it_beats_again(mechanism):
    run_seeded(SCRIPT, [mechanism], home_prefix='aft_unheard_joiner_home_')
