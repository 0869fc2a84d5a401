"""Power-off of a site's whole process tree, with real processes (no ROS); what a roslaunch log says of its end."""
import os
import signal
import subprocess
import sys
import time

import psutil

from aft_ftm.sites import (PF_EXITING, Site, launch_failure, pid_gone, power_off, process_tree, silence_trees,
                           thread_silent, wait_stopped)

# A parent whose children start their own sessions, as roslaunch's nodes do.
TREE = ('import os, subprocess, sys, time\n'
        'for _ in range(3):\n'
        '    subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], start_new_session=True)\n'
        'print("ready", flush=True)\n'
        'time.sleep(60)\n')


def start_tree():
    site = Site('t', [sys.executable, '-c', TREE])
    site.proc = subprocess.Popen(site.argv, stdout=subprocess.PIPE, start_new_session=True)
    assert site.proc.stdout.readline().strip() == b'ready'
    return site


def test_power_off_kills_every_process_of_the_site_even_in_other_sessions():
    site = start_tree()
    try:
        pids = [p.pid for p in process_tree(site.pid)]
        assert len(pids) == 4
        assert len({os.getsid(p) for p in pids}) == 4
        assert site.power_off() == 4
        time.sleep(0.05)
        assert not [p for p in pids if not pid_gone(p)]
    finally:
        site.stop(grace=1)


def test_stop_never_raises_and_leaves_nothing():
    site = start_tree()
    pids = [p.pid for p in process_tree(site.pid)]
    site.stop(grace=1)
    site.stop(grace=1)
    assert not [p for p in pids if not pid_gone(p)]


# Eight threads that each append to a file as fast as they can: any instruction they run shows.
BUSY = ('import sys, threading\n'
        'out = open(sys.argv[1], "a", buffering=1)\n'
        'def work(k):\n'
        '    while True:\n'
        '        out.write("%d\\n" % k)\n'
        'for k in range(8):\n'
        '    threading.Thread(target=work, args=(k,), daemon=True).start()\n'
        'print("ready", flush=True)\n'
        'threading.Event().wait()\n')


# A launcher that respawns its busy child (as roslaunch's respawn="true" does) the moment it dies.
RESPAWNING = ('import subprocess, sys, time\n'
              'child = [sys.executable, "-c", sys.argv[1], sys.argv[2]]\n'
              'proc = subprocess.Popen(child, stdout=subprocess.PIPE, start_new_session=True)\n'
              'print(proc.stdout.readline().decode().strip(), proc.pid, flush=True)\n'
              'while True:\n'
              '    proc.wait()\n'
              '    proc = subprocess.Popen(child, start_new_session=True)\n')


def test_silence_trees_silences_a_site_at_once_and_its_launcher_respawns_nothing(tmp_path):
    """What Recovery's fail-silence does before a promotion: the launcher stopped first, its known node
    next, then the rest of its tree; every thread seen stopped, then all killed. From its return not one
    more line is written, a SIGCONT (a freeze injector ending its freeze) resumes nothing, and the
    launcher, stopped before its node was killed, never respawns it."""
    for round_ in range(3):
        out = tmp_path / ('busy%d' % round_)
        launcher = subprocess.Popen([sys.executable, '-c', RESPAWNING, BUSY, str(out)], stdout=subprocess.PIPE,
                                    start_new_session=True)
        try:
            ready, child = launcher.stdout.readline().split()
            assert ready == b'ready'
            time.sleep(0.02)
            procs = silence_trees([psutil.Process(launcher.pid)], [psutil.Process(int(child))])
            assert sorted(p.pid for p in procs) == sorted([launcher.pid, int(child)])
            size = os.path.getsize(out)
            for proc in procs:
                try:
                    proc.resume()
                except psutil.NoSuchProcess:
                    pass
            launcher.wait(5)
            time.sleep(0.1)
            assert pid_gone(int(child))
            assert os.path.getsize(out) == size, 'a thread ran, or the node was respawned, after silence_trees ' \
                                                 'returned (round %d)' % round_
        finally:
            launcher.kill()
            launcher.wait()
            for proc in psutil.process_iter(['cmdline']):
                if str(out) in (proc.info['cmdline'] or []):
                    proc.kill()


def test_a_thread_is_silent_stopped_dead_or_exiting_whatever_its_name():
    stat = '42 (a) b (c)) %s 1 42 42 0 -1 %d 0 0'
    assert not thread_silent(stat % ('R', 0x400040))
    assert not thread_silent(stat % ('S', 0x400040))
    assert thread_silent(stat % ('S', 0x400040 | PF_EXITING))   # in do_exit: never back to user space
    for state in 'TtZX':
        assert thread_silent(stat % (state, 0x400040))


def test_power_off_of_a_missing_process_is_a_no_op():
    proc = subprocess.Popen([sys.executable, '-c', 'pass'])
    proc.wait()
    assert power_off(proc.pid) == 0


ROSLAUNCH_REQUIRED_DIED = """process[slave/tr/protocol-1]: started with pid [6816]
process[slave/tr/before-2]: started with pid [6857]
[WARN] [1795434903.627303]: wait_for_service(/slave/bank_server/get_state): failed to contact, will keep trying
[ERROR] [1795434933.118673]: /slave/tr/protocol: Before/After not connected within 30.0 s (ports ['to_before'])
[FATAL] [1795434933.120193]: /slave/tr/protocol: set-up failed, exiting
[ERROR] [1795434933.792961]: /slave/tr/before: the server state manager (/slave/bank_server/get_state) is not available
================================================================================REQUIRED process [slave/tr/protocol-1] has died!
process has died [pid 6816, exit code 1, cmd /x/protocol __name:=protocol].
log file: /x/slave-tr-protocol-1*.log
Initiating shutdown!
[slave/tr/before-2] killing on exit
"""


def test_launch_failure_names_the_node_that_died_its_exit_code_and_the_last_errors():
    why = launch_failure(ROSLAUNCH_REQUIRED_DIED, errors=1)
    assert why == ('/slave/tr/protocol died (exit code 1); last error: /slave/tr/before: the server state '
                   'manager (/slave/bank_server/get_state) is not available')


def test_launch_failure_of_a_killed_node_and_of_a_launch_that_says_nothing():
    killed = '[master/before_pbr-1] process has died [pid 12, exit code -9, cmd /x/before].\n'
    assert launch_failure(killed) == '/master/before_pbr died (exit code -9)'
    assert launch_failure('process[a-1]: started with pid [1]\n') == ''


# A roslaunch whose node dies in its set-up while the launch itself keeps running (the node is not required).
LAUNCH_NODE_DIES = ('import sys, time\n'
                    'print("process[site/tr/after-6]: started with pid [1]", flush=True)\n'
                    'time.sleep(float(sys.argv[1]))\n'
                    'print("[ERROR] [1.0]: /site/tr/after: ports [\'out\'] not connected within 30.0 s", flush=True)\n'
                    'print("[site/tr/after-6] process has died [pid 1, exit code 1, cmd after].", flush=True)\n'
                    'time.sleep(60)\n')


def test_a_site_whose_node_died_while_its_launch_runs_on_is_a_failure_named_with_the_node(tmp_path):
    log = str(tmp_path / 'site.log')
    with open(log, 'w') as f:   # an earlier start's output in the same log is not this start's failure
        f.write('[old/node-1] process has died [pid 9, exit code 1, cmd x].\n')
    site = Site('site', [sys.executable, '-c', LAUNCH_NODE_DIES, '0.3'], log_path=log).start()
    try:
        assert site.failure() is None
        deadline = time.monotonic() + 10
        while site.failure() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        why = site.failure()
        assert site.alive()
        assert why.startswith('site site: /site/tr/after died (exit code 1)'), why
        assert 'not connected within 30.0 s' in why and '/old/node' not in why
        # A node retired on purpose (an adaptation killed it, by SIGKILL when SIGINT was not enough)
        # is no failure of its site; any other node's death still is.
        assert site.failure(ignore={'/site/tr/after'}) is None
        assert site.failure(ignore={'/site/tr/before'}) == why
    finally:
        site.stop(grace=1)
    assert site.failure() == 'site site exited (code %s)' % site.proc.returncode
    assert Site('never', ['true']).failure() is None


def _sigkill_sent_or_dead(pid):
    """Whether pid can run no more of its own code: gone, a zombie, exiting, or SIGKILL pending."""
    try:
        with open('/proc/%d/status' % pid) as f:
            fields = dict(line.split(':', 1) for line in f if ':' in line)
    except OSError:
        return True
    pending = int(fields['ShdPnd'], 16) | int(fields['SigPnd'], 16)
    return fields['State'].split()[0] in ('Z', 'X') or bool(pending & (1 << (9 - 1))) or pid_gone(pid)


def test_a_stop_undone_by_someone_elses_sigcont_is_sent_again(tmp_path):
    """Fencing stops a whole site before anything else; a SIGCONT from anyone else (a frozen host resumed,
    a parent, a debugger) undid it, and the wait for the stop ran out its whole timeout while the
    process ran (tjp_sim's board_freeze: the board ran on 5 s, its backup promoted only then)."""
    proc = subprocess.Popen([sys.executable, '-c', 'import time\nwhile True: time.sleep(0.001)'])
    try:
        p = psutil.Process(proc.pid)
        p.send_signal(signal.SIGSTOP)
        p.send_signal(signal.SIGCONT)   # the resume, right after the fencing's stop
        assert wait_stopped([p], 2.0) == [], 'the process resumed by someone else was never stopped again'
    finally:
        proc.kill()
        proc.wait()


def test_a_site_is_killed_before_its_power_off_lets_anyone_take_over():
    """on_stopped() (the watchdog promotes the backup there) runs once every process of the site was sent
    SIGKILL: a stopped process resumed meanwhile by anyone would otherwise run beside the new primary."""
    site = start_tree()
    seen = {}
    try:
        pids = [p.pid for p in process_tree(site.pid)]
        killed = power_off(site.pid, on_stopped=lambda: seen.update({pid: _sigkill_sent_or_dead(pid) for pid in pids}))
        assert killed == 4 and sorted(seen) == sorted(pids)
        assert all(seen.values()), 'processes not yet sent SIGKILL when the take-over ran: %s' % seen
    finally:
        site.stop(grace=1)
