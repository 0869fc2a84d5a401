"""A crash detector's failure report is never lost to a Recovery that is not connected yet.

rospy handles a publisher's inbound connections one at a time: one stalled handshake held a
Recovery's subscription back for 60 s in a CI run, and the failure published meanwhile reached
nobody (the backup never took over). Here the detector declares its peer failed with nobody
subscribed: it must say so on /aft/alarms and send the report as soon as a subscriber connects.
The script runs in a process of its own, with a master of its own; every process it starts carries
the test's AFT_TEST_TAG and is killed at the end."""
import os
import subprocess
import sys
import tempfile
import uuid

from leftovers import kill_tagged

SCRIPT = r'''
import subprocess, sys, tempfile, time
import rospy
from aft_msgs.msg import Alarm, Failure
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until
core = start_master(tempfile.mkdtemp(prefix='aft_detector_'))
detector = subprocess.Popen(['rosrun', 'aft_ftm', 'crash_detector', '__name:=detector', '_site:=a', '_peer:=b',
                             '_period:=0.01', '_timeout:=0.05', '_startup_grace:=0.5',
                             'failures:=/t/failures', 'peer_heartbeat:=/t/peer', 'heartbeat:=/t/mine'])
try:
    rospy.init_node('checker')
    alarms, failures = [], []
    rospy.Subscriber('/aft/alarms', Alarm, alarms.append)
    if not wait_until(lambda: any(a.kind == 'failure_undelivered' for a in alarms), 30, 0.05):
        sys.exit('no failure_undelivered alarm: %s' % [(a.kind, a.detail) for a in alarms])
    rospy.Subscriber('/t/failures', Failure, failures.append)       # a Recovery connects late
    if not wait_until(lambda: failures, 10, 0.05):
        sys.exit('the failure report never reached the subscriber that connected late')
    print('delivered late: site %s, %s' % (failures[0].site, failures[0].reason))
    sys.exit(0 if failures[0].site == 'b' and len(failures) == 1 else 'wrong report(s): %s' % failures)
finally:
    detector.terminate()
    detector.wait(10)
    core.stop()
'''


def test_a_failure_declared_before_recovery_connects_is_sent_once_it_does():
    tag = uuid.uuid4().hex
    env = dict(os.environ, AFT_TEST_TAG=tag, ROS_HOME=tempfile.mkdtemp(prefix='aft_detector_home_'))
    try:
        run = subprocess.run([sys.executable, '-c', SCRIPT], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             timeout=120)
    finally:
        leftovers = kill_tagged(tag)
    output = run.stdout.decode(errors='replace')
    assert run.returncode == 0, output[-3000:]
    assert 'delivered late: site b' in output, output[-3000:]
    assert not leftovers, 'processes left running: %s' % [p.pid for p in leftovers]
