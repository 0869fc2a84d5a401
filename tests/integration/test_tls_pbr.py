"""The PBR bank with mutual TLS on every TCPROS connection (issue 16): an attacker on the graph,
without a certificate or with one the policy trusts with nothing, tries the control plane of a
running pair under client load: a forged checkpoint, a forged failure report, a heartbeat that
announces the primary's fail-stop, a role change of the backup's Protocol, a state written into the
primary's server, a shutdown of the backup's Protocol over its XML-RPC API (``rosnode kill``); then
a sweep of the whole graph as the master lists it: a default message of the right type on every
topic somebody subscribes to, a call of every service; last, the backup Protocol's name registered at
the ROS master at the attacker's own address, then at the backup's After's (the master's API is open:
it drops the real node's registrations and asks it to shut down). Each is refused (the refusing node
raises ``tls connection_refused``, ``tls shutdown_refused`` or ``tls name_taken``: a node whose name
was taken goes on and registers again, unless the new one proves the name over TLS), none changes anything (no failover, the
servers' states equal the clients' model); then the primary site loses power and the backup takes
over under TLS with every call answered exactly once. The same runs against LFR, and against issue
16's deployment, SEC with PBR+TR; the bank's own client, unmodified, under ``rosrun aft_ftm with_tls``
as party app is served, as a party the policy does not allow on /account it is refused.
Runs in a process of its own with a master of its own; every process it starts carries the test's
AFT_TEST_TAG and is killed at the end."""
import re

import pytest

from leftovers import run_tagged

SCRIPT = r'''
import os, subprocess, sys, tempfile, time
import rospkg, rospy
from aft_msgs.msg import Alarm
from aft_msgs.srv import Account, GetState
from aft_examples.bank import Account as Model, operation
from aft_examples.ros.deployment import PbrDeployment, witness_status
from aft_examples.ros.bank_nodes import account_caller
from aft_ftm.ros.graph import start_master
from aft_ftm.ros.params import secure_from_environment
from aft_ftm.sites import wait_until

ATTACK = r"""
import sys, time, rospy
from aft_msgs.msg import Checkpoint, Failure, Heartbeat, Reply
from aft_msgs.srv import SetRole, SetState
from aft_ftm.ros.params import secure_from_environment
secure_from_environment()
rospy.init_node(sys.argv[1])
pubs = [rospy.Publisher('/ftm/checkpoints/master', Checkpoint, queue_size=10, latch=True),
        rospy.Publisher('/slave/failures', Failure, queue_size=10, latch=True),
        rospy.Publisher('/ftm/heartbeat/master', Heartbeat, queue_size=10, latch=True)]
for seq in range(1, 40):
    pubs[0].publish(Checkpoint(seq=10 ** 6 + seq, first_seq=1, sender='/master/after', epoch=2, state=b'{"balance": 1}'))
    pubs[1].publish(Failure(site='master', reason='forged', detected=rospy.Time.now()))
    pubs[2].publish(Heartbeat(site='master', seq=10 ** 6 + seq, stopping='forged', stamp=rospy.Time.now()))
    time.sleep(0.05)
for name, kind, request in (('/slave/protocol/set_role', SetRole, dict(role=2, last_seq=0, epoch=3)),
                            ('/master/bank_server/set_state', SetState, dict(state=b'{"balance": 1000000}'))):
    try:
        rospy.ServiceProxy(name, kind)(**request)
        print('CALL %s served' % name)
    except Exception as e:
        print('CALL %s refused: %s' % (name, str(e)[:160]))
subscribers = sum(p.get_num_connections() for p in pubs)
print('SUBSCRIBERS %d' % subscribers)
# rosnode kill of the backup's Protocol: its XML-RPC API is open to anyone on the network
import rosgraph, xmlrpc.client
def answers(uri):
    try:
        return xmlrpc.client.ServerProxy(uri).getPid(rospy.get_name())[0] == 1
    except Exception:
        return False
try:
    uri = rosgraph.Master(rospy.get_name()).lookupNode('/slave/protocol')
    try:
        code, said, _ = xmlrpc.client.ServerProxy(uri).shutdown(rospy.get_name(), 'user request')
    except Exception as e:   # a node obeying at once may close the connection before its answer
        code, said = None, str(e)
    gone = time.monotonic() + 3.0
    while answers(uri) and time.monotonic() < gone:
        time.sleep(0.05)
    print('XMLRPC shutdown of /slave/protocol %s (%s)' % ('refused' if answers(uri) else 'obeyed', said[:100]))
except Exception as e:
    print('XMLRPC shutdown of /slave/protocol failed: %s' % str(e)[:100])
if len(sys.argv) > 2:
    # the sweep (aft_ftm.ros.intruder): a default message of the right type on every topic somebody
    # subscribes to, and a call with a default request of every service, read from the master
    from aft_ftm import tls
    from aft_ftm.ros.intruder import sweep
    got = sweep(tls.Permissions.load(sys.argv[2]))
    print('SWEEP topics %d connected %s services refused %d unknown %d served %s'
          % (len(got['topics']), got['connected'], got['refused'], len(got['unknown']), got['served']))
# Name theft (last: the master's eviction of the thief reaches this node): /slave/protocol registered at
# the master at this node's own URI, then at /slave/after's. The master drops the real node's
# registrations and asks it to shut down; under TLS it refuses (the thief proves no right to the name)
# and registers again. Printed: whether the name came back to the same process within 5 s.
def lookup(name):
    try:
        return rosgraph.Master(rospy.get_name()).lookupNode(name)
    except Exception:
        return None
real = lookup('/slave/protocol')
try:
    real_pid = xmlrpc.client.ServerProxy(real).getPid(rospy.get_name())[2]
except Exception:   # (the control: the XML-RPC shutdown above stopped it)
    real_pid = None
for where, uri in (('own', rospy.core.get_node_uri()), ('after', lookup('/slave/after'))):
    rosgraph.Master('/slave/protocol').registerPublisher('/stolen_%s' % where, 'std_msgs/String', uri)
    started = time.monotonic()
    while lookup('/slave/protocol') != real and time.monotonic() - started < 5.0:
        time.sleep(0.02)
    back = lookup('/slave/protocol') == real
    try:
        same = xmlrpc.client.ServerProxy(real).getPid(rospy.get_name())[2] == real_pid
    except Exception:
        same = False
    print('NAME /slave/protocol taken at %s: %s, %s' % (
        where, 'back in %.2f s' % (time.monotonic() - started) if back else 'not back in 5 s',
        'same process' if same else 'the node is gone'))
"""

# The bank's application client, unmodified (no AFT import), run under rosrun aft_ftm with_tls: an
# operation the bank refuses, so that a served call changes nothing and says it reached the bank
APP = r"""
import sys, rospy
from aft_msgs.srv import Account
rospy.init_node(sys.argv[1])
try:
    print('ACCOUNT answered %r' % (rospy.ServiceProxy('/account', Account)(op='inspect', amount=0),))
except rospy.ServiceException as e:
    print('ACCOUNT error %s' % str(e)[:300].replace('\n', ' '))
"""

log_dir = tempfile.mkdtemp(prefix='aft_tls_pbr_')
attack = os.path.join(log_dir, 'attack.py')
with open(attack, 'w') as f:
    f.write(ATTACK)
app = os.path.join(log_dir, 'app_client.py')
with open(app, 'w') as f:
    f.write(APP)
with_tls = sys.argv[1] == 'tls'
mechanism = sys.argv[2] if len(sys.argv) > 2 else 'pbr'
variant = dict(sec=True, inner='tr') if sys.argv[3:] == ['sec_tr'] else {}   # issue 16's SEC + PBR + TR
policy = os.path.join(rospkg.RosPack().get_path('aft_examples'), 'config', 'tls_policy.yaml')
core = start_master(log_dir)
# Detection at 500 ms, not the default 30 ms: this test is about what the control plane refuses. Once in
# CI (LFR, not reproduced since) the pair failed over during the attacks; every attack that reached a
# node was refused, and the one way found there that needs no refused connection to get through is a
# false suspicion under the sweep's burst of TLS handshakes on 2 cores (detection under load is
# measured by the detection benchmark and the hosts tests, at 30 ms).
deployment = PbrDeployment(log_dir, mechanism=mechanism, tls_policy=policy if with_tls else None, timeout=0.5,
                           **variant)
try:
    if with_tls:
        os.environ.update(deployment.tls_env('operator'))
        secure_from_environment()
    rospy.init_node('operator')
    alarms = []
    rospy.Subscriber('/aft/alarms', Alarm, alarms.append)
    print('started in %.1f s' % deployment.start())
    call = account_caller(rospy.ServiceProxy('/account', Account, persistent=True))
    model, wrong, done = Model(), 0, 0

    def calls(n):
        global wrong, done
        for _ in range(n):
            op, amount = operation(done)
            if tuple(call(op, amount)) != tuple(model.apply(op, amount)):
                wrong += 1
            done += 1
    calls(50)
    for name, party in (('plain_attacker', None), ('client2_attacker', 'client2')):
        env = deployment.tls_env(party) if party and with_tls else dict(
            (k, v) for k, v in os.environ.items() if not k.startswith('AFT_TLS_'))
        # (stderr apart: rospy's log lines on stderr, written while a buffered stdout is flushed, once
        # cut a NAME line in two in CI)
        attacker = subprocess.run([sys.executable, attack, name] + ([policy] if with_tls else []), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  env=env, timeout=90, universal_newlines=True)
        print('%s: %s' % (name, ' | '.join(l for l in attacker.stdout.splitlines() if l.startswith(('CALL', 'SUBSCRIBERS', 'XMLRPC', 'SWEEP', 'NAME')))))
        if with_tls:   # (the control's pair may be left with nobody serving)
            calls(25)
    if with_tls:   # /account under TLS: the app party's client is served, a party it does not allow is not
        for name, party in (('bank_client_app', 'app'), ('client2_app', 'client2')):
            ran = subprocess.run(['rosrun', 'aft_ftm', 'with_tls', app, name], stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, env=deployment.tls_env(party), timeout=90,
                                 universal_newlines=True)
            print('APP %s exit %d: %s' % (name, ran.returncode, ' | '.join(
                l for l in ran.stdout.splitlines() if l.startswith('ACCOUNT')) or ran.stdout[-300:]))
    status = witness_status()
    print('AFTER ATTACKS epoch %d primary %s backup %s' % (status.epoch, status.primary, status.backup))
    if with_tls and (status.epoch, status.primary, status.backup) != (2, 'master', 'slave'):
        # What made the pair change (once seen in CI, not reproduced since): every alarm but TLS refusals,
        # and what the sites' logs say of failures, so that the failure names its cause.
        for a in alarms:
            if a.mechanism != 'tls':
                print('UNEXPECTED alarm %s %s %s: %s' % (a.source, a.mechanism, a.kind, a.detail[:300]))
        for site in ('master', 'slave'):
            with open(os.path.join(log_dir, site + '.log'), errors='replace') as f:
                for text in f:
                    if any(w in text for w in ('FAIL-STOP', 'declared', 'promot', 'deposed', 'suspect', 'alone')):
                        print('UNEXPECTED %s.log: %s' % (site, text.rstrip()[:300]))
        sys.exit('the attacks changed the pair: epoch %d primary %s backup %s (see UNEXPECTED above)' % (
            status.epoch, status.primary, status.backup))
    if not with_tls:
        sys.exit(0)   # the control: what the same attacks do to a pair without TLS (printed above)
    states = [rospy.ServiceProxy('/%s/bank_server/get_state' % s, GetState)().state for s in ('master', 'slave')]
    expected = Model(*model.snapshot())
    for site, state in zip(('master', 'slave'), states):
        got = Model()
        got.set_state(state)
        print('STATE %s %s' % (site, 'equal' if got.snapshot() == expected.snapshot() else 'DIFFERS %r %r' % (got.snapshot(), expected.snapshot())))
    refusals = [a for a in alarms if a.mechanism == 'tls' and a.kind == 'connection_refused']
    print('REFUSALS %d by %s' % (len(refusals), sorted(set(a.source for a in refusals))))
    shutdowns = [a for a in alarms if a.mechanism == 'tls' and a.kind == 'shutdown_refused']
    print('SHUTDOWN REFUSALS %d by %s' % (len(shutdowns), sorted(set(a.source for a in shutdowns))))
    taken = [a for a in alarms if a.mechanism == 'tls' and a.kind == 'name_taken']
    print('NAMES TAKEN %d by %s' % (len(taken), sorted(set(a.source for a in taken))))
    own = [a.detail for a in refusals if any('party %s may not' % p in a.detail
                                             for p in ('master', 'slave', 'client', 'app', 'witness', 'operator'))]
    print('OWN REFUSALS %d %s' % (len(own), own[:3]))   # the deployment's own parties, refused by its policy
    deployment.sites['master'].power_off()
    started = time.monotonic()
    calls(50)
    got = Model()
    got.set_state(rospy.ServiceProxy('/slave/bank_server/get_state', GetState)().state)
    print('FAILOVER calls %d wrong %d slave %s (50 calls in %.2f s after the power loss)' % (
        done, wrong, 'equal' if got.snapshot() == model.snapshot() else 'DIFFERS', time.monotonic() - started))
finally:
    deployment.teardown()
    core.stop()
'''


@pytest.mark.family('control_experiments', 1)
def test_without_tls_the_same_attacker_changes_roles_and_state():
    """The control: the attacks are real. On the default deployment (no TLS) the plain attacker's calls
    are served and its forgeries reach the replicas: the pair is no longer what it was."""
    code, output = run_tagged(SCRIPT, args=('open',), timeout=300, home_prefix='aft_tls_pbr_home_')
    assert code == 0, output[-5000:]
    attacked = [l for l in output.splitlines() if l.startswith('plain_attacker')]
    assert attacked and 'served' in attacked[0] and 'SUBSCRIBERS 0' not in attacked[0], output[-3000:]
    assert 'XMLRPC shutdown of /slave/protocol obeyed' in attacked[0], attacked[0]
    after = [l for l in output.splitlines() if l.startswith('AFTER ATTACKS')]
    assert after and after[0] != 'AFTER ATTACKS epoch 2 primary master backup slave', after


@pytest.mark.family('tls_pbr', 1)
def test_the_control_plane_refuses_every_forgery_and_the_failover_holds_under_tls():
    check_under_tls('pbr')


@pytest.mark.family('tls_pbr', 1)
def test_lfr_under_tls_refuses_every_forgery_and_fails_over():
    """The same attacks and sweep against Leader-Follower Replication (its own topics: the leader's
    notifications, the followers' acknowledgements), under the same policy."""
    check_under_tls('lfr')


@pytest.mark.family('tls_pbr', 1)
def test_sec_pbr_tr_under_tls_refuses_every_forgery_and_fails_over():
    """Issue 16's deployment: SEC (requests and replies sealed per client, the CA) with PBR+TR, under
    mutual TLS: the same attacks and sweep refused, nothing of the deployment's own refused, the
    failover exactly once."""
    check_under_tls('pbr', 'sec_tr')


def check_under_tls(mechanism, variant=''):
    code, output = run_tagged(SCRIPT, args=('tls', mechanism) + ((variant,) if variant else ()), timeout=300,
                              home_prefix='aft_tls_pbr_home_')
    assert code == 0, output[-5000:]
    lines = output.splitlines()

    def line(prefix):
        found = [l for l in lines if l.startswith(prefix)]
        assert found, (prefix, output[-5000:])
        return found[-1]
    for attacker in ('plain_attacker', 'client2_attacker'):
        text = line(attacker)
        assert text.count('CALL ') == 2 and text.count(' refused: ') == 2 and ' served' not in text[:text.index('SWEEP')], text
        assert 'SUBSCRIBERS 0' in text and 'XMLRPC shutdown of /slave/protocol refused' in text, text
        swept = text[text.index('SWEEP'):].split(' | ')[0]
        sweep = swept.split()
        topics, services_refused, unknown = int(sweep[2]), int(sweep[7]), int(sweep[9])
        assert topics >= 15 and swept.endswith(' connected [] services refused %d unknown %d served []'
                                                 % (services_refused, unknown)), text
        assert services_refused >= 30 and unknown <= 2, text
        for where in ('own', 'after'):   # the name taken at the master comes back to the same process
            assert re.search(r'NAME /slave/protocol taken at %s: back in [0-9.]+ s, same process' % where, text), text
    # the application's client (party app, under with_tls) reaches the bank (its own error for an unknown
    # operation); a certified party the policy does not allow on /account does not
    assert 'ACCOUNT error' in line('APP bank_client_app') and "unknown operation 'inspect'" in line('APP bank_client_app')
    assert 'ACCOUNT error' in line('APP client2_app') and 'unknown operation' not in line('APP client2_app')
    assert 'may not call /account' in line('APP client2_app'), line('APP client2_app')
    assert line('AFTER ATTACKS') == 'AFTER ATTACKS epoch 2 primary master backup slave'
    assert line('STATE master') == 'STATE master equal' and line('STATE slave') == 'STATE slave equal'
    assert not line('REFUSALS').startswith('REFUSALS 0 '), line('REFUSALS')
    assert line('OWN REFUSALS').startswith('OWN REFUSALS 0 '), line('OWN REFUSALS')
    assert line('SHUTDOWN REFUSALS').endswith(" by ['/slave/protocol']"), line('SHUTDOWN REFUSALS')
    assert line('NAMES TAKEN').endswith(" by ['/slave/protocol']"), line('NAMES TAKEN')
    failover = line('FAILOVER')
    assert 'wrong 0 slave equal' in failover and failover.startswith('FAILOVER calls 150 '), failover
