"""The required nodes of a replica site, watched by its crash detector: the death of one is the
site's failure, told at once.

roslaunch shuts a whole launch down when one of its required nodes dies, but it notices only at its
next poll (every 0.1 s) and then stops the nodes one after the other, each with SIGINT and a
grace: the site's crash detector went on heartbeating for about 200 ms after a kill, and the peer
took over only then (the campaign's kills: client-visible failover about 200 ms more than a power
loss's). The detector now holds a pidfd (Linux 5.3) of each required node of its own launch, and
the kernel wakes it the moment one exits: it stops heartbeating at once (a fail-stop, with its
alarm), and the peer takes over after its detection timeout alone. Nothing changes in what fails
the site: exactly the nodes whose death roslaunch answers with a shutdown anyway.

No rospy here: the processes come from psutil, the node names from their command line and
environment (roslaunch passes ``__name:=`` and sets ROS_NAMESPACE), the required names from the
launch file (aft_ftm.ros.launch_files).
"""
import os
import select
import stat
import time

import psutil

from .errors import AftError

# Where an adaptation marks the processes it is about to stop on purpose (one file per process, named by
# its pid and start time, holding when it was written): the watch of an adaptable site lets those die. A tmpfs shared by
# every network namespace of the host (emulated hosts included), one directory per user, which must be
# that user's alone (a mark planted by another user would hide a crash). AFT_RETIRED_DIR overrides it.
RETIRED_DIR = os.environ.get('AFT_RETIRED_DIR') or os.path.join(
    '/dev/shm' if os.path.isdir('/dev/shm') else '/tmp', 'aft_retired-%d' % os.geteuid())
STALE_MARK_S = 600.0   # a mark older than this is removed by the next one written
# A mark counts only if the watch takes it this soon after it was written. The engine writes it just
# before it stops the node (SIGINT, SIGKILL 5 s later, then 2 s more), and the watch takes it when it
# hears the death, at once. An engine stopped between the mark and the signal leaves a mark behind:
# without this limit, that node's real crash minutes later would be let go as a retirement and its site
# would not fail over. The mark holds the time it was written on CLOCK_BOOTTIME (one clock for every
# process of the host, never stepped: a wall-clock step cannot age or rejuvenate a mark).
MARK_VALID_S = 20.0


def _boot_clock():
    return time.clock_gettime(time.CLOCK_BOOTTIME)


def start_ticks(pid):
    """The start time of process pid in clock ticks since boot (/proc/PID/stat, field 22): with the
    pid, it names one process for good. (psutil's create time adds the boot time, which each process
    reads once and which moves with the wall clock: two processes could name the same one apart.)
    Raises OSError (ProcessLookupError included) if there is no such process."""
    with open('/proc/%d/stat' % pid) as f:
        return int(f.read().rsplit(')', 1)[1].split()[19])


def _marker(pid, ticks):
    return os.path.join(RETIRED_DIR, '%d-%d' % (pid, ticks))


def _own_directory():
    """Whether RETIRED_DIR is a directory of this user that nobody else may write into."""
    try:
        info = os.stat(RETIRED_DIR)
    except OSError:
        return False
    return stat.S_ISDIR(info.st_mode) and info.st_uid == os.geteuid() and not info.st_mode & 0o022


def mark_retired(pid):
    """Say that process pid is about to be stopped on purpose (an adaptation retires its node), so that
    its site's watch does not take its death for a failure. Returns the mark's path, or None if the
    process is gone already. Raises OSError if the mark cannot be written (or the directory is not
    this user's alone)."""
    try:
        ticks = start_ticks(pid)
    except (FileNotFoundError, ProcessLookupError):
        return None
    os.makedirs(RETIRED_DIR, mode=0o700, exist_ok=True)
    if not _own_directory():
        raise PermissionError('%s is not a directory of this user alone' % RETIRED_DIR)
    _prune(time.time() - STALE_MARK_S)
    path = _marker(pid, ticks)
    with open(path, 'w') as f:
        f.write('%.6f\n' % _boot_clock())
    return path


def _prune(before):
    """Remove the marks written before that time (their process's watch, if any, took them long ago, or
    it died with its site first)."""
    try:
        names = os.listdir(RETIRED_DIR)
    except OSError:
        return
    for name in names:
        path = os.path.join(RETIRED_DIR, name)
        try:
            if os.stat(path).st_mtime < before:
                os.unlink(path)
        except OSError:   # taken meanwhile
            pass


def take_retired(pid, ticks, now=None):
    """Whether process pid, started at ticks, was marked retired at most MARK_VALID_S ago (``now`` on
    CLOCK_BOOTTIME, default the clock's); the mark is removed, fresh or not. A directory that is not this
    user's alone, a mark that does not hold its time, or any error, counts as no mark: the death is then
    a failure."""
    if not _own_directory():
        return False
    path = _marker(pid, ticks)
    try:
        with open(path) as f:
            text = f.read(64)
        os.unlink(path)
        written = float(text)
    except (OSError, ValueError):
        return False
    age = (_boot_clock() if now is None else now) - written
    return 0.0 <= age <= MARK_VALID_S


class WatchError(AftError):
    """The site's nodes cannot be watched here (no pidfd on this kernel)."""


def node_name(cmdline, environ):
    """The absolute ROS name of a node process started by roslaunch, or None if it is not one."""
    name = ns = None
    for arg in cmdline:
        if arg.startswith('__name:='):
            name = arg[len('__name:='):]
        elif arg.startswith('__ns:='):
            ns = arg[len('__ns:='):]
    if not name:
        return None
    if name.startswith('/'):
        return name
    ns = ns if ns is not None else environ.get('ROS_NAMESPACE', '/')
    ns = '/' + ns.strip('/')
    return (ns.rstrip('/') + '/' + name) if ns != '/' else '/' + name


def children_named(launcher_pid):
    """[(pid, node name or None)] of a process's direct children, as /proc names them. Left out: a
    child gone meanwhile or unreadable (looked at again at the next scan), and one forked but not yet
    exec'd, its command line still its parent's (it is nobody's node yet)."""
    found = []
    try:
        launcher = psutil.Process(launcher_pid)
        children, own = launcher.children(), launcher.cmdline()
    except psutil.Error:
        return found
    for child in children:
        try:
            argv = child.cmdline()
            if argv != own:
                found.append((child.pid, node_name(argv, child.environ())))
        except psutil.Error:
            continue
    return found


def children_nodes(launcher_pid):
    """[(pid, node name)] of the ROS nodes the launcher process started (its direct children)."""
    return [(pid, name) for pid, name in children_named(launcher_pid) if name]


class SiteWatch(object):
    """Holds a pidfd of each required node found; ``wait`` says which of them died.

    ``required``: the absolute names to watch (the caller leaves out itself). A node is adopted
    when a scan finds it; a required node not found yet is simply not watched yet (it may not have
    started: roslaunch answers its death anyway, as before).
    """

    def __init__(self, required):
        if not hasattr(os, 'pidfd_open'):
            raise WatchError('this Python has no os.pidfd_open (Linux 5.3 and Python 3.9 are needed)')
        self.required = frozenset(required)
        self.watched = {}        # fd -> (pid, name)
        self.created = {}        # pid -> start time (ticks), of the processes adopted
        self.names = set()
        self.poller = select.poll()
        self.dead = []           # (pid, name) of the watched nodes that died, in the order seen

    def missing(self):
        return self.required - self.names

    def adopt(self, nodes):
        """Watch the required ones among (pid, name) pairs not watched yet; returns the names adopted."""
        adopted = []
        for pid, name in nodes:
            if name not in self.required or name in self.names:
                continue
            try:
                fd = os.pidfd_open(pid)
            except ProcessLookupError:
                continue   # died before it could be watched: roslaunch answers it
            except OSError as e:
                raise WatchError('pidfd_open(%d) for %s: %s' % (pid, name, e))
            try:
                self.created[pid] = start_ticks(pid)
            except OSError:   # died meanwhile (the pidfd tells it at the next wait): not marked, a failure
                self.created[pid] = None
            self.watched[fd] = (pid, name)
            self.names.add(name)
            self.poller.register(fd, select.POLLIN)
            adopted.append(name)
        return adopted

    def wait(self, timeout):
        """Wait at most timeout s; the (pid, name) of the watched nodes that died meanwhile."""
        died = []
        for fd, _ in self.poller.poll(max(0, int(timeout * 1000))):
            pid, name = self.watched.pop(fd)
            self.poller.unregister(fd)
            os.close(fd)
            died.append((pid, name))
        self.dead += died
        return died

    def retired(self, pid):
        """Whether the adopted process pid, now dead, was marked retired (mark_retired); the mark is removed."""
        ticks = self.created.get(pid)
        return ticks is not None and take_retired(pid, ticks)

    def close(self):
        for fd in list(self.watched):
            self.poller.unregister(fd)
            os.close(fd)
        self.watched.clear()
