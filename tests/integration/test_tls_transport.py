"""Mutual TLS on TCPROS (issue 16, aft_ftm.tls and aft_ftm.ros.tls_transport), for real: a witness
started with AFT_TLS_DIR answers only peers whose certificate and policy allow it. Checked from
processes of each kind: a node of an allowed party (served, and its subscription gets the latched
configuration); a plain rospy process with no certificate (what ROS 1 lets any attacker run: its
call fails and its subscription gets nothing); a process with a valid certificate of a party the
policy does not let call the witness (refused) but lets subscribe (served); and a publisher with a
certificate whose party may not publish a topic the checker subscribes to (the checker refuses it).
Every refusal is logged by the node that refused it. Runs in a process of its own with a master of
its own; every process it starts carries the test's AFT_TEST_TAG and is killed at the end."""
from leftovers import run_tagged

SCRIPT = r'''
import os, subprocess, sys, tempfile, textwrap, time
import rospy
from aft_msgs.msg import Configuration
from aft_msgs.srv import Witness
from std_msgs.msg import String
from aft_ftm import tls
from aft_ftm.ros.graph import start_master
from aft_ftm.ros.params import secure_from_environment
from aft_ftm.sites import wait_until

log_dir = tempfile.mkdtemp(prefix='aft_tls_')
keys = os.path.join(log_dir, 'tls')
tls.make_authority(keys)
for party in ('witness', 'master', 'client'):
    tls.issue(keys, party)
policy = os.path.join(log_dir, 'policy.yaml')
with open(policy, 'w') as f:
    f.write(textwrap.dedent("""
        plaintext: [/rosout]
        parties:
          witness: {publish: ['/witness/*', /rosout], serve: ['/witness/*']}
          master: {subscribe: ['/witness/*', '/aft_test/*'], call: ['/witness/*'], publish: [/rosout]}
          client: {subscribe: [/witness/configuration], publish: [/rosout]}
        """))

def env(party=None):
    e = dict(os.environ)
    for k in ('AFT_TLS_DIR', 'AFT_TLS_PARTY', 'AFT_TLS_POLICY'):
        e.pop(k, None)
    if party:
        e.update(AFT_TLS_DIR=keys, AFT_TLS_PARTY=party, AFT_TLS_POLICY=policy)
    return e

ATTACK = r"""
import os, sys, time, rospy
from aft_msgs.msg import Configuration
from aft_msgs.srv import Witness
from std_msgs.msg import String
from aft_ftm.ros.params import secure_from_environment
secure_from_environment()
rospy.init_node(sys.argv[1])
seen = []
rospy.Subscriber('/witness/configuration', Configuration, seen.append)
try:
    rospy.ServiceProxy('/witness/request', Witness)(op=0, site='attacker')
    print('CALL served')
except Exception as e:
    print('CALL refused: %s' % str(e)[:200])
deadline = time.monotonic() + 4.0
while not seen and time.monotonic() < deadline:
    time.sleep(0.05)
print('SUBSCRIPTION %s' % ('served' if seen else 'nothing'))
pub = rospy.Publisher('/aft_test/commands', String, queue_size=10, latch=True)
pub.publish(String(data='forged by ' + sys.argv[1]))
time.sleep(float(sys.argv[2]))
sys.stdout.flush()
"""
attack = os.path.join(log_dir, 'attack.py')
with open(attack, 'w') as f:
    f.write(ATTACK)

core = start_master(log_dir)
procs = []
try:
    procs.append(subprocess.Popen(['rosrun', 'aft_ftm', 'witness', '__name:=witness', '_initial_primary:=master'],
                                  stdout=open(log_dir + '/witness.out', 'w'), stderr=subprocess.STDOUT, env=env('witness')))
    os.environ.update(env('master'))
    secure_from_environment()
    rospy.init_node('checker')
    rospy.wait_for_service('/witness/request', 30)
    answer = rospy.ServiceProxy('/witness/request', Witness)(op=0, site='checker')
    configurations = []
    rospy.Subscriber('/witness/configuration', Configuration, configurations.append)
    if not wait_until(lambda: configurations, 8.0, 0.05):
        sys.exit('the allowed party got no configuration')
    print('ALLOWED served: epoch %d, configuration heard' % answer.epoch)
    commands = []
    rospy.Subscriber('/aft_test/commands', String, commands.append)
    results = {}
    for name, party in (('plain_attacker', None), ('client_attacker', 'client')):
        done = subprocess.run([sys.executable, attack, name, '3.0'], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              env=env(party), timeout=60, universal_newlines=True)
        results[name] = done.stdout
        print('%s: %s' % (name, ' | '.join(l for l in done.stdout.splitlines() if l.startswith(('CALL', 'SUBSCRIPTION')))))
    if commands:
        sys.exit('a forged command reached the checker: %s' % commands)
    print('FORGED commands refused')
    out = open(log_dir + '/witness.out').read()
    print('WITNESS refusals: %d' % out.count('tls connection_refused'))
finally:
    for p in procs:
        p.terminate()
        p.wait(10)
    core.stop()
'''


def test_only_certified_parties_the_policy_allows_reach_a_tls_node():
    code, output = run_tagged(SCRIPT, timeout=180, home_prefix='aft_tls_home_')
    assert code == 0, output[-4000:]
    assert 'ALLOWED served' in output, output[-4000:]
    lines = dict(line.split(': ', 1) for line in output.splitlines() if line.startswith(('plain_attacker', 'client_attacker')))
    assert 'CALL refused' in lines['plain_attacker'] and 'SUBSCRIPTION nothing' in lines['plain_attacker'], lines
    assert 'CALL refused' in lines['client_attacker'] and 'SUBSCRIPTION served' in lines['client_attacker'], lines
    assert 'FORGED commands refused' in output
    refusals = [line for line in output.splitlines() if line.startswith('WITNESS refusals')]
    assert refusals and int(refusals[0].split(': ')[1]) >= 2, output[-3000:]
