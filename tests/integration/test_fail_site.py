"""A required node an adaptation launched dies: its site fail-stops through its own fail_stop topic.

The adaptation engine starts a replacement Before, Proceed or After under a guard
(aft_ftm.ros.guarded_launch) with --fail-site SITE. When that launch ends by itself, the guard tells
the site to fail-stop on /SITE/fail_stop, which its crash detector hears (then its peer takes over);
the site's launcher, which may run the other replica too, is left alone. Here the site is a process
standing for the site's launcher and a subscriber standing for its crash detector; a second launch
is retired on purpose (disarmed first) and must tell nothing. A third guard finds no subscriber
(the site is down already): it says so in an alarm. Runs in a process of its own with a master of
its own; every process it starts carries the test's AFT_TEST_TAG and is killed at the end."""
from leftovers import run_tagged

SCRIPT = r'''
import os, subprocess, sys, tempfile, time
import psutil, rospy
from aft_msgs.msg import Alarm, Failure
from aft_ftm.ros.graph import start_master
from aft_ftm.ros.guarded_launch import create_time_of, disarm_guard_of, guarded
from aft_ftm.site_guard import Owner
from aft_ftm.sites import process_tree, wait_until
core = start_master(tempfile.mkdtemp(prefix='aft_fail_site_'))
site = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)'])
owner = Owner(site.pid, create_time_of(site.pid))
started = [site]
try:
    rospy.init_node('checker')
    failures, alarms = [], []
    detector = rospy.Subscriber('/master/fail_stop', Failure, failures.append)
    rospy.Subscriber('/aft/alarms', Alarm, alarms.append)

    def run_guard(seconds, site_name, env=None):
        guard = subprocess.Popen(guarded([sys.executable, '-c', 'import time; time.sleep(%s)' % seconds], [owner],
                                         poll=0.05, grace=1.0, fail_site=site_name),
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        started.append(guard)
        return guard

    # 1. Retired on purpose: disarmed, then its node killed. Nothing is told.
    guard = run_guard(60, 'master')
    wait_until(lambda: len(process_tree(guard.pid)) >= 2, 10, 0.01)
    node = process_tree(guard.pid)[1]
    if disarm_guard_of(node.pid) != guard.pid:
        sys.exit('disarm_guard_of did not find the guard')
    said = [guard.stdout.readline() for _ in range(2)]   # what it guards and that it is disarmed, either first
    if not any('disarmed' in line for line in said):
        sys.exit('the guard did not say it was disarmed: %s' % said)
    node.kill()
    guard.wait(20)
    out = ''.join(said) + guard.stdout.read()
    if failures or ' fails: ' in out:
        sys.exit('a retired launch failed its site: %s %s' % (failures, out))
    # 2. The replacement dies by itself: the site is told, once, and its launcher runs on. The guard
    # started by a process roslaunch put in a namespace (the Monitoring Engine's /aft): the fail-stop's
    # node is named /fail_site_SITE_* all the same, the name the TLS policy binds to the site's party.
    guard = run_guard(0.5, 'master', env=dict(os.environ, ROS_NAMESPACE='/aft'))
    code = guard.wait(60)
    out = guard.stdout.read()
    if not wait_until(lambda: failures, 10, 0.02):
        sys.exit('no fail_stop heard (guard exit %s): %s' % (code, out))
    time.sleep(0.5)
    if len(failures) != 1 or failures[0].site != 'master' or 'ended by itself' not in failures[0].reason:
        sys.exit('wrong fail_stop: %s' % failures)
    if 'told on its fail_stop topic' not in out or site.poll() is not None:
        sys.exit('guard output or site wrong (site exit %s): %s' % (site.poll(), out))
    if not wait_until(lambda: any(a.kind == 'fail_stop' and 'told to stop' in a.detail for a in alarms), 5, 0.02):
        sys.exit('no fail_stop alarm: %s' % [(a.kind, a.detail) for a in alarms])
    source = [a.source for a in alarms if a.kind == 'fail_stop' and 'told to stop' in a.detail][0]
    if not source.startswith('/fail_site_master_'):
        sys.exit('the fail-stop came from %s, not a node named /fail_site_master_*' % source)
    print('told: %s' % failures[0].reason)
    # 3. Nobody listens on the site's topic (it is down): the alarm says the site could not be told.
    guard = run_guard(0.2, 'gone')
    guard.wait(60)
    out = guard.stdout.read()
    if not wait_until(lambda: any('could not be told' in a.detail and 'gone' in a.detail for a in alarms), 5, 0.02):
        sys.exit('no alarm for a site nobody listens for: %s %s' % ([a.detail for a in alarms], out))
    if 'had no subscriber' not in out:
        sys.exit('the guard did not say the site was not told: %s' % out)
    print('unheard: alarm raised')
finally:
    for proc in started:
        for p in process_tree(proc.pid):
            try:
                p.kill()
            except psutil.NoSuchProcess:
                pass
    core.stop()
'''


def test_a_dead_replacement_fail_stops_its_site_by_its_topic_and_a_retired_one_does_not():
    code, output = run_tagged(SCRIPT, home_prefix='aft_fail_site_home_')
    assert code == 0, output[-4000:]
    assert 'told: python' in output and 'unheard: alarm raised' in output, output[-4000:]
