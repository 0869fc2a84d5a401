"""A crash detector's failure report is never lost to a Recovery that is not connected yet.

rospy handles a publisher's inbound connections one at a time: one stalled handshake held a
Recovery's subscription back for 60 s in a CI run, and the failure published meanwhile reached
nobody (the backup never took over). Here the detector declares its peer failed with nobody
subscribed: it must say so on /aft/alarms and send the report as soon as a subscriber connects,
unless the peer was heard again meanwhile (then the report is moot: the peer came back; the detector
says so with peer_back, sends no failure, and, the peer being the incarnation declared failed, watches
it again: peer_watched).
The script runs in a process of its own, with a master of its own; every process it starts carries
the test's AFT_TEST_TAG and is killed at the end."""
import re

from leftovers import run_tagged

SCRIPT = r'''
import os, subprocess, sys, tempfile, time
import rospy
from aft_msgs.msg import Alarm, Failure, Heartbeat
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until
core = start_master(tempfile.mkdtemp(prefix='aft_detector_'))
detector = subprocess.Popen(['rosrun', 'aft_ftm', 'crash_detector', '__name:=detector', '_site:=a', '_peer:=b',
                             '_period:=0.01', '_timeout:=0.05',
                             # a grace verdict before the first beat would make 'heard' and 'stall' moot
                             '_startup_grace:=%s' % ('0' if sys.argv[1] in ('heard', 'stall') else '0.5'),
                             'failures:=/t/failures', 'peer_heartbeat:=/t/peer', 'heartbeat:=/t/mine'])
try:
    rospy.init_node('checker')
    alarms, failures = [], []
    rospy.Subscriber('/aft/alarms', Alarm, alarms.append)
    if sys.argv[1] == 'heard':   # ~peer_status: does the peer's site run? (asked before a joiner is admitted)
        from aft_msgs.srv import PeerStatus
        rospy.wait_for_service('/detector/peer_status', 30)
        status = rospy.ServiceProxy('/detector/peer_status', PeerStatus)
        peer = rospy.Publisher('/t/peer', Heartbeat, queue_size=10)
        seq, seen = [0], []

        def beat(stopping=''):
            seq[0] += 1
            peer.publish(Heartbeat(site='b', host='h', pid=4242, seq=seq[0], stamp=rospy.Time.now(), stopping=stopping))
            time.sleep(0.01)

        def look(what):
            answer = status()
            seen.append((what, answer.heard, answer.state, answer.peer))
        for _ in range(3000):
            beat()
            if seq[0] % 20 == 0 and status().state == 'ALIVE':
                break
        look('beating')
        time.sleep(0.3)
        look('silent')
        for _ in range(30):
            beat()
        look('beating again')
        # As the After asks it (PeerCheck): beating, it is heard; another site is not known; a frozen
        # detector's answer is not known within the 0.5 s (the After then admits, and says so).
        import threading, psutil
        from aft_ftm.ros.peer_check import PeerCheck
        check, asking = PeerCheck('a', '/detector'), threading.Event()
        beating = threading.Thread(target=lambda: [beat() for _ in range(2000) if not asking.is_set()], daemon=True)
        beating.start()
        def ask_until(site, wanted, seconds=10.0):   # a loaded machine may miss a beat or the first connection
            end = time.monotonic() + seconds
            while True:
                answer = check.heard(site)
                if wanted(answer) or time.monotonic() > end:
                    return answer
                time.sleep(0.05)
        try:
            asked = [ask_until('b', lambda a: a[0] is True), ask_until('c', lambda a: 'watches' in a[1])]
            psutil.Process(detector.pid).suspend()

            def stopped(pid):   # SIGSTOP takes a moment to stop every thread: one answered first in CI
                for tid in os.listdir('/proc/%d/task' % pid):
                    with open('/proc/%d/task/%s/stat' % (pid, tid)) as f:
                        if f.read().rsplit(')', 1)[1].split()[0] not in ('T', 't'):
                            return False
                return True
            wait_until(lambda: stopped(detector.pid), 5.0, 0.002)
            try:
                started = time.monotonic()
                asked += [check.heard('b'), round(time.monotonic() - started, 1)]
            finally:
                psutil.Process(detector.pid).resume()
        finally:
            asking.set()
            beating.join()
        print('PeerCheck.heard: %s' % asked)
        if asked[0][0] is not True or asked[1][0] is not None or 'watches' not in asked[1][1] \
                or asked[2][0] is not None or 'did not answer within 0.5 s' not in asked[2][1] or asked[3] > 3.0:
            sys.exit('PeerCheck.heard: %s' % asked)
        for _ in range(30):   # heard again before the fail-stop announcement below
            beat()
        beat('its server died')
        time.sleep(0.1)
        look('stopped')
        print('peer_status: %s' % seen)
        sys.exit(0 if seen == [('beating', True, 'ALIVE', 'b'), ('silent', False, 'FAILED', 'b'),
                               ('beating again', True, 'ALIVE', 'b'), ('stopped', False, 'FAILED', 'b')] else 1)
    if sys.argv[1] == 'stall':   # heard, then its next beat sent 0.3 s late: the peer_back alarm says so
        peer = rospy.Publisher('/t/peer', Heartbeat, queue_size=10)
        seq = 0
        while not any(a.kind == 'peer_back' for a in alarms) and seq < 3000:
            seq += 1
            peer.publish(Heartbeat(site='b', host='h', pid=4242, seq=seq, stamp=rospy.Time.now()))
            time.sleep(0.3 if seq == 300 else 0.01)
        back = [a.detail for a in alarms if a.kind == 'peer_back']
        print('heard again: %s' % back)
        sys.exit(0 if back and 'the sender stalled' in back[0] else 'no stall told: %s' % back)
    if not wait_until(lambda: any(a.kind == 'failure_undelivered' for a in alarms), 30, 0.05):
        sys.exit('no failure_undelivered alarm: %s' % [(a.kind, a.detail) for a in alarms])
    if sys.argv[1] == 'back':   # the peer is heard again before any Recovery connects
        peer = rospy.Publisher('/t/peer', Heartbeat, queue_size=10)
        seq = 0
        while not any(a.kind == 'peer_back' for a in alarms) and seq < 3000:
            seq += 1
            peer.publish(Heartbeat(site='b', host='h', pid=4242, seq=seq, stamp=rospy.Time.now()))
            time.sleep(0.01)
        if not any(a.kind == 'peer_back' for a in alarms):
            sys.exit('the peer heard again raised no peer_back: %s' % [(a.kind, a.detail) for a in alarms])
    recovery = rospy.Subscriber('/t/failures', Failure, failures.append)       # a Recovery connects late
    if sys.argv[1] == 'back':
        # The peer beats on: the report is moot, and the peer, heard again as the incarnation declared
        # failed, is watched again (peer_watched): its real failure later is reported.
        connected = time.monotonic()
        while time.monotonic() < connected + 10 and (recovery.get_num_connections() < 1 or
                                                     time.monotonic() < connected + 1.0):
            seq += 1
            peer.publish(Heartbeat(site='b', host='h', pid=4242, seq=seq, stamp=rospy.Time.now()))
            time.sleep(0.01)
        if recovery.get_num_connections() < 1:
            sys.exit('the late subscriber never connected to the detector')
        # A kept report goes out within a check period (2 ms) of the connection: 1 s is 500 of them.
        if failures:
            sys.exit('a moot failure report was sent: %s' % failures)
        if not any(a.kind == 'peer_watched' for a in alarms):
            sys.exit('the peer heard again is not watched again: %s' % [(a.kind, a.detail) for a in alarms])
        # Then it stops for real: reported once, to the Recovery now connected.
        if not wait_until(lambda: failures, 10, 0.05):
            sys.exit('the real failure of the peer watched again was never reported')
        time.sleep(0.3)
        print('reported after being watched again: %s' % [(f.site, f.pid, f.reason) for f in failures])
        sys.exit(0 if len(failures) == 1 and failures[0].site == 'b' and failures[0].pid == 4242
                 else 'wrong report(s): %s' % failures)
    if not wait_until(lambda: failures, 10, 0.05):
        sys.exit('the failure report never reached the subscriber that connected late')
    print('delivered late: site %s, %s' % (failures[0].site, failures[0].reason))
    sys.exit(0 if failures[0].site == 'b' and len(failures) == 1 else 'wrong report(s): %s' % failures)
finally:
    detector.terminate()
    detector.wait(10)
    core.stop()
'''


def run_script(case):
    """SCRIPT for case ('late', 'back', 'stall' or 'heard'): its exit status and output; every process it started is gone."""
    return run_tagged(SCRIPT, [case], timeout=120, home_prefix='aft_detector_home_')


def test_a_failure_declared_before_recovery_connects_is_sent_once_it_does():
    code, output = run_script('late')
    assert code == 0, output[-3000:]
    assert 'delivered late: site b' in output, output[-3000:]


def test_a_kept_failure_report_is_dropped_once_the_peer_is_heard_again_and_the_peer_watched_again():
    """Without a witness to re-arm it, the detector left the peer FAILED for good: a pair whose detectors
    suspected each other while they started never reported the real failure that came later (session 50)."""
    code, output = run_script('back')
    assert code == 0, output[-3000:]
    assert 'reported after being watched again' in output, output[-3000:]


def test_a_peer_heard_again_after_its_sender_stalled_is_told_as_a_stall():
    """A false suspicion explained: the peer's beat after the verdict was sent late (its sender
    stalled), not delayed on the way; the peer_back alarm says which, from the beats' numbers and stamps."""
    code, output = run_script('stall')
    assert code == 0, output[-3000:]
    sent = re.search(r'was sent ([0-9.]+) ms after the last one heard', output)
    assert sent and float(sent.group(1)) >= 290.0, output[-3000:]   # the 0.3 s the sender slept


def test_a_detector_says_whether_its_peer_site_runs_even_after_declaring_it_failed():
    """What a primary's After asks before it admits a joiner: its beats heard within the timeout (also
    after a verdict: a site back; here no Recovery is connected, so the peer heard again as the same
    incarnation is watched again, ALIVE), and not once it announced its fail-stop (a site stopping,
    whose After may still join)."""
    code, output = run_script('heard')
    assert code == 0, output[-3000:]
