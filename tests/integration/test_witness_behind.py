"""A witness restarted without its record (no state file) under running sites: it must grant nothing.

A real witness (no ~state_file) and a site's WitnessClient as the replicas use it: the site registers
as the first primary and admits a backup (epoch 2), subscribed to the configurations. The witness is
then stopped and started again: it publishes epoch 0. The site hears a configuration older than one
it heard and tells the witness (a STATUS saying epoch 2); the witness raises ``witness_behind`` and
from then on grants nothing: a site started again claiming the first primary's role (which a fresh
witness grants) is refused, and the running site's own requests are refused as "behind", not
answered as if its configuration were gone (a "deposed" primary would fail-stop). Before this, the
claim was granted: a second primary, serving from an empty state. Runs in a process of its own with a
master of its own; every process it starts carries the test's AFT_TEST_TAG and is killed at the end."""
from leftovers import run_tagged

SCRIPT = r'''
import os, subprocess, sys, tempfile, time
import rospy
from aft_msgs.msg import Alarm
from aft_ftm.ros.graph import start_master
from aft_ftm.ros.witness_client import WitnessClient, WitnessUnreachable
from aft_ftm.sites import wait_until
from aft_ftm.witness import Op
log_dir = tempfile.mkdtemp(prefix='aft_witness_behind_')
core = start_master(log_dir)
procs = []

def start_witness(n):
    procs.append(subprocess.Popen(['rosrun', 'aft_ftm', 'witness', '__ns:=/aft', '__name:=witness'],
                                  stdout=open('%s/witness%d.out' % (log_dir, n), 'w'), stderr=subprocess.STDOUT))

def ask(client, op, **kwargs):
    try:
        return client.request(op, **kwargs)
    except WitnessUnreachable as e:
        return e

try:
    start_witness(1)
    rospy.init_node('site_master')
    alarms, configurations = [], []
    rospy.Subscriber('/aft/alarms', Alarm, lambda a: alarms.append(a) if a.kind == 'witness_behind' else None)
    master = WitnessClient('/aft/witness/request', 'master', os.getpid(), timeout=2.0)
    if not master.setup(30.0):
        sys.exit('the witness did not come up')
    grant = ask(master, Op.REGISTER, claim=True)
    admit = ask(master, Op.ADMIT, peer='slave', peer_incarnation='s1')
    if not (getattr(grant, 'granted', False) and getattr(admit, 'granted', False) and admit.epoch == 2):
        sys.exit('set-up: %r, %r' % (grant, admit))
    master.subscribe(lambda c: configurations.append(c.epoch))
    if not wait_until(lambda: 2 in configurations, 10.0, 0.05):
        sys.exit('the configuration of epoch 2 was not heard: %s' % configurations)
    procs.pop().terminate()
    start_witness(2)                       # no state file: its record is gone
    if not wait_until(lambda: 0 in configurations, 20.0, 0.05):
        sys.exit('the restarted witness\'s configuration was not heard: %s' % configurations)
    if not wait_until(lambda: alarms, 10.0, 0.05):
        sys.exit('no witness_behind alarm after the site heard epoch 0 (epochs heard: %s)' % configurations)
    restarted = WitnessClient('/aft/witness/request', 'slave', os.getppid(), timeout=2.0)
    restarted.setup(10.0)
    claim = ask(restarted, Op.REGISTER, claim=True)
    if not isinstance(claim, WitnessUnreachable) or 'lost or rolled back' not in str(claim):
        sys.exit('a site claiming the first primary\'s role was answered %r' % (claim,))
    own = ask(master, Op.EXCLUDE)
    if not isinstance(own, WitnessUnreachable) or 'lost or rolled back' not in str(own):
        sys.exit('the running primary was answered %r' % (own,))
    print('configurations heard %s; alarm: %s; claim refused: %s' % (configurations, alarms[0].detail, claim))
finally:
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
    core.stop()
'''


def test_a_witness_restarted_without_its_record_grants_nothing_once_a_site_has_seen_a_newer_epoch():
    code, output = run_tagged(SCRIPT, timeout=150, home_prefix='aft_witness_behind_home_')
    assert code == 0, output[-3000:]
    assert 'claim refused' in output, output[-3000:]
