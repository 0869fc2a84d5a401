"""A crash detector being stopped gives its cores back at once (aft_ftm.ros.xmlrpc_shutdown and
CrashDetectorNode._leave_realtime).

The crash detector runs every thread under SCHED_FIFO. Stopped (roslaunch's SIGINT, a site relaunched),
it used to spend its last seconds with rosgraph's XML-RPC thread spinning on its closed socket, still at
real-time priority: beside bench_healing two stopping detectors held both cores for 950 ms of every
second, and every ordinary process of the machine stalled. Here a detector runs with its real-time
priority; after SIGINT, no thread of it is SCHED_FIFO any more and it uses little CPU until it exits.
Runs in a process of its own with a master of its own; every process it starts carries the test's
AFT_TEST_TAG and is killed at the end."""
from leftovers import run_tagged

SCRIPT = r'''
import os, signal, subprocess, sys, tempfile, time
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until
log_dir = tempfile.mkdtemp(prefix='aft_stopping_')
core = start_master(log_dir)
TICK = os.sysconf('SC_CLK_TCK')


def threads(pid):
    """{tid: (policy, cpu ticks)} of pid's threads."""
    found = {}
    for tid in os.listdir('/proc/%d/task' % pid):
        try:
            with open('/proc/%d/task/%s/stat' % (pid, tid)) as f:
                rest = f.read().rsplit(')', 1)[1].split()
            found[int(tid)] = (int(rest[38]), int(rest[11]) + int(rest[12]))
        except (OSError, IndexError):
            pass
    return found


def cpu(pid):
    with open('/proc/%d/stat' % pid) as f:
        rest = f.read().rsplit(')', 1)[1].split()
    return (int(rest[11]) + int(rest[12])) / float(TICK)


proc = subprocess.Popen(['rosrun', 'aft_ftm', 'crash_detector', '__name:=detector', '_site:=here', '_peer:=there',
                         '_site_pid:=0', '_realtime_priority:=10', '_timeout:=0.5'],
                        stdout=open(log_dir + '/detector.out', 'w'), stderr=subprocess.STDOUT)
try:
    pid = None
    def python_pid():   # rosrun execs the node: the same pid, once it runs Python
        return proc.pid if 'crash_detector' in open('/proc/%d/cmdline' % proc.pid).read() else None
    if not wait_until(lambda: python_pid() and sum(1 for p, _ in threads(proc.pid).values() if p == 1) >= 3,
                      30.0, 0.1):
        sys.exit('the detector did not put its threads under SCHED_FIFO: %s' % open(log_dir + '/detector.out').read()[-2000:])
    time.sleep(1.0)   # a steady state: heartbeats, its rospy threads
    fifo = sum(1 for p, _ in threads(proc.pid).values() if p == 1)
    before = cpu(proc.pid)
    stopped_at = time.monotonic()
    proc.send_signal(signal.SIGINT)
    still_fifo_after = None
    last_cpu = before
    while proc.poll() is None and time.monotonic() - stopped_at < 30.0:
        try:
            now = threads(proc.pid)
            last_cpu = cpu(proc.pid)
        except OSError:
            break
        if time.monotonic() - stopped_at > 0.5 and any(p == 1 for p, _ in now.values()):
            still_fifo_after = sorted(t for t, (p, _) in now.items() if p == 1)
        time.sleep(0.02)
    took = time.monotonic() - stopped_at
    proc.wait(10)
    used = last_cpu - before
    print('detector: %d SCHED_FIFO threads; after SIGINT exited in %.2f s using %.2f s of CPU' % (fifo, took, used))
    if still_fifo_after:
        sys.exit('threads %s still SCHED_FIFO 0.5 s after SIGINT' % still_fifo_after)
    if used > 0.25 * took + 0.2:
        sys.exit('the stopping detector used %.2f s of CPU in %.2f s (a thread spinning?)' % (used, took))
finally:
    if proc.poll() is None:
        proc.kill()
    core.stop()
'''


def test_a_stopping_crash_detector_leaves_real_time_at_once_and_spins_nothing():
    code, output = run_tagged(SCRIPT, timeout=120, home_prefix='aft_stopping_home_')
    assert code == 0, output[-3000:]
    assert 'exited in' in output, output[-3000:]
