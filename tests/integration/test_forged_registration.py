"""A forged registration at the ROS master never makes fencing or an adaptation kill another process.

The master's XML-RPC API is open: anyone may register a node name with the URI of an XML-RPC server of
its own, whose getPid answers any pid. Recovery learns the pids of its peer's name space that way and
SIGKILLs them at a failover, as root; the Adaptation Engine kills the nodes a script retires the same way.

Here, on a running PBR bank, names are registered under MASTER's name space (/master/forged_*):
- one at a forged XML-RPC server answering the pid of a process drawn from a seed (SLAVE's Protocol, its
  Recovery, its server, SLAVE's roslaunch, the witness, the ROS master, a plain rospy node outside the
  sites, the test's own process, pid 1);
- one at the real XML-RPC URI of SLAVE's Protocol (its getPid answers that real node's pid);
- one at the ROS master's address (spelt another way), and one at the plain rospy node's: after a
  failover, fencing asks what is left of the failed site to shut down, and both would obey.
Then, under client load, MASTER is powered off, or (the other case) its heartbeat is forged: a last
beat announcing MASTER's fail-stop, naming the drawn process as MASTER's launcher on this host. Alone,
it names another incarnation than MASTER's beats: SLAVE's detector refuses it (``stale_announcement``)
and nothing fails over. Sent right after a beat naming that launcher, it is taken; Recovery
kills a failed site's launcher's process tree, so it must be sure the pid is that launcher (a process above
a node of MASTER learned by pid, and not above itself), else it raises ``fence_refused`` and kills the name
space's nodes only. The false failover itself is what a wrong announcement costs (no more). Checked: SLAVE's Recovery raised ``fence_refused`` for
every name before the failover; the failover succeeded and killed MASTER's real nodes by pid; every
process drawn from is still the same process, the ROS master still answers and the plain node still
runs after the clean-up; every call answered exactly once and SLAVE's state equals a failure-free run.
And the Adaptation Engine refuses a script that retires a forged node, naming it, and kills nothing.
Before: SLAVE's Recovery killed whatever pid the forged server named (its own Protocol: nobody served).
Runs in a process of its own with a master of its own; every process it starts carries the test's
AFT_TEST_TAG and is killed at the end, pass or fail."""
import pytest

from leftovers import run_seeded

SCRIPT = r'''
import json, os, random, subprocess, sys, tempfile, threading
from xmlrpc.server import SimpleXMLRPCServer
import psutil, rosgraph, rospy
from aft_msgs.msg import Alarm, Heartbeat
from aft_msgs.srv import Account, GetState
from std_msgs.msg import String
from aft_examples.bank import Account as Model, ReplyChecker, operation
from aft_examples.ros.bank_nodes import account_caller, drive_with_faults
from aft_examples.ros.deployment import PbrDeployment, start_retrying
from aft_ftm.ros.fencing import NotTheNode, node_api, visible_pid
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import this_host, wait_until

seed, FAULT = int(sys.argv[1]), sys.argv[2]
rng = random.Random(seed)
COUNT, LIMIT = 300, 90.0
OFF_AT = rng.randrange(50, 250)
log_dir = tempfile.mkdtemp(prefix='aft_forged_')
core = start_master(log_dir)
deployment = PbrDeployment(log_dir, timeout=0.15, mechanism='pbr')
master = rosgraph.Master('/checker')
outsider = None

def pid_of(node):
    return node_api(master.lookupNode(node), 2.0).getPid('/checker')[2]

def pid_of_master():
    return node_api(rosgraph.get_master_uri(), 2.0).getPid('/checker')[2]

def registered(node):
    try:
        master.lookupNode(node)
        return True
    except Exception:
        return False

def connected_to(node, topic):
    """The callers node's publisher of topic is connected to (its getBusInfo)."""
    try:
        _, _, bus = node_api(master.lookupNode(node), 2.0).getBusInfo('/checker')
    except Exception:
        return []
    return [dest for _, dest, direction, _, name, *rest in bus if direction == 'o' and name == topic]

class Forged(object):
    def __init__(self, pid):
        self.pid = pid
    def getPid(self, caller_id):
        return 1, 'forged', self.pid

try:
    rospy.init_node('checker', disable_signals=True)
    start_retrying(deployment)
    # A plain rospy node outside the sites: it obeys any shutdown request, as rospy does.
    outsider = subprocess.Popen([sys.executable, '-c', 'import rospy; rospy.init_node("outsider"); rospy.spin()'],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    if not wait_until(lambda: registered('/outsider'), 30.0, 0.1):
        sys.exit('the outsider node did not register within 30 s')
    victims = {'slave protocol': pid_of('/slave/protocol'), 'slave recovery': pid_of('/slave/recovery'),
               'slave server': pid_of('/slave/bank_server'), 'slave roslaunch': deployment.sites['slave'].pid,
               'witness': pid_of('/aft/witness'), 'the ROS master': pid_of_master(), 'outsider': outsider.pid,
               'the test itself': os.getpid(), 'pid 1': 1}
    drawn = rng.choice(sorted(victims))
    victim = victims[drawn]
    print('seed %d: forged getPid answers %s (pid %d); %s at reply %d' % (seed, drawn, victim, FAULT, OFF_AT),
          flush=True)
    created = {name: psutil.Process(pid).create_time() for name, pid in victims.items()}
    server = SimpleXMLRPCServer(('127.0.0.1', 0), logRequests=False, allow_none=True)
    server.register_instance(Forged(victim))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    pubs, subs, srvs = master.getSystemState()
    genuine = {n for _, nodes in list(pubs) + list(subs) + list(srvs) for n in nodes if n.startswith('/master/')}
    # Names under MASTER's name space, registered at: the forged server; SLAVE's Protocol; the ROS
    # master (its shutdown stops it); the plain outsider (its shutdown stops it). The ROS master's
    # address is written another way than the master's own URI.
    forged = {'/master/forged_server': 'http://127.0.0.1:%d/' % server.server_address[1],
              '/master/forged_alias': master.lookupNode('/slave/protocol'),
              '/master/forged_master': rosgraph.get_master_uri().replace('127.0.0.1', 'localhost').rstrip('/'),
              '/master/forged_plain': master.lookupNode('/outsider')}
    alarms = []
    rospy.Subscriber('/aft/alarms', Alarm, lambda m: alarms.append((m.source, m.kind, m.detail)))
    events = []
    rospy.Subscriber('/slave/recovery/events', String, lambda m: events.append(json.loads(m.data)))
    # Heard from SLAVE's Recovery before anything is forged: its alarm comes once.
    if not wait_until(lambda: '/checker' in connected_to('/slave/recovery', '/aft/alarms'), 10.0, 0.05):
        sys.exit('seed %d: /slave/recovery\'s alarms never reached the checker' % seed)
    for name, uri in forged.items():
        rosgraph.Master(name).registerPublisher(name + '_topic', 'std_msgs/String', uri)

    def refused():
        return {name for name in forged for source, kind, detail in list(alarms)
                if source == '/slave/recovery' and kind == 'fence_refused' and detail.startswith(name + ' ')}
    if not wait_until(lambda: refused() == set(forged), 30.0, 0.05):
        sys.exit('seed %d: SLAVE\'s Recovery raised fence_refused for %s only (of %s); alarms: %s' % (
            seed, sorted(refused()), sorted(forged), alarms[-6:]))
    # The Adaptation Engine's view: a node to retire whose pid is not its process is never signalled.
    for name, uri in forged.items():
        try:
            visible_pid(uri, '/checker', name)
            sys.exit('seed %d: %s (at %s) was taken for its process' % (seed, name, uri))
        except NotTheNode as e:
            print('  %s: %s' % (name, e), flush=True)
    script = os.path.join(log_dir, 'retire_forged.yaml')
    with open(script, 'w') as f:
        f.write('name: retire_forged\nkind: update\ndescription: retire a forged node\n'
                'suspend: [/master/protocol]\nretire: [/master/forged_server]\n')
    adapt = subprocess.run(['rosrun', 'aft_ftm', 'adapt', script, '--check'], stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, universal_newlines=True, timeout=60)
    if adapt.returncode == 0 or 'nothing is killed on that word' not in adapt.stdout:
        sys.exit('seed %d: the Adaptation Engine did not refuse the forged node to retire (exit %d):\n%s' % (
            seed, adapt.returncode, adapt.stdout[-2000:]))

    account = rospy.ServiceProxy('/account', Account, persistent=True)
    account.wait_for_service(30)
    slave_state = rospy.ServiceProxy('/slave/bank_server/get_state', GetState, persistent=True)
    checker = ReplyChecker()
    fault = deployment.sites['master'].power_off
    if FAULT == 'forged fail-stop':
        # MASTER's last heartbeat forged: it announces MASTER's fail-stop, naming the drawn victim as
        # MASTER's launcher on this host. The failover is real (a false one); the victim's tree is not.
        beats = rospy.Publisher('/ftm/heartbeat/master', Heartbeat, queue_size=10)
        if not wait_until(lambda: any(c.endpoint_id == '/slave/crash_detector' for c in beats.impl.connections),
                          10.0, 0.05):
            sys.exit('seed %d: the forged heartbeats reach no detector' % seed)

        wrong = []

        def stale_told():
            return [d for source, kind, d in list(alarms) if source == '/slave/crash_detector'
                    and kind == 'stale_announcement' and 'from pid %d on ' % victim in d]

        def fault():
            # A last word alone, naming another launcher than MASTER's beats name: taken for a late one
            # of an old incarnation (or forged), it is refused with an alarm and fails nothing over.
            beats.publish(Heartbeat(site='master', host=this_host(), pid=victim, seq=10 ** 6,
                                    stamp=rospy.Time.now(), stopping='forged'))
            # (this runs in drive_with_faults' thread: what is wrong is kept, and said once the failover came)
            if not wait_until(stale_told, 5.0, 0.02):
                wrong.append('a fail-stop announced by pid %d, not MASTER\'s launcher, raised no '
                             'stale_announcement: %s' % (victim, alarms[-6:]))
            elif any('failed_site' in e for e in events):
                wrong.append('a stale fail-stop announcement failed MASTER over: %s' % (events[-2:],))
            # So the forger beats as the victim's incarnation first, then says it stops.
            for seq in range(1, 200):   # until SLAVE's Recovery took over (bounded: 10 s)
                beats.publish(Heartbeat(site='master', host=this_host(), pid=victim, seq=10 ** 6 + 2 * seq,
                                        stamp=rospy.Time.now()))
                beats.publish(Heartbeat(site='master', host=this_host(), pid=victim, seq=10 ** 6 + 2 * seq + 1,
                                        stamp=rospy.Time.now(), stopping='forged'))
                if wait_until(lambda: any('failed_site' in e for e in events), 0.05, 0.01):
                    return
    records, _ = drive_with_faults(account_caller(account), COUNT, checker, [(OFF_AT, fault)], LIMIT)
    if records is None:
        sys.exit('seed %d: not every call answered within %.0f s: %s; events %s' % (
            seed, LIMIT, checker.summary(), events[-2:]))
    # After the failover and its clean-up of MASTER's names (fencing asks what is left to shut down):
    # every process drawn from is still the same process, and the ROS master answers.
    wait_until(lambda: not registered('/master/protocol'), 10.0, 0.1)
    for name, pid in victims.items():
        try:
            same = psutil.Process(pid).create_time() == created[name]
        except psutil.NoSuchProcess:
            same = False
        if not same:
            sys.exit('seed %d: %s (pid %d) was killed' % (seed, name, pid))
    if not registered('/outsider') or pid_of_master() != victims['the ROS master']:
        sys.exit('seed %d: the outsider or the ROS master was shut down by the clean-up' % seed)
    summary = checker.summary()
    if summary != {'correct': COUNT, 'lost': 0, 'duplicated': 0, 'reordered': 0, 'errors': 0}:
        sys.exit('seed %d: not exactly once: %s' % (seed, summary))
    model, expected = Model(), Model()
    model.set_state(slave_state().state)
    for i in range(COUNT):
        expected.apply(*operation(i))
    if model.snapshot() != expected.snapshot():
        sys.exit('seed %d: SLAVE state %s differs from a failure-free run %s' % (seed, model.snapshot(),
                                                                               expected.snapshot()))
    if not wait_until(lambda: any('failed_site' in e for e in events), 10):
        sys.exit('seed %d: no failover record of /slave/recovery: %s' % (seed, events))
    if FAULT == 'forged fail-stop' and wrong:
        sys.exit('seed %d: %s' % (seed, wrong[0]))
    failover = [e for e in events if 'failed_site' in e][-1]
    if not failover['ok']:
        sys.exit('seed %d: the failover failed: %s' % (seed, failover))
    silenced = [s['detail'] for s in failover['steps'] if s['step'] == 'FAIL_SILENCE']
    if not any('(%d nodes learned by pid)' % len(genuine) in d for d in silenced):
        sys.exit('seed %d: fail-silence did not kill the %d nodes of MASTER by pid: %s' % (seed, len(genuine), silenced))
    if FAULT == 'forged fail-stop':
        def why():
            return [d for source, kind, d in list(alarms) if source == '/slave/recovery' and kind == 'fence_refused'
                    and d.startswith('pid %d, named as the launcher of master' % victim)]
        if not any('pid %d, named as the launcher' % victim in d or 'launcher %d also runs this process' % victim in d
                   for d in silenced):
            sys.exit('seed %d: fail-silence did not refuse the tree of pid %d: %s' % (seed, victim, silenced))
        above = victim in [p.pid for p in psutil.Process(pid_of('/slave/recovery')).parents()]
        if not above and not wait_until(why, 5.0, 0.05):
            sys.exit('seed %d: no fence_refused alarm for the forged launcher pid %d: %s' % (seed, victim, alarms[-6:]))
    print('FIGURES ' + json.dumps({'fault': FAULT, 'victim': drawn, 'recovery_ms': round(failover['seconds'] * 1e3, 1),
                                   'fail_silence': silenced}), flush=True)
finally:
    if outsider is not None:
        outsider.kill()
    deployment.teardown()
    core.stop()
print('ok')
'''


@pytest.mark.family('forged_registration', 1)
@pytest.mark.parametrize('fault', ['power off', 'forged fail-stop'])
def test_a_forged_registration_or_heartbeat_never_makes_fencing_or_an_adaptation_kill_another_process(fault):
    run_seeded(SCRIPT, [fault], home_prefix='aft_forged_home_')
