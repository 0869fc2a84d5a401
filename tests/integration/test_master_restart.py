"""A ROS master killed and restarted on its port: the nodes started by run_node register again.

Plain rospy registers once, at init_node: a master restarted under running nodes knows none of them,
so their services cannot be looked up and their topics get no new peers. Here a real witness (run
by run_node, checking every 0.3 s) and a second one with the check turned off
(AFT_MASTER_REJOIN_PERIOD=0, plain rospy's behaviour: the control) run, the checker subscribes to
a topic, the roscore is killed (SIGKILL of its whole tree) and started again on the same port. Then
the witness's service is looked up and called, a new subscription gets its latched configuration,
a publisher started after the restart reaches the checker's old subscription (though the checker
is known to the new master by its newer subscription), the witness's parameter is back; the
control witness stays unknown to the new master. Runs in a process of its own with a master of its own; every
process it starts carries the test's AFT_TEST_TAG and is killed at the end."""
from leftovers import run_tagged

# What both scripts start with: a master of their own, the witnesses they start, a service lookup.
PRELUDE = r'''
import contextlib, io, os, subprocess, sys, tempfile, time
import rosgraph, rosnode, rospy
from std_msgs.msg import String
from aft_msgs.msg import Configuration
from aft_msgs.srv import Witness
from aft_ftm.ros.graph import start_master
from aft_ftm.ros.rejoin import keep_registered
from aft_ftm.sites import wait_until
log_dir = tempfile.mkdtemp(prefix='aft_rejoin_')
core = start_master(log_dir)
port = int(os.environ['ROS_MASTER_URI'].rsplit(':', 1)[1])
procs = []

def start(argv, name, period):
    env = dict(os.environ, AFT_MASTER_REJOIN_PERIOD=period)
    procs.append(subprocess.Popen(argv, env=env, stdout=open('%s/%s.out' % (log_dir, name), 'w'),
                                  stderr=subprocess.STDOUT))

def known(name):
    try:
        rosgraph.Master('/checker').lookupService(name)
        return True
    except Exception:
        return False

def stop_all():
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
    core.stop()
'''

SCRIPT = PRELUDE + r'''
try:
    start(['rosrun', 'aft_ftm', 'witness', '__name:=witness', '_initial_primary:=master'], 'witness', '0.3')
    start(['rosrun', 'aft_ftm', 'witness', '__name:=control', '_initial_primary:=master'], 'control', '0')
    rospy.init_node('checker')
    keep_registered(0.3)
    heard = []
    rospy.Subscriber('/probe', String, lambda m: heard.append(m.data))
    if not wait_until(lambda: known('/witness/request') and known('/control/request'), 30.0, 0.1):
        sys.exit('the witnesses did not come up')
    core.power_off()                       # the roscore's tree: rosmaster and rosout, SIGKILL
    if known('/witness/request'):
        sys.exit('the master still answers after its power-off')
    core = start_master(log_dir, port=port)
    t0 = time.monotonic()
    if not wait_until(lambda: known('/witness/request'), 10.0, 0.05):
        sys.exit('the witness did not register again within 10 s of the restart')
    rejoined_s = time.monotonic() - t0
    answer = rospy.ServiceProxy('/witness/request', Witness)(op=0, site='checker')
    configurations = []
    rospy.Subscriber('/witness/configuration', Configuration, configurations.append)
    if not wait_until(lambda: configurations, 10.0, 0.05):
        sys.exit('a new subscription to the witness got nothing')
    start(['rostopic', 'pub', '-l', '/probe', 'std_msgs/String', 'after the restart'], 'probe', '0')
    if not wait_until(lambda: heard, 10.0, 0.05):
        sys.exit('a publisher started after the restart did not reach a subscription made before it')
    if known('/control/request'):
        sys.exit('the control witness (check off) was found: the test cannot tell')
    master = rosgraph.Master('/checker')
    if master.getParam('/witness/initial_primary') != 'master':
        sys.exit('the witness did not set again the parameter it read')
    if master.hasParam('/control/initial_primary'):
        sys.exit('the control witness parameter is back: the test cannot tell')
    out = open(log_dir + '/witness.out').read()
    if 'registered again with the ROS master' not in out:
        sys.exit('the witness did not log its registration: %s' % out[-2000:])
    print('rejoined after %.2f s; epoch %d; configuration heard; probe heard: %r' % (rejoined_s, answer.epoch, heard[0]))
finally:
    stop_all()
'''


def test_nodes_register_again_with_a_restarted_master_and_plain_rospy_ones_do_not():
    code, output = run_tagged(SCRIPT, timeout=150, home_prefix='aft_rejoin_home_')
    assert code == 0, output[-3000:]
    assert 'rejoined after' in output and 'probe heard' in output, output[-3000:]


CLEANED = PRELUDE + r'''
try:
    start(['rosrun', 'aft_ftm', 'witness', '__name:=witness', '_initial_primary:=master'], 'witness', '0.3')
    start(['rosrun', 'aft_ftm', 'witness', '__name:=control', '_initial_primary:=master'], 'control', '0')
    rospy.init_node('checker')
    if not wait_until(lambda: known('/witness/request') and known('/control/request'), 30.0, 0.1):
        sys.exit('the witnesses did not come up')
    master = rosgraph.Master('/checker')
    # What rosnode cleanup does to a node that answered its ping too late: everything unregistered.
    with contextlib.redirect_stdout(io.StringIO()):
        rosnode.cleanup_master_blacklist(master, ['/witness', '/control'])
    if known('/witness/request') or known('/control/request'):
        sys.exit('the clean-up left registrations: the test cannot tell')
    t0 = time.monotonic()
    if not wait_until(lambda: known('/witness/request'), 10.0, 0.05):
        sys.exit('the witness did not register again within 10 s of being cleaned up')
    rejoined_s = time.monotonic() - t0
    answer = rospy.ServiceProxy('/witness/request', Witness)(op=0, site='checker')   # and it answers
    if known('/control/request'):
        sys.exit('the control witness (check off) is registered again: the test cannot tell')
    print('re-registered %.2f s after the clean-up; epoch %d' % (rejoined_s, answer.epoch))
finally:
    stop_all()
'''


def test_a_live_node_whose_registrations_a_clean_up_removed_registers_again():
    """rosnode cleanup (and the deployments' clean-up of dead nodes) takes a live node that answers its
    ping late for dead and unregisters it; the master still knows its name. Found by the hosts campaign:
    a backup's crash detector cleaned up this way never heard its re-joined peer again. The node's own
    ~get_loggers, gone from the master, makes it register everything again."""
    code, output = run_tagged(CLEANED, timeout=120, home_prefix='aft_cleaned_home_')
    assert code == 0, output[-3000:]
    assert 're-registered' in output, output[-3000:]
