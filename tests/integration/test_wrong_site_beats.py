"""A crash detector takes no other site's heartbeats for its peer's.

Heartbeats of another site on the peer's topic (a remapping gone wrong, two replica pairs sharing a
topic, or forged without TLS) said nothing of the peer, yet kept it alive: with the peer dead and the
other site beating on, its failure was never declared, and nobody took over. Here a detector watches
peer ``there``; beats of ``there`` come, then only beats of another site (drawn from a seed), at the
same rate. Checked: the detector declares ``there`` failed within its timeout of the last real beat
(plus scheduling), and says once (``wrong_site``) that it ignores the other site's beats. Runs in a
process of its own with a master of its own; every process it starts carries the test's AFT_TEST_TAG
and is killed at the end, pass or fail. AFT_SEED replays a run."""
from leftovers import run_seeded

SCRIPT = r'''
import random, subprocess, sys, tempfile, time
import rospy
from aft_msgs.msg import Alarm, Failure, Heartbeat
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until

seed = int(sys.argv[1])
rng = random.Random(seed)
other = rng.choice(['there2', 'elsewhere', 'THERE', 'there '])
TIMEOUT = 0.2
log_dir = tempfile.mkdtemp(prefix='aft_wrong_site_')
core = start_master(log_dir)
proc = subprocess.Popen(['rosrun', 'aft_ftm', 'crash_detector', '__name:=detector', '_site:=here', '_peer:=there',
                         '_site_pid:=0', '_timeout:=%s' % TIMEOUT, '_period:=0.01', '_realtime_priority:=0'],
                        stdout=open(log_dir + '/detector.out', 'w'), stderr=subprocess.STDOUT)
try:
    rospy.init_node('checker', disable_signals=True)
    failures, alarms = [], []
    rospy.Subscriber('/failures', Failure, lambda m: failures.append((time.monotonic(), m.site, m.reason)))
    rospy.Subscriber('/aft/alarms', Alarm, lambda m: alarms.append((m.source, m.kind, m.detail)))
    beats = rospy.Publisher('/peer_heartbeat', Heartbeat, queue_size=100)
    if not wait_until(lambda: beats.get_num_connections() > 0, 30.0, 0.05):
        sys.exit('the detector never subscribed to /peer_heartbeat: %s' % open(log_dir + '/detector.out').read()[-2000:])
    seq = [0]

    def beat_for(site, seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            seq[0] += 1
            beats.publish(Heartbeat(site=site, host='h', pid=4242, seq=seq[0], stamp=rospy.Time.now()))
            time.sleep(0.01)
    beat_for('there', 1.5)
    if failures:
        sys.exit('seed %d: there was declared failed while it beat: %s' % (seed, failures))
    last_real = time.monotonic()
    beat_for(other, 1.5)
    if not failures:
        sys.exit('seed %d: beats of site %r kept the silent peer there alive (no failure in 1.5 s); alarms %s'
                 % (seed, other, alarms[-4:]))
    at, site, reason = failures[0]
    told = [a for a in alarms if a[0] == '/detector' and a[1] == 'wrong_site']
    print('seed %d: beats of %r ignored; there declared failed %.0f ms after its last beat (%s); wrong_site told %d '
          'time(s)' % (seed, other, (at - last_real) * 1e3, reason, len(told)), flush=True)
    if site != 'there' or at - last_real > TIMEOUT + 0.5:
        sys.exit('seed %d: the failure %r came %.2f s after the last beat' % (seed, (site, reason), at - last_real))
    if len(told) != 1 or repr(other) not in told[0][2]:
        sys.exit('seed %d: wrong_site should be told once, naming %r: %s' % (seed, other, told))
finally:
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
    core.stop()
print('ok')
'''


def test_another_sites_heartbeats_never_keep_the_peer_alive():
    run_seeded(SCRIPT, home_prefix='aft_wrong_site_home_')
