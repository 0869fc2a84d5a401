"""Mutual TLS on TCPROS (issue 16, aft_ftm.tls and aft_ftm.ros.tls_transport), for real: a witness
started with AFT_TLS_DIR answers only peers whose certificate and policy allow it. Checked from
processes of each kind: a node of an allowed party (served, and its subscription gets the latched
configuration); a plain rospy process with no certificate (what ROS 1 lets any attacker run: its
call fails and its subscription gets nothing); a process with a valid certificate of a party the
policy does not let call the witness (refused) but lets subscribe (served); and a publisher with a
certificate whose party may not publish a topic the checker subscribes to (the checker refuses it).
Every refusal is logged by the node that refused it. Then, on the running graph: a party's
certificate revoked (the CA's list re-signed) has its live connection cut and its reconnections
and new calls refused; a certificate that expires has its live connection cut. Runs in a process of its own with a master of
its own; 20 connections stalled in their handshake (half after a ClientHello's first bytes) hold up
no allowed call and are closed by the node. A party's key is rotated twice: with its listener running,
and with it frozen (SIGSTOP) through the rotation and past its keeper's 5 s hurry. Every process it
starts carries the test's AFT_TEST_TAG and is killed at the end."""
from leftovers import run_tagged
from reporting import report

SCRIPT = r'''
import datetime, os, socket, subprocess, sys, tempfile, textwrap, threading, time
import rosgraph, rospy
from rospy.core import parse_rosrpc_uri
from aft_msgs.msg import Alarm, Configuration
from aft_msgs.srv import Witness
from std_msgs.msg import String
from aft_ftm import tls
from aft_ftm.ros.graph import start_master
from aft_ftm.ros.params import secure_from_environment
from aft_ftm.sites import wait_until

log_dir = tempfile.mkdtemp(prefix='aft_tls_')
keys = os.path.join(log_dir, 'tls')
tls.make_authority(keys)
for party in ('witness', 'master', 'client', 'rotating'):
    tls.issue(keys, party)
policy = os.path.join(log_dir, 'policy.yaml')
with open(policy, 'w') as f:
    f.write(textwrap.dedent("""
        plaintext: [/rosout]
        parties:
          witness: {publish: ['/witness/*', /rosout, /aft/alarms], serve: ['/witness/*']}
          master: {subscribe: ['/witness/*', '/aft_test/*', /aft/alarms], call: ['/witness/*'],
                   publish: [/rosout, /aft_test/ticks, /aft/alarms]}
          client: {subscribe: [/witness/configuration, /aft_test/ticks], publish: [/rosout, /aft/alarms]}
          brief: {subscribe: [/aft_test/ticks], publish: [/rosout, /aft/alarms]}
          rotating: {subscribe: [/aft_test/ticks], publish: [/rosout, /aft/alarms]}
        """))

def env(party=None, directory=keys):
    e = dict(os.environ)
    for k in ('AFT_TLS_DIR', 'AFT_TLS_PARTY', 'AFT_TLS_POLICY'):
        e.pop(k, None)
    if party:
        e.update(AFT_TLS_DIR=directory, AFT_TLS_PARTY=party, AFT_TLS_POLICY=policy)
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
LISTEN = r"""
import sys, time, rospy
from std_msgs.msg import String
from aft_ftm.ros.params import secure_from_environment
secure_from_environment()
if sys.argv[3:] == ['keep']:   # the subscription keeper, as run_node gives every AFT node: a cut subscription
    from aft_ftm.ros.subscription_keeper import keep_subscriptions   # is made again (rospy gives it up)
    keep_subscriptions(period=0.5)
rospy.init_node(sys.argv[1])
heard = []
rospy.Subscriber('/aft_test/ticks', String, lambda m: heard.append(time.time()))
time.sleep(float(sys.argv[2]))
gap = max([b - a for a, b in zip(heard, heard[1:])] or [0.0])
print('HEARD %d, the last at %.3f, the longest gap %.3f s' % (len(heard), heard[-1] if heard else 0, gap), flush=True)
print('TIMES %s' % ' '.join('%.3f' % t for t in heard), flush=True)
"""
listen = os.path.join(log_dir, 'listen.py')
with open(listen, 'w') as f:
    f.write(LISTEN)
# An application's own rospy client, unmodified (no AFT import): rosrun aft_ftm with_tls gives it TLS
UNMODIFIED = r"""
import sys, rospy
from aft_msgs.srv import Witness
rospy.init_node(sys.argv[1])
try:
    print('UNMODIFIED served: epoch %d' % rospy.ServiceProxy('/witness/request', Witness)(op=0, site='app').epoch)
except Exception as e:
    print('UNMODIFIED refused: %s' % str(e)[:200])
"""
unmodified = os.path.join(log_dir, 'unmodified.py')
with open(unmodified, 'w') as f:
    f.write(UNMODIFIED)

core = start_master(log_dir)
procs = []
try:
    procs.append(subprocess.Popen(['rosrun', 'aft_ftm', 'witness', '__name:=witness', '_initial_primary:=master'],
                                  stdout=open(log_dir + '/witness.out', 'w'), stderr=subprocess.STDOUT, env=env('witness')))
    os.environ.update(env('master'))
    secure_from_environment()
    rospy.init_node('checker')
    alarms = []
    rospy.Subscriber('/aft/alarms', Alarm, alarms.append)
    rospy.wait_for_service('/witness/request', 30)
    answer = rospy.ServiceProxy('/witness/request', Witness)(op=0, site='checker')
    configurations = []
    rospy.Subscriber('/witness/configuration', Configuration, configurations.append)
    if not wait_until(lambda: configurations, 8.0, 0.05):
        sys.exit('the allowed party got no configuration')
    print('ALLOWED served: epoch %d, configuration heard' % answer.epoch)
    # -- a hang: connections that stall in the handshake (TLS begun and left, or silent) hold nothing up
    host, port = parse_rosrpc_uri(rosgraph.Master('/checker').lookupService('/witness/request'))
    stalled = []
    for i in range(20):
        s = socket.create_connection((host, port), timeout=5.0)
        if i % 2:
            s.sendall(bytes([0x16, 0x03, 0x01, 0x02, 0x00, 0x01]))   # a ClientHello's first bytes, no more
        stalled.append(s)
    begun = time.monotonic()
    rospy.ServiceProxy('/witness/request', Witness)(op=0, site='checker')
    print('STALLED 20 handshakes: an allowed call served in %.3f s' % (time.monotonic() - begun))
    def closed(s):
        s.settimeout(0.01)
        try:
            return s.recv(1) == b''
        except socket.timeout:
            return False
        except OSError:
            return True
    shut = set()
    wait_until(lambda: shut.update(i for i, s in enumerate(stalled) if i not in shut and closed(s)) or len(shut) == 20,
               15.0, 0.05)
    print('STALLED closed by the node: %d of 20, %.1f s after' % (len(shut), time.monotonic() - begun))
    for s in stalled:
        s.close()
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
    for name, argv, party in (('with_tls', ['rosrun', 'aft_ftm', 'with_tls', unmodified, 'app_tls'], 'master'),
                              ('in_clear', [sys.executable, unmodified, 'app_clear'], 'master'),
                              ('no_tls_dir', ['rosrun', 'aft_ftm', 'with_tls', unmodified, 'app_none'], None)):
        done = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env(party), timeout=60,
                              universal_newlines=True)
        said = [l for l in done.stdout.splitlines() if l.startswith(('UNMODIFIED', 'with_tls:'))]
        print('APP %s exit %d: %s' % (name, done.returncode, ' | '.join(said)))
    out = open(log_dir + '/witness.out').read()
    print('WITNESS refusals: %d' % out.count('tls connection_refused'))

    # -- on the running graph: a revoked certificate, an expiring one
    ticks = rospy.Publisher('/aft_test/ticks', String, queue_size=10)
    done = threading.Event()
    def tick():
        while not done.wait(0.01):
            ticks.publish(String(data='tick'))
    threading.Thread(target=tick, daemon=True).start()
    tls.issue(keys, 'brief', lifetime=datetime.timedelta(seconds=12))
    from cryptography import x509
    with open(os.path.join(keys, 'brief.tls.crt'), 'rb') as f:
        brief_end = x509.load_pem_x509_certificate(f.read()).not_valid_after.replace(
            tzinfo=datetime.timezone.utc).timestamp()
    listeners = [subprocess.Popen([sys.executable, listen, name, '22'], stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, env=env(party), universal_newlines=True)
                 for name, party in (('listener', 'client'), ('brief_listener', 'brief'))]
    procs.extend(listeners)
    peers = lambda: set(c.endpoint_id for c in ticks.impl.connections)
    if not wait_until(lambda: peers() >= {'/listener', '/brief_listener'}, 10.0, 0.01):
        sys.exit('the listeners did not connect before the brief certificate ended: %s' % peers())
    stolen = tls.export_party(keys, 'client', os.path.join(log_dir, 'stolen'))   # kept by an attacker: no list
    revoked_at = time.time()
    tls.revoke(keys, ['client'])
    if not wait_until(lambda: '/listener' not in peers(), 5.0, 0.002):
        sys.exit('the revoked party is still connected 5 s after the revocation')
    print('REVOKED cut after %.3f s' % (time.time() - revoked_at))
    again = subprocess.run([sys.executable, attack, 'revoked_attacker', '0.5'], stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, env=env('client', stolen), timeout=60, universal_newlines=True).stdout
    print('revoked_attacker: %s' % ' | '.join(l for l in again.splitlines() if l.startswith(('CALL', 'SUBSCRIPTION'))))
    if not wait_until(lambda: '/brief_listener' not in peers(), max(0.0, brief_end - time.time()) + 5.0, 0.002):
        sys.exit('the expired certificate is still connected 5 s after its end')
    print('EXPIRED cut %.3f s after the certificate ended' % (time.time() - brief_end))
    back = wait_until(lambda: peers() & {'/listener', '/brief_listener'}, 2.0, 0.01)
    print('RECONNECTED %s' % (sorted(back) or 'none'))
    # -- a rotation without a restart: the listener's key and certificate issued again in its directory,
    # then the replaced certificate revoked: its connection is cut, and it comes back with the new one
    from aft_ftm.ros import tls_transport
    def rotating_serials():
        with tls_transport._LOCK:
            return set(serial for party, serial, _ in tls_transport._LIVE.values() if party == 'rotating')
    rotating = subprocess.Popen([sys.executable, listen, 'rotating_listener', '30', 'keep'], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, env=env('rotating'), universal_newlines=True)
    procs.append(rotating)
    if not wait_until(lambda: '/rotating_listener' in peers() and rotating_serials(), 10.0, 0.01):
        sys.exit('the rotating listener did not connect')
    old_serials = rotating_serials()
    tls.issue(keys, 'rotating')
    new_serial = tls.serial_of(keys, 'rotating')
    revoked_at = time.time()
    tls.revoke(keys, ['rotating'], replaced_only=True)
    back = wait_until(lambda: rotating_serials() == {new_serial}, 15.0, 0.005)
    print('ROTATION old %s cut, %s' % ('not' if rotating_serials() & old_serials else 'all',
                                       'back with the new certificate %.3f s after the revocation'
                                       % (time.time() - revoked_at) if back else 'not back with the new one in 15 s'))
    # -- the same, with the listener frozen (SIGSTOP) through the rotation and for longer than the keeper's
    # hurry (5 s): resumed, it sees its new pair and the list that revokes the pair before in one round
    time.sleep(1.0)
    import signal
    frozen_at = time.time()
    os.kill(rotating.pid, signal.SIGSTOP)
    before = rotating_serials()
    tls.issue(keys, 'rotating')
    second = tls.serial_of(keys, 'rotating')
    tls.revoke(keys, ['rotating'], replaced_only=True)
    cut = wait_until(lambda: not (rotating_serials() & before), 5.0, 0.005)
    time.sleep(max(0.0, frozen_at + 6.5 - time.time()))
    resumed_at = time.time()
    os.kill(rotating.pid, signal.SIGCONT)
    back = wait_until(lambda: rotating_serials() == {second}, 15.0, 0.005)
    print('FROZEN ROTATION old %s while frozen, %s' % ('cut' if cut else 'not cut',
          'back with the new certificate %.3f s after SIGCONT' % (time.time() - resumed_at) if back
          else 'not back with the new one 15 s after SIGCONT'))
    out, _ = rotating.communicate(timeout=60)
    heard = [float(t) for l in out.splitlines() if l.startswith('TIMES ') for t in l.split()[1:]]
    around = [t for t in heard if revoked_at - 0.5 <= t <= frozen_at]
    print('rotating_listener %s, revoked at %.3f, the longest gap around the first rotation %.3f s, '
          'the last tick %.3f s after SIGCONT' % ([l for l in out.splitlines() if l.startswith('HEARD')], revoked_at,
          max([b - a for a, b in zip(around, around[1:])] or [99.0]), (heard[-1] if heard else 0) - resumed_at))
    done.set()
    for p in listeners:
        out, _ = p.communicate(timeout=40)
        print('%s %s' % (p.args[2], [l for l in out.splitlines() if l.startswith('HEARD')]))
    out = open(log_dir + '/witness.out').read()
    print('WITNESS revoked refusals: %d' % out.count('is revoked'))
    wait_until(lambda: ('/checker', 'certificate_expired') in set((a.source, a.kind) for a in alarms), 3.0)
    print('ALARMS %s' % ' '.join(sorted(set('%s:%s' % (a.source, a.kind) for a in alarms if a.mechanism == 'tls'))))
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
    # an unmodified rospy client: served under with_tls, refused in clear; with_tls without a TLS directory
    # refuses to start it in clear
    apps = dict(line[4:].split(' exit ', 1) for line in output.splitlines() if line.startswith('APP '))
    assert apps['with_tls'].startswith('0: UNMODIFIED served: epoch'), apps
    assert apps['in_clear'].startswith('0: UNMODIFIED refused'), apps
    assert apps['no_tls_dir'].startswith('2: with_tls: AFT_TLS_DIR is not set'), apps
    refusals = [line for line in output.splitlines() if line.startswith('WITNESS refusals')]
    assert refusals and int(refusals[0].split(': ')[1]) >= 2, output[-3000:]
    served = [line for line in output.splitlines() if line.startswith('STALLED 20')][0]
    assert float(served.split()[-2]) < 2.0, served     # not held up behind 20 stalled handshakes (5 s each)
    assert 'STALLED closed by the node: 20 of 20' in output, output[-3000:]
    # revocation and expiry on the running graph
    assert 'REVOKED cut after' in output and 'EXPIRED cut' in output, output[-4000:]
    assert 'RECONNECTED none' in output, output[-3000:]
    revoked = [line for line in output.splitlines() if line.startswith('revoked_attacker')][0]
    assert 'CALL refused' in revoked and 'SUBSCRIPTION nothing' in revoked, revoked
    heard = [line for line in output.splitlines() if line.startswith(('listener', 'brief_listener'))]
    assert len(heard) == 2 and all('HEARD 0' not in line for line in heard), heard   # each was served before
    heard = [line for line in output.splitlines() if line.startswith('ALARMS')][0].split()
    for alarm in ('/witness:connection_refused', '/checker:certificate_revoked', '/checker:certificate_expired',
                  '/brief_listener:own_certificate_ending'):   # (the last: said by the node itself, in advance)
        assert alarm in heard, (alarm, heard)     # raised on /aft/alarms, not only logged
    assert not [a for a in heard if a.endswith(':own_certificate_ending') and 'brief' not in a], heard   # a month
    # a rotation without a restart: cut, back with the new certificate, and ticks heard after it
    rotation = [line for line in output.splitlines() if line.startswith('ROTATION')]
    assert rotation and rotation[0].startswith('ROTATION old all cut, back with the new certificate'), output[-3000:]
    listened = [line for line in output.splitlines() if line.startswith('rotating_listener')]
    assert listened and 'HEARD' in listened[0], output[-3000:]
    listened = listened[0]
    last, revoked_at = float(listened.split('the last at ')[1].split(',')[0]), float(listened.split('revoked at ')[1].split(',')[0])
    assert last > revoked_at + 1.0, listened
    # back at once, not after the subscription keeper's grace: the listener saw its old certificate
    # revoked, and its keeper made the cut subscription again at its next look (5.4 s before: the grace)
    from aft_ftm.subscriptions import GRACE
    gap = float(listened.split('the longest gap around the first rotation ')[1].split(' s')[0])
    assert gap < GRACE / 2, listened
    # frozen through a second rotation, past the hurry window: cut while frozen, back with the new
    # certificate at once once resumed, and ticks heard after it
    frozen = [line for line in output.splitlines() if line.startswith('FROZEN ROTATION')]
    assert frozen and frozen[0].startswith('FROZEN ROTATION old cut while frozen, back with the new certificate'), \
        output[-3000:]
    assert float(frozen[0].split('certificate ')[1].split(' s')[0]) < GRACE / 2, frozen[0]
    assert float(listened.split('the last tick ')[1].split(' s')[0]) > 3.0, listened
    report('TLS rotation under 100 messages/s: %s; the listener\'s longest gap around it %.3f s; %s'
           % (rotation[0][len('ROTATION '):], gap, frozen[0]))
    revoked_refusals = [line for line in output.splitlines() if line.startswith('WITNESS revoked refusals')]
    assert int(revoked_refusals[0].split(': ')[1]) >= 1, output[-3000:]
