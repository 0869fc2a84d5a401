"""Adaptation and re-join of the PBR bank under mutual TLS (issue 16): the control plane's changes
of mechanism authenticated, not only its failover.

A TLS bank (the demo's policy) with adaptable sites, under client load:
  * ``rosrun aft_ftm adapt compose`` run as a party the policy does not let suspend or rebind (the
    operator, who drives the demo, and client2, certified and trusted with nothing): rejected in its
    dry run, naming the refusal, nothing changed (no node launched, the pair as it was);
  * run as ``engine`` in the paper's order and interrupted (SIGINT) at a step drawn from the seed
    (kill, launch, wait_launched, rebind), under load: it rolls back as the engine, every call
    exactly once, the graph as before with each node (the Proceeds started again too) its site's
    party, nothing it launched left;
  * run as the party ``engine``: PBR becomes PBR+TR on both sites while the client goes on, every
    call exactly once; each node the engine launched speaks as the party of the site it joined (its
    process's AFT_TLS_PARTY), and nothing of the deployment's own is refused by the policy;
  * the primary site loses power: the backup's TR nodes, launched by the engine, serve the failover;
  * ``rosrun aft_ftm rejoin master --launch ...`` under TLS: refused without ``--launch-tls-dir``
    (the site would run as the operator) or with a party the policy does not let run the site's
    nodes, nothing launched; with the site's directory the site comes back as party master and
    re-joins, and both servers' states equal the client's model.
The seed (AFT_SEED replays) draws how many calls come before the adaptation and the power loss.
Runs in a process of its own with a master of its own; every process it starts carries the test's
AFT_TEST_TAG and is killed at the end."""
from leftovers import run_seeded

SCRIPT = r'''
import os, random, shlex, signal, subprocess, sys, tempfile, threading, time
import psutil, rosgraph, rospkg, rospy, xmlrpc.client
from aft_msgs.msg import Alarm
from aft_msgs.srv import Account, GetState
from aft_examples.bank import Account as Model, ReplyChecker
from aft_examples.ros.bank_nodes import account_caller, drive, drive_through_fault
from aft_examples.ros.deployment import PbrDeployment, witness_status
from aft_ftm.ros.graph import roslaunch, start_master
from aft_ftm.ros.params import secure_from_environment
from aft_ftm.sites import terminate_tree, wait_until

seed = int(sys.argv[1])
rng = random.Random(seed)
print('seed %d' % seed)
log_dir = tempfile.mkdtemp(prefix='aft_tls_adapt_')
policy = os.path.join(rospkg.RosPack().get_path('aft_examples'), 'config', 'tls_policy.yaml')
core = start_master(log_dir)
d = PbrDeployment(log_dir, tls_policy=policy, timeout=0.5, adaptable=True)
rejoined = []


def nodes():
    """node -> (pid, its TLS party), for every node the master knows (getPid over its API)."""
    master = rosgraph.Master('/operator')
    found = {}
    for name in sorted(set(n for table in master.getSystemState() for _, ns in table for n in ns)):
        try:
            pid = xmlrpc.client.ServerProxy(master.lookupNode(name)).getPid('/operator')[2]
            found[name] = (pid, psutil.Process(pid).environ().get('AFT_TLS_PARTY'))
        except Exception as e:   # a node gone meanwhile
            found[name] = (None, 'unreadable: %s' % e)
    return found


def adapt(party, script='compose'):
    ran = subprocess.run(['rosrun', 'aft_ftm', 'adapt', script], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         env=d.tls_env(party), timeout=180, universal_newlines=True)
    return ran.returncode, ran.stdout


def interrupted(step, delay):
    """adapt compose in the paper's order as the engine, SIGINT delay s after it says step: (exit, output)."""
    proc = subprocess.Popen(['rosrun', 'aft_ftm', 'adapt', 'compose', '--mode', 'paper'], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=d.tls_env('engine'),
                            universal_newlines=True, start_new_session=True)
    limit = threading.Timer(180.0, proc.kill)   # (a hung command fails the test, it does not hang it)
    limit.start()
    lines = []
    try:
        for line in proc.stdout:   # ends when the command does
            lines.append(line)
            if line.startswith('step %s:' % step) or (' step %s:' % step) in line:
                time.sleep(delay)
                proc.send_signal(signal.SIGINT)
                break
        lines.append(proc.communicate(timeout=170)[0])
    finally:
        limit.cancel()
    return proc.returncode, ''.join(lines)


def rejoin(*options):
    ran = subprocess.run(['rosrun', 'aft_ftm', 'rejoin', 'master'] + list(options), stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, env=d.tls_env('operator'), timeout=120, universal_newlines=True)
    return ran.returncode, ran.stdout


try:
    os.environ.update(d.tls_env('operator'))
    secure_from_environment()
    rospy.init_node('operator')
    alarms = []
    rospy.Subscriber('/aft/alarms', Alarm, alarms.append)
    print('started in %.1f s' % d.start())
    call = account_caller(rospy.ServiceProxy('/account', Account, persistent=True))
    checker = ReplyChecker()
    sent = rng.randint(5, 30)
    drive(call, sent, checker)
    before = nodes()

    # Parties the policy does not let suspend or rebind: rejected in the dry run, nothing changed.
    for party in ('operator', 'client2'):
        code, output = adapt(party)
        refused = 'refused by the TLS policy: party %s may not ' % party in output
        print('ADAPT AS %s exit %d %s: %s' % (party, code, 'refused' if refused else 'NOT REFUSED',
                                            output.strip().splitlines()[-1][:300] if output.strip() else ''))
        drive(call, 5, checker, first=sent)
        sent += 5
    unchanged = sorted(set(nodes()) ^ set(before))
    print('NODES CHANGED BY REFUSED ADAPTATIONS %s' % unchanged)

    # As the engine, interrupted at a drawn step of the paper's order, under load: rolled back.
    # (rebind is the last step before the resumes: interrupted 0.2 s into it, a light machine had the
    # adaptation done and exited 0 before the signal, nothing to roll back; session 48's first CI)
    step = rng.choice(['kill', 'launch', 'wait_launched', 'rebind'])
    delay = 0.0 if step == 'rebind' else rng.choice([0.0, 0.05, 0.2])
    stopped = {}

    def stop_it():
        stopped['code'], stopped['output'] = interrupted(step, delay)
        return 0, time.time()
    count = rng.randint(40, 80)
    drive_through_fault(call, count, checker, rng.randint(1, 20), stop_it, rng, first=sent)
    sent += count
    print('INTERRUPTED at %s +%.2f s exit %d: %s' % (step, delay, stopped['code'], ' | '.join(
        l for l in stopped['output'].splitlines() if 'interrupted' in l or 'Traceback' in l)[:400]))
    settled = wait_until(lambda: set(nodes()) == set(before), 20.0, 0.2)   # its launches stop within their grace
    now = nodes()
    print('NODES AFTER THE ROLLBACK %s' % ('as before' if settled else sorted(set(now) ^ set(before))))
    print('ROLLBACK PARTIES WRONG %s' % {n: p for n, (_, p) in now.items()
                                         if n.startswith(('/master/', '/slave/')) and p != n.split('/')[1]})
    print('SUMMARY interrupted %s' % checker.summary())

    # As the engine, under load: the adaptation lands anywhere in the calls.
    outcome = {}

    def adaptation():
        outcome['code'], outcome['output'] = adapt('engine')
        return 0, time.time()
    count = rng.randint(60, 120)
    records, _ = drive_through_fault(call, count, checker, rng.randint(1, 20), adaptation, rng, first=sent)
    sent += count
    print('ADAPT AS engine exit %d: %s' % (outcome['code'], ' | '.join(
        l for l in outcome['output'].splitlines() if 'done' in l or 'FAIL' in l or 'rejected' in l)[:400]))
    after = nodes()
    launched = {n: after[n] for n in sorted(set(after) - set(before))}
    wrong = {n: p for n, (_, p) in launched.items() if p != n.strip('/').split('/')[0]}
    print('LAUNCHED %d %s WRONG PARTY %s' % (len(launched), sorted(launched), wrong))
    print('SUMMARY adaptation %s' % checker.summary())

    # The primary loses power: the backup's TR (launched by the engine) serves.
    count = rng.randint(30, 60)
    records, _ = drive_through_fault(call, count, checker, rng.randint(1, 20),
                                     lambda: (d.sites['master'].power_off(), time.time()), rng, first=sent)
    sent += count
    status = witness_status()
    print('FAILOVER primary %s epoch %d summary %s' % (status.primary, status.epoch, checker.summary()))

    # rejoin under TLS
    launch_file, args = d.launch_args['master']
    launch = shlex.join(roslaunch('aft_examples', launch_file, **dict(args, role='backup')))
    code, output = rejoin('--launch', launch)
    print('REJOIN without dir exit %d: %s' % (code, output.strip().splitlines()[-1][:300]))
    code, output = rejoin('--launch', launch, '--launch-tls-dir', os.path.join(d.tls_dir, 'client2'))
    print('REJOIN as client2 exit %d: %s' % (code, output.strip().splitlines()[-1][:300]))
    print('MASTER NODES AFTER REFUSED REJOINS %s' % sorted(   # (the dead site's registrations are left)
        n for n, (pid, _) in nodes().items() if n.startswith('/master/') and pid))
    code, output = rejoin('--launch', launch, '--launch-tls-dir', os.path.join(d.tls_dir, 'master'), '--timeout', '90')
    for proc in psutil.process_iter():
        try:
            if 'demo_replica_site.launch' in ' '.join(proc.cmdline()) and proc.environ().get('AFT_TEST_TAG') == \
                    os.environ.get('AFT_TEST_TAG') and 'site:=master' in proc.cmdline():
                rejoined.append(proc.pid)
        except psutil.Error:
            pass
    print('REJOIN as master exit %d: %s' % (code, output.strip().splitlines()[-1][:300]))
    parties = sorted(set(p for n, (pid, p) in nodes().items() if n.startswith('/master/') and pid))
    print('REJOINED PARTIES %s' % parties)
    drive(call, 20, checker, first=sent)
    sent += 20
    states = []
    for site in ('master', 'slave'):
        got = Model()
        got.set_state(rospy.ServiceProxy('/%s/bank_server/get_state' % site, GetState)().state)
        states.append(got.snapshot())
    print('STATES equal to the model %s' % (states == [checker.model.snapshot()] * 2))
    print('SUMMARY end %s sent %d' % (checker.summary(), sent))
    own = [a.detail for a in alarms if a.mechanism == 'tls' and any(
        'party %s may not' % p in a.detail for p in ('master', 'slave', 'client', 'app', 'witness', 'engine'))]
    print('OWN REFUSALS %d %s' % (len(own), own[:3]))
finally:
    for pid in rejoined:
        terminate_tree(pid, grace=2.0)
    d.teardown()
    core.stop()

    def ours():   # what this test started, still running (this process apart)
        found = []
        for proc in psutil.process_iter():
            try:
                if proc.pid != os.getpid() and proc.environ().get('AFT_TEST_TAG') == os.environ.get('AFT_TEST_TAG'):
                    found.append(proc)
            except psutil.Error:
                pass
        return found
    # The nodes the adaptation launched stop with their site: their guard sees its launcher gone within
    # its poll, then gives their roslaunch its grace (5 s). Waited for, bounded: what is left after
    # fails the test (run_tagged).
    wait_until(lambda: not ours(), 20.0, 0.1)
print('ok')
'''


def line(output, prefix):
    found = [l for l in output.splitlines() if l.startswith(prefix)]
    assert found, (prefix, output[-5000:])
    return found[-1]


def test_adaptation_and_rejoin_under_tls_only_as_the_parties_allowed_and_nothing_lost():
    output = run_seeded(SCRIPT, timeout=600, home_prefix='aft_tls_adapt_home_')
    clean = dict(lost=0, duplicated=0, reordered=0, errors=0)
    for party in ('operator', 'client2'):
        refused = line(output, 'ADAPT AS %s ' % party)
        assert refused.startswith('ADAPT AS %s exit 2 refused' % party) and 'nothing changed' in refused, refused
    assert line(output, 'NODES CHANGED BY REFUSED ADAPTATIONS') == 'NODES CHANGED BY REFUSED ADAPTATIONS []'
    interrupted = line(output, 'INTERRUPTED')
    assert ' exit 1: ' in interrupted and 'interrupted (SIGINT): rolled back' in interrupted, interrupted
    assert line(output, 'NODES AFTER THE ROLLBACK') == 'NODES AFTER THE ROLLBACK as before'
    assert line(output, 'ROLLBACK PARTIES WRONG') == 'ROLLBACK PARTIES WRONG {}'
    assert line(output, 'ADAPT AS engine').startswith('ADAPT AS engine exit 0: adaptation compose done')
    launched = line(output, 'LAUNCHED')
    assert launched.startswith('LAUNCHED 8 ') and launched.endswith('WRONG PARTY {}'), launched
    for what in ('interrupted', 'adaptation', 'end'):
        summary = eval(line(output, 'SUMMARY %s' % what).split(' ', 2)[2].split(' sent ')[0])
        assert {k: summary[k] for k in clean} == clean, (what, summary)
    assert line(output, 'FAILOVER primary slave epoch 3')
    assert line(output, 'REJOIN without dir exit 2: ').endswith('nothing started'), line(output, 'REJOIN without')
    assert 'may not run' in line(output, 'REJOIN as client2 exit 2: '), line(output, 'REJOIN as client2')
    assert line(output, 'MASTER NODES AFTER REFUSED REJOINS') == 'MASTER NODES AFTER REFUSED REJOINS []'
    assert line(output, 'REJOIN as master exit 0: ').endswith('after the start'), line(output, 'REJOIN as master')
    assert line(output, 'REJOINED PARTIES') == "REJOINED PARTIES ['master']"
    assert line(output, 'STATES equal') == 'STATES equal to the model True'
    assert line(output, 'OWN REFUSALS').startswith('OWN REFUSALS 0 '), line(output, 'OWN REFUSALS')
