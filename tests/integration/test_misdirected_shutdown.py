"""A ROS master's shutdown request meant for a dead node reaches the live process that now has its
address (a host back with its old address, ports handed out again: found on emulated hosts, where a
relaunched site's Proceed was shut down for its crash detector and its roslaunch stopped the site).

Reproduced exactly: a node name (/ghost) is registered with the address of a running witness (as the
dead process's registration is), then registered again from another address, so that the master asks
the old address to shut down, naming /ghost. The witness started by run_node ignores the request, names
it in a warning, and goes on answering; a control witness with the guard off
(AFT_OBEY_EVERY_SHUTDOWN=1, plain rospy) shuts down. Runs in a process of its own with a master of its
own; every process it starts carries the test's AFT_TEST_TAG and is killed at the end."""
from leftovers import run_tagged

SCRIPT = r'''
import os, subprocess, sys, tempfile
import rosgraph, rospy
from aft_msgs.srv import Witness
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until
log_dir = tempfile.mkdtemp(prefix='aft_bumped_')
core = start_master(log_dir)
procs = {}

def start(name, obey):
    env = dict(os.environ, AFT_OBEY_EVERY_SHUTDOWN='1' if obey else '0')
    procs[name] = subprocess.Popen(['rosrun', 'aft_ftm', 'witness', '__name:=%s' % name, '_initial_primary:=master'],
                                   env=env, stdout=open('%s/%s.out' % (log_dir, name), 'w'), stderr=subprocess.STDOUT)

def known(service):
    try:
        rosgraph.Master('/checker').lookupService(service)
        return True
    except Exception:
        return False

def bump_through(name):
    """/ghost_<name> registered at the witness's address, then from another: the master shuts the first down."""
    ghost = '/ghost_%s' % name
    address = rosgraph.Master('/checker').lookupNode('/' + name)
    rosgraph.Master(ghost).registerPublisher('/ghost_topic', 'std_msgs/String', address)
    rosgraph.Master(ghost).registerPublisher('/ghost_topic', 'std_msgs/String', 'http://127.0.0.1:9/')

try:
    start('guarded', obey=False)
    start('control', obey=True)
    rospy.init_node('checker')
    if not wait_until(lambda: known('/guarded/request') and known('/control/request'), 30.0, 0.1):
        sys.exit('the witnesses did not come up')
    bump_through('control')
    if not wait_until(lambda: procs['control'].poll() is not None, 10.0, 0.05):
        sys.exit('the control witness (plain rospy) did not obey the shutdown: the test cannot tell')
    bump_through('guarded')
    wait_until(lambda: procs['guarded'].poll() is not None, 3.0, 0.05)   # the control died within this
    if procs['guarded'].poll() is not None:
        sys.exit('the guarded witness obeyed a shutdown naming /ghost_guarded: %s'
                 % open(log_dir + '/guarded.out').read()[-2000:])
    answer = rospy.ServiceProxy('/guarded/request', Witness)(op=0, site='checker')
    out = open(log_dir + '/guarded.out').read()
    if 'ignored: it names another node' not in out:
        sys.exit('the guarded witness did not say it ignored the request: %s' % out[-2000:])
    print('control shut down; guarded witness answered at epoch %d' % answer.epoch)
finally:
    for p in procs.values():
        p.terminate()
    for p in procs.values():
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
    core.stop()
'''


def test_a_shutdown_meant_for_a_dead_node_at_this_address_is_ignored_and_plain_rospy_obeys_it():
    code, output = run_tagged(SCRIPT, timeout=120, home_prefix='aft_bumped_home_')
    assert code == 0, output[-3000:]
    assert 'guarded witness answered' in output, output[-3000:]
