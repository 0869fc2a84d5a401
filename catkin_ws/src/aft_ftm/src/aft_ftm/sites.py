"""Sites: groups of processes that live and die together (our stand-in for a machine).

A site is a roslaunch process and its children. roslaunch puts every node in a session
of its own, so a process group is not enough to find them: the process tree is.
:func:`power_off` freezes the whole tree first (so nothing respawns or reacts), then
kills it, which is as abrupt as a power loss for everything on the site.
"""
import os
import re
import signal
import subprocess
import threading
import time

import psutil


def process_tree(pid):
    """The process pid and all its descendants (empty if pid does not exist)."""
    try:
        root = psutil.Process(pid)
        return [root] + root.children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def _signal_all(procs, sig):
    """Signal every process; one that is gone, or that may not be signalled, does not stop the others."""
    for proc in procs:
        try:
            proc.send_signal(sig)
        except psutil.Error:   # gone (NoSuchProcess), or AccessDenied: its wait says it is still running
            pass


def power_off(pid, timeout=5.0, on_stopped=None, snapshot=None):
    """SIGSTOP then SIGKILL pid and every descendant, as a power loss would end them; returns once
    they are dead. Returns the number of processes killed.

    on_stopped() is called the moment every process is stopped (and sent SIGKILL, so that no one's
    SIGCONT can start it again): that is when the site stops computing, the instant a power loss
    would happen.
    """
    return power_off_trees([pid], timeout, on_stopped, snapshot)


def power_off_trees(pids, timeout=5.0, on_stopped=None, snapshot=None):
    """power_off() of several process trees at the same instant: every process of every tree is
    stopped before any is killed, so none sees another go. Returns the number of processes killed.

    Every thread of every process is seen stopped (or the process gone) before SIGKILL is sent: from
    then on none of them runs another instruction of its own. Then the kernel's tear-down of the
    killed processes (20-160 ms for a site of eight rospy nodes on 2 cores; their sockets are closed
    by then) is waited for. snapshot: the trees' processes as the caller just listed them (one scan
    of /proc fewer). A failover does not wait for the tear-down: see silence_trees."""
    procs = list(snapshot) if snapshot is not None else [proc for pid in pids for proc in process_tree(pid)]
    _signal_all(procs, signal.SIGSTOP)
    # Children forked between the snapshot and the stop are caught by a second look.
    seen = {p.pid for p in procs}
    for proc in [proc for pid in pids for proc in process_tree(pid)]:
        if proc.pid not in seen:
            procs.append(proc)
            _signal_all([proc], signal.SIGSTOP)
    wait_stopped(procs, timeout)
    # Killed before on_stopped() (a promotion) runs: a stopped process resumed by anyone meanwhile ran
    # during the promotion; a killed one never runs another instruction, whoever resumes it.
    _signal_all(procs, signal.SIGKILL)
    if on_stopped is not None:
        on_stopped()
    wait_dead(procs, timeout)
    return len(procs)


def _dead(proc):
    """Gone, or a zombie: it runs no more, whoever reaps it and whenever."""
    try:
        return proc.status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def pid_gone(pid):
    """The process ``pid`` runs no more: gone, or a zombie. One read, so a process that exits
    between two looks (exists, then its status) is not an error."""
    try:
        return _dead(psutil.Process(pid))
    except psutil.NoSuchProcess:
        return True


PF_EXITING = 0x4   # include/linux/sched.h: the thread is in do_exit, never to run user code again


def thread_silent(stat):
    """Whether a thread, from the text of its /proc/PID/task/TID/stat, runs no more instruction of its
    own: stopped, a zombie, dead, or exiting (PF_EXITING in its flags, the 9th field: set as it
    enters do_exit, after which it never returns to user space)."""
    fields = stat.rsplit(')', 1)[1].split()
    return fields[0] in ('T', 't', 'Z', 'X') or bool(int(fields[6]) & PF_EXITING)


def _stopped(proc):
    """Gone, a zombie, or every one of its threads silent (thread_silent: a group stop or exit is done
    by each thread itself: the main thread stopped does not mean the others have)."""
    if not proc.is_running():   # gone, or its pid reused since: not this process any more
        return True
    try:
        tids = os.listdir('/proc/%d/task' % proc.pid)
    except OSError:
        return _dead(proc)
    for tid in tids:
        try:
            with open('/proc/%d/task/%s/stat' % (proc.pid, tid)) as f:
                silent = thread_silent(f.read())
        except (OSError, IndexError, ValueError):
            continue   # that thread ended meanwhile
        if not silent:
            return False
    return True


def silence_trees(roots, first=(), timeout=5.0):
    """Fail-silence at once, for a promotion: the roots (psutil.Process of launchers, checked by the
    caller) are stopped first (they neither fork nor respawn, and no child is re-parented), then the
    processes ``first`` (known nodes: a psutil.Process checks that its pid is still theirs), then every
    other process of the roots' trees, looked for twice (a child forked meanwhile is caught by the
    second look). Once every thread of them is silent (stopped, exiting or gone: see thread_silent)
    they are all sent SIGKILL, and it returns them without waiting for the kernel's tear-down: from
    then on none runs another instruction, and none can be resumed (a SIGCONT from anyone is moot)."""
    _signal_all(roots, signal.SIGSTOP)
    _signal_all(first, signal.SIGSTOP)
    seen = {p.pid for p in first}
    procs = list(first)
    for _ in range(2):
        for root in roots:
            for proc in process_tree(root.pid):
                if proc.pid not in seen:
                    seen.add(proc.pid)
                    procs.append(proc)
                    _signal_all([proc], signal.SIGSTOP)
    running = wait_stopped(procs, timeout)
    _signal_all(procs, signal.SIGKILL)
    if running:   # never seen stopped (in the kernel's uninterruptible sleep): seen dead, then
        wait_dead(running, timeout)
    return procs


def _wait_all(procs, done, timeout, poll, meanwhile=None):
    """Wait until done(p) for every process, polling (meanwhile(left) at each poll, if given); returns
    those it still is not."""
    deadline = time.monotonic() + timeout
    left = [p for p in procs if not done(p)]
    while left and time.monotonic() < deadline:
        if meanwhile is not None:
            meanwhile(left)
        time.sleep(poll)
        left = [p for p in left if not done(p)]
    return left


def wait_stopped(procs, timeout):
    """Wait until every process is stopped or dead (see _stopped), sending SIGSTOP again to those not
    yet: a SIGCONT from anyone else (a frozen host resumed, its processes' own parent, a debugger)
    undoes a stop, and the wait then held a fencing for its whole timeout while the process ran (a
    whole board frozen and resumed in the middle of its fencing ran on for 5 s, and its backup was
    promoted only then: tjp_sim's board_freeze). Returns those still running."""
    return _wait_all(procs, _stopped, timeout, 0.0005, meanwhile=lambda left: _signal_all(left, signal.SIGSTOP))


def wait_dead(procs, timeout):
    """Wait until every process is dead (see _dead). Returns those still running."""
    return _wait_all(procs, _dead, timeout, 0.001)


def terminate_tree(pid, grace=5.0):
    """Ask pid's tree to stop (SIGINT, as Ctrl-C to roslaunch), then power it off after grace seconds."""
    procs = process_tree(pid)
    if not procs:
        return 0
    _signal_all(procs[:1], signal.SIGINT)
    alive = wait_dead(procs, grace)
    if alive:
        _signal_all(alive, signal.SIGKILL)
        wait_dead(alive, grace)
    return len(procs)


class Site(object):
    """A command started as a site (for example ``roslaunch --wait pkg file.launch args``)."""

    def __init__(self, name, argv, env=None, log_path=None, cwd=None):
        self.name = name
        self.argv = list(argv)
        self.env = env
        self.cwd = cwd             # working directory of the command (None: this process's)
        self.log_path = log_path
        self.proc = None
        self._log = None
        self._log_start = 0        # where this start's output begins in the log (it is appended to)
        self.powered_off_at = None   # wall-clock time at which power_off() stopped the whole site

    def start(self, niceness=0):
        """Start the command; with niceness > 0 it (and what it starts) runs at a lower priority."""
        if self.log_path:
            self._log = open(self.log_path, 'ab')
            self._log_start = self._log.tell()
        out = self._log if self._log else subprocess.DEVNULL
        self.proc = subprocess.Popen(self.argv, env=self.env, cwd=self.cwd, stdout=out, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, start_new_session=True,
                                     preexec_fn=(lambda: os.nice(niceness)) if niceness else None)
        return self

    def set_niceness(self, niceness):
        """Give every process of the site this niceness. Returns the processes that refused
        (lowering it needs privileges)."""
        refused = []
        for proc in process_tree(self.pid) if self.alive() else []:
            try:
                proc.nice(niceness)
            except psutil.AccessDenied:
                refused.append(proc.pid)
            except psutil.NoSuchProcess:
                pass
        return refused

    @property
    def pid(self):
        return self.proc.pid if self.proc else None

    def alive(self):
        return self.proc is not None and self.proc.poll() is None

    def failure(self, ignore=()):
        """Why the started site is no longer whole, or None: its command exited, or a node of it
        died (read from this start's roslaunch output in the log), other than the nodes in ignore
        (graph names: nodes retired on purpose, such as those an adaptation killed). A site waited
        for while it starts can be given up at once then, rather than at the end of the wait."""
        if self.proc is None:
            return None
        if self.proc.poll() is not None:
            return 'site %s exited (code %s)' % (self.name, self.proc.returncode)
        text = self.output()
        if not [node for node in nodes_died(text) if node not in ignore]:
            return None
        return 'site %s: %s' % (self.name, launch_failure(text))

    def output(self):
        """What this start of the command wrote to its log so far ('' without a log, or none yet)."""
        if self.proc is None or not self.log_path:
            return ''
        try:
            with open(self.log_path, 'rb') as f:
                f.seek(self._log_start)
                return f.read().decode(errors='replace')
        except OSError:   # not written yet
            return ''

    def ended(self):
        """{node: how it ended} for the nodes of this start whose process its roslaunch says ended
        (:func:`nodes_ended`) while the launch may run on (nodes not required)."""
        return nodes_ended(self.output())

    def power_off(self):
        """Kill the whole site at once, as a power loss would."""
        if self.proc is None or self.proc.poll() is not None:
            return 0
        count = power_off(self.proc.pid, on_stopped=lambda: setattr(self, 'powered_off_at', time.time()))
        self.proc.wait()
        return count

    def power_off_fault(self):
        """power_off() as a fault to inject: returns (processes killed, wall time the site stopped)."""
        return self.power_off(), self.powered_off_at

    def stop(self, grace=5.0):
        """Stop the site cleanly if it can, by force otherwise. Never raises."""
        try:
            # Once reaped, the pid may belong to another process: never signal it then.
            if self.proc is not None and self.proc.poll() is None:
                terminate_tree(self.proc.pid, grace)
                power_off(self.proc.pid)
                try:
                    self.proc.wait(timeout=grace)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
        except Exception:   # shutdown paths never raise
            pass
        finally:
            if self._log:
                self._log.close()
                self._log = None


def power_off_sites(sites, timeout=5.0):
    """Power off every running site at the same instant (power_off_trees), then reap and close
    them: the end of a test or an experiment, where nothing needs a clean exit. Never raises."""
    try:
        running = [site for site in sites if site.alive()]
        power_off_trees([site.pid for site in running], timeout)
        for site in running:
            site.proc.wait(timeout)
    except Exception:   # shutdown paths never raise: Site.stop below kills what is left
        pass
    for site in sites:
        site.stop(grace=1.0)


def stop_sites(sites, grace=5.0):
    """Site.stop() of every site at once: a roslaunch takes a second or two to stop its nodes,
    and the sites do not wait for one another. Never raises."""
    threads = [threading.Thread(target=site.stop, kwargs={'grace': grace}, daemon=True) for site in sites]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(3 * grace + 5.0)   # Site.stop waits at most 3 grace


_DIED = re.compile(r'process \[?([^\]\s]+?)(?:-\d+)?\]? has died|\[([^\]\s]+?)-\d+\] process has died')
_EXIT_CODE = re.compile(r'exit code (-?\d+)')
_ERROR = re.compile(r'\[(?:FATAL|ERROR)\] \[[\d.]+\]: (.*)')


def nodes_died(text):
    """The nodes a roslaunch's output says died, in order, each once."""
    died = []
    for line in text.splitlines():
        match = _DIED.search(line)
        if match:
            name = '/' + (match.group(1) or match.group(2)).lstrip('/')
            if name not in died:
                died.append(name)
    return died


_FINISHED = re.compile(r'\[([^\]\s]+?)-\d+\] process has finished cleanly')
_RESTARTED = re.compile(r'\[([^\]\s]+?)-\d+\] restarting process')


def nodes_ended(text):
    """{node: how its process ended} for the nodes whose process a roslaunch's output says ended and
    was not started again since (respawn): 'died (exit code N)', 'died' or 'finished cleanly'."""
    ended = {}
    for line in text.splitlines():
        restarted = _RESTARTED.search(line)
        if restarted:
            ended.pop('/' + restarted.group(1).lstrip('/'), None)
            continue
        died, finished = _DIED.search(line), _FINISHED.search(line)
        if died:
            code = _EXIT_CODE.search(line)
            ended['/' + (died.group(1) or died.group(2)).lstrip('/')] = \
                'died (exit code %s)' % code.group(1) if code else 'died'
        elif finished:
            ended['/' + finished.group(1).lstrip('/')] = 'finished cleanly'
    return ended


def launch_failure(text, errors=2):
    """Why a roslaunch ended, from its output: the nodes that died with their exit codes, then its
    last errors. '' if the output says nothing of it."""
    died, codes = nodes_died(text), []
    for line in text.splitlines():
        match = _EXIT_CODE.search(line)
        if match and 'has died' in line:
            codes.append(match.group(1))
    parts = []
    if died:
        parts.append('%s died%s' % (', '.join(died), ' (exit code %s)' % ', '.join(codes) if codes else ''))
    said = last_errors(text, errors)
    if said:
        parts.append(said)
    return '; '.join(parts)


def last_errors(text, errors=2):
    """'last error(s): ...': the last ``errors`` ERROR or FATAL lines of a roslaunch's output ('' if none)."""
    messages = [m.group(1).strip() for m in (_ERROR.search(line) for line in text.splitlines()) if m]
    if not messages:
        return ''
    return 'last error%s: %s' % ('s' if len(messages[-errors:]) > 1 else '', '; '.join(messages[-errors:]))


def wait_until(predicate, timeout, interval=0.02):
    """Poll predicate until it is true or timeout seconds passed. Returns its last value."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value or time.monotonic() >= deadline:
            return value
        time.sleep(interval)


def this_host():
    """The name this host's nodes are known by: ROS_HOSTNAME, else ROS_IP (as ROS advertises its
    nodes), else the machine's name. Emulated hosts share one kernel, so the machine's name is the
    same in all of them; their ROS_IP/ROS_HOSTNAME tell them apart."""
    return os.environ.get('ROS_HOSTNAME') or os.environ.get('ROS_IP') or os.uname()[1]
