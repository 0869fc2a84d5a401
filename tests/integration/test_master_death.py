"""The bank's failover works with the ROS master dead (issue 15).

The three sites of the bank demo (PBR, LFR, or PBR behind SEC gates) run under a master of their
own. A client calls /account through a persistent connection; after KILL_AT replies the roscore is
killed (SIGKILL of its whole process tree), after OFF_AT replies the MASTER site is powered off
(detection after 150 ms of silence). Every connection the failover needs was opened at set-up, so
SLAVE takes over without the master: every call is answered exactly once, SLAVE's state equals a
failure-free sequential run, SLAVE's Recovery says master_unreachable (an alarm), and its failover
record shows every step done. The script runs in a process of its own; every process it starts
carries the test's AFT_TEST_TAG and is killed at the end, pass or fail.
"""
import os
import subprocess
import sys
import tempfile
import uuid

import pytest
from leftovers import kill_tagged
from reporting import report

SCRIPT = r'''
import json, sys, tempfile, time
import rosgraph
import rospy
from aft_msgs.msg import Alarm
from aft_msgs.srv import Account, GetState
from std_msgs.msg import String
from aft_examples.bank import Account as Model, ReplyChecker, operation
from aft_examples.ros.bank_nodes import account_caller, drive_with_faults
from aft_examples.ros.deployment import PbrDeployment, start_retrying
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until

COUNT, KILL_AT, OFF_AT, LIMIT = 600, 150, 250, 60.0
log_dir = tempfile.mkdtemp(prefix='aft_nomaster_')
core = start_master(log_dir)
# Detection after 150 ms of silence: a false suspicion before the faults (30 ms has seen them on a
# loaded machine) would fail the sites over while the master lives, and test nothing.
MECHANISM, SEC = sys.argv[1], sys.argv[2] == 'sec'
deployment = PbrDeployment(log_dir, timeout=0.15, mechanism=MECHANISM, sec=SEC)
try:
    rospy.init_node('checker', disable_signals=True)
    start_retrying(deployment)
    alarms, events = [], []
    alarm_log = rospy.Subscriber('/aft/alarms', Alarm, alarms.append, tcp_nodelay=True)
    rospy.Subscriber('/slave/recovery/events', String, lambda m: events.append(json.loads(m.data)))
    pubs = rosgraph.Master('/checker').getSystemState()[0]
    alarm_publishers = [n for t, nodes in pubs if t == '/aft/alarms' for n in nodes if n != '/checker']
    if not wait_until(lambda: alarm_log.get_num_connections() >= len(alarm_publishers), 20):
        sys.exit('the alarm log is not connected to the %d publishers of /aft/alarms' % len(alarm_publishers))
    # Everything the client needs after the master's death is connected now.
    account = rospy.ServiceProxy('/account', Account, persistent=True)
    account.wait_for_service(30)
    slave_state = rospy.ServiceProxy('/slave/bank_server/get_state', GetState, persistent=True)
    slave_state()
    checker = ReplyChecker()
    faults = {}

    def kill_roscore():
        faults['roscore_killed'] = core.power_off()
        faults['roscore_wall'] = time.time()

    def power_off_master():
        faults['master_site_killed'] = deployment.sites['master'].power_off()
        faults['master_site_wall'] = deployment.sites['master'].powered_off_at
    faults['records'], _ = drive_with_faults(account_caller(account), COUNT, checker,
                                             [(KILL_AT, kill_roscore), (OFF_AT, power_off_master)], LIMIT)
    if faults['records'] is None:
        sys.exit('not every call answered within %.0f s: %s; faults %s; slave recovery %s' % (
            LIMIT, checker.summary(), {k: v for k, v in faults.items() if k != 'records'},
            [e for e in events if 'failed_site' in e or e.get('last_recovery')][-1:]))
    if 'master_site_wall' not in faults:
        sys.exit('the faults were not injected: %s' % faults)
    summary = checker.summary()
    if summary != {'correct': COUNT, 'lost': 0, 'duplicated': 0, 'reordered': 0, 'errors': 0}:
        sys.exit('not exactly once: %s' % summary)
    model, expected = Model(), Model()
    model.set_state(slave_state().state)
    for i in range(COUNT):
        expected.apply(*operation(i))
    if model.snapshot() != expected.snapshot():
        sys.exit('SLAVE state %s differs from a failure-free run %s' % (model.snapshot(), expected.snapshot()))
    if not wait_until(lambda: any(a.kind == 'master_unreachable' and a.source == '/slave/recovery'
                                  for a in alarms), 10):
        sys.exit('no master_unreachable alarm from /slave/recovery: %s; slave recovery events %s'
                 % ([(a.source, a.kind, a.detail) for a in alarms], events))
    if not wait_until(lambda: any('failed_site' in e for e in events), 10):
        sys.exit('no failover record of /slave/recovery: %s' % events)
    failover = [e for e in events if 'failed_site' in e][-1]
    if not failover['ok'] or failover['failed_site'] != 'master':
        sys.exit('the failover failed: %s' % failover)
    if failover['detected_wall'] < faults['master_site_wall']:
        sys.exit('SLAVE took over before the MASTER site was powered off (a false suspicion): %s' % failover)
    replies = [r for r in faults['records'] if r[2] > faults['master_site_wall']]
    print('FIGURES ' + json.dumps({
        'mechanism': MECHANISM + (' under SEC' if SEC else ''), 'calls': COUNT,
        'roscore_processes_killed': faults['roscore_killed'],
        'recovery_ms': round(failover['seconds'] * 1e3, 1),
        'steps': ['%s %.1f ms' % (s['step'], s['seconds'] * 1e3) for s in failover['steps']],
        'failover_ms': round((replies[0][2] - faults['master_site_wall']) * 1e3, 1) if replies else None,
        'alarms': sorted({a.kind for a in alarms})}))
finally:
    deployment.teardown()
    core.stop()
'''


@pytest.mark.family('master_death', 1)
@pytest.mark.parametrize('mechanism,sec', [('pbr', ''), ('lfr', ''), ('pbr', 'sec')])
def test_the_bank_fails_over_with_the_ros_master_dead(mechanism, sec):
    """PBR; LFR (the follower takes over); PBR behind SEC gates (the backup's gate is the entry)."""
    tag = uuid.uuid4().hex
    env = dict(os.environ, AFT_TEST_TAG=tag, ROS_HOME=tempfile.mkdtemp(prefix='aft_nomaster_home_'))
    try:
        run = subprocess.run([sys.executable, '-c', SCRIPT, mechanism, sec or 'plain'], env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=400)
    finally:
        leftovers = kill_tagged(tag)
    output = run.stdout.decode(errors='replace')
    assert run.returncode == 0, output[-5000:]
    figures = [line[len('FIGURES '):] for line in output.splitlines() if line.startswith('FIGURES ')]
    assert figures, output[-3000:]
    report('master death: %s' % figures[0])
    assert not leftovers, 'processes left running: %s' % [p.pid for p in leftovers]
