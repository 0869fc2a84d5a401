"""Alarms bound to their sender (issue 16), for real: an alarm changes the Monitoring Engine's fault
model F, and so chooses the next adaptation; under TLS, only the node an alarm names may raise it.

A Monitoring Engine (`rosrun aft_ftm monitor`) runs under a TLS policy whose parties are bound to
node names (`nodes`). An insider, a certified party allowed to publish `/aft/alarms`, tries:
  * its node calling itself by a name of another party (`/site/sec_gate`): the Monitoring Engine
    refuses the connection (`connection_refused`, naming the name), F unchanged;
  * its node under its own name sending an alarm in the name of `/site/sec_gate`: refused
    (`forged_alarm`), F unchanged;
  * the control: the same alarm raised by `/site/sec_gate` itself, of the site's party, is taken
    (F gains the fault it shows).
Then a restart with an older revocation list, or with none, than the one a directory held: the node
refuses to start and names the rollback; with the newest list it starts.
Every process it starts carries the test's AFT_TEST_TAG and is killed at the end.
"""
from leftovers import run_tagged

SCRIPT = r'''
import json, os, shutil, subprocess, sys, tempfile, time
import rospy, yaml
from aft_msgs.msg import Alarm
from std_msgs.msg import String
from aft_ftm import tls
from aft_ftm.ros.graph import start_master
from aft_ftm.ros.params import secure_from_environment
from aft_ftm.sites import wait_until

POLICY = {'plaintext': ['/rosout'], 'parties': {
    'monitor': {'nodes': ['/aft/monitor'], 'publish': ['/aft/*', '/rosout'], 'subscribe': ['*']},
    'site': {'nodes': ['/site/*'], 'publish': ['/aft/alarms', '/rosout']},
    'mallory': {'nodes': ['/mallory*'], 'publish': ['/aft/alarms', '/rosout']},   # an insider
    'checker': {'nodes': ['/checker'], 'subscribe': ['*'], 'publish': ['/rosout']}}}
log_dir = tempfile.mkdtemp(prefix='aft_tls_alarms_')
keys = os.path.join(log_dir, 'tls')
tls.make_authority(keys)
[tls.issue(keys, party) for party in POLICY['parties']]
policy = os.path.join(log_dir, 'policy.yaml')
with open(policy, 'w') as f:
    yaml.safe_dump(POLICY, f)

def env(party):
    return dict(os.environ, AFT_TLS_DIR=keys, AFT_TLS_PARTY=party, AFT_TLS_POLICY=policy)

RAISE = r"""
import sys, time, rospy
from aft_msgs.msg import Alarm
from aft_ftm.ros.params import secure_from_environment
secure_from_environment()
rospy.init_node('raiser')   # its name and namespace: __name, __ns
source, mechanism, kind, hold = rospy.myargv()[1:]
pub = rospy.Publisher('/aft/alarms', Alarm, queue_size=10, latch=True)
pub.publish(Alarm(source=source, mechanism=mechanism, kind=kind, detail='raised by a test', stamp=rospy.Time.now()))
time.sleep(float(hold))
"""
raiser = os.path.join(log_dir, 'raise.py')
with open(raiser, 'w') as f:
    f.write(RAISE)

def raise_alarm(party, node, source, mechanism, kind, hold=3.0):
    namespace, name = node.rsplit('/', 1)
    out = open(os.path.join(log_dir, '%s.out' % node.strip('/').replace('/', '_')), 'w')
    return subprocess.Popen([sys.executable, raiser, source, mechanism, kind, str(hold), '__ns:=%s' % (namespace or '/'),
                             '__name:=%s' % name], env=env(party), stdout=out, stderr=subprocess.STDOUT)

core = start_master(log_dir)
procs = []
try:
    procs.append(subprocess.Popen(
        ['rosrun', 'aft_ftm', 'monitor', '__name:=monitor', '__ns:=/aft', 'alarms:=/aft/alarms',
         '_running:=pbr+tr', '_lost_after:=600', '_alarms_from:=[/site]'],   # the nodes below are this service's
        stdout=open(log_dir + '/monitor.out', 'w'), stderr=subprocess.STDOUT, env=env('monitor')))
    os.environ.update(env('checker'))
    secure_from_environment()
    rospy.init_node('checker')
    alarms, models = [], []
    rospy.Subscriber('/aft/alarms', Alarm, alarms.append)
    rospy.Subscriber('/aft/monitor/model', String, lambda m: models.append(json.loads(m.data)))
    if not wait_until(lambda: models, 30.0, 0.05):
        sys.exit('the monitor published no model')

    def faults():
        return sorted(models[-1]['model']['faults'])
    print('START F %s' % faults())

    def alarms_of(source, kind):
        return [a for a in alarms if a.source == source and a.kind == kind]

    # 1. an insider's node naming itself as a node of the site
    procs.append(raise_alarm('mallory', '/site/sec_gate', '/site/sec_gate', 'sec', 'bad_signature'))
    refused = wait_until(lambda: [a for a in alarms_of('/aft/monitor', 'connection_refused')
                                  if 'party mallory may not run a node named /site/sec_gate' in a.detail], 15.0, 0.05)
    procs[-1].wait(30)
    time.sleep(0.5)   # ticks of the monitor since the publisher left: F is what it would show
    print('IMPERSONATION %s; F %s' % ('refused' if refused else 'NOT refused', faults()))

    # 2. the insider under its own name, sending an alarm in the site's name
    procs.append(raise_alarm('mallory', '/mallory', '/site/sec_gate', 'sec', 'bad_signature'))
    forged = wait_until(lambda: alarms_of('/aft/monitor', 'forged_alarm'), 15.0, 0.05)
    procs[-1].wait(30)
    time.sleep(0.5)
    print('FORGED %s; F %s; %s' % ('refused' if forged else 'NOT refused', faults(),
                                   forged[0].detail if forged else ''))

    # 3. the control: the site's own node raises an alarm that shows a fault
    procs.append(raise_alarm('site', '/site/tr_before', '/site/tr_before', 'tr', 'no_majority'))
    taken = wait_until(lambda: 'transient_value' in faults(), 15.0, 0.05)
    procs[-1].wait(30)
    print('OWN ALARM %s; F %s' % ('taken' if taken else 'NOT taken', faults()))
    print('REFUSED OWN %d' % len([a for a in alarms if a.kind == 'connection_refused'
                                  and 'party site' in a.detail]))
finally:
    for p in procs:
        if p.poll() is None:
            p.terminate()
            p.wait(10)
    core.stop()

# 4. a restart with an older revocation list than the directory held
START = "from aft_ftm.ros.params import secure_from_environment; secure_from_environment(); print('STARTED')"
def start(party):
    run = subprocess.run([sys.executable, '-c', START], env=env(party), stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, universal_newlines=True, timeout=60)
    return run.returncode, run.stdout.strip().splitlines()[-1] if run.stdout.strip() else ''
tls.revoke(keys, ['mallory'])
first = os.path.join(log_dir, 'crl.1')
shutil.copy(os.path.join(keys, 'ca.tls.crl'), first)
print('LIST 1 %s %s' % start('site'))
tls.revoke(keys, ['mallory'])
second = os.path.join(log_dir, 'crl.2')
shutil.copy(os.path.join(keys, 'ca.tls.crl'), second)
print('LIST 2 %s %s' % start('site'))
shutil.copy(first, os.path.join(keys, 'ca.tls.crl'))
print('BACK TO 1 %s %s' % start('site'))
os.remove(os.path.join(keys, 'ca.tls.crl'))
print('NO LIST %s %s' % start('site'))
shutil.copy(second, os.path.join(keys, 'ca.tls.crl'))
print('LIST 2 AGAIN %s %s' % start('site'))
print('REVOKED PARTY %s %s' % start('mallory'))
'''


def test_only_the_node_an_alarm_names_may_raise_it_and_a_revocation_list_never_rolls_back():
    code, output = run_tagged(SCRIPT, timeout=240, home_prefix='aft_tls_alarms_home_')
    assert code == 0, output[-5000:]
    lines = output.splitlines()

    def line(prefix):
        found = [l for l in lines if l.startswith(prefix)]
        assert found, (prefix, output[-4000:])
        return found[0]
    assert line('START F') == "START F ['crash']", output[-3000:]
    assert line('IMPERSONATION') == "IMPERSONATION refused; F ['crash']", output[-4000:]
    forged = line('FORGED')
    assert forged.startswith("FORGED refused; F ['crash']; "), output[-4000:]
    assert '/site/sec_gate' in forged and '/mallory' in forged, forged
    assert line('OWN ALARM') == "OWN ALARM taken; F ['crash', 'transient_value']", output[-4000:]
    assert line('REFUSED OWN') == 'REFUSED OWN 0', output[-3000:]
    # the revocation list: each newer list starts; an older one, or none, is a rollback and starts nothing
    assert line('LIST 1') == 'LIST 1 0 STARTED'
    assert line('LIST 2') == 'LIST 2 0 STARTED'
    back = line('BACK TO 1')
    assert not back.startswith('BACK TO 1 0') and 'rollback' in back and 'number 1' in back, back
    none = line('NO LIST')
    assert not none.startswith('NO LIST 0') and 'rollback' in none and 'missing' in none, none
    assert line('LIST 2 AGAIN') == 'LIST 2 AGAIN 0 STARTED'
    revoked = line('REVOKED PARTY')
    assert not revoked.startswith('REVOKED PARTY 0') and 'revoked' in revoked, revoked
