"""What the service manager trusts, checked (issue 16). The manager runs as root in the documented
set-up and signals process groups: everything that tells it which process to signal, or that a
service is alive, must come from itself or from its own children. No rospy.

- :func:`ensure_private_dir`: its state directory is a real directory that it owns and that no one
  else may write (made 0700 when missing); anything else is refused, naming the problem, rather
  than used (a planted pid file in a world-writable ``/tmp/aft_service_state`` had it kill the
  process groups the file named).
- :func:`write_private_json` / :func:`read_private_json`: the pid file written atomically, 0600,
  and read only if it is still a regular file of the manager's own.
- :func:`describe` / :func:`same_process`: a process is named by its pid, its start time and its
  command line, and signalled only while all three still match (a pid is reused).
- :class:`HeartbeatOrigins`: a heartbeat counts only if it comes from the service's own process
  tree: the claimed pid must be the child or a descendant (pid 0 is no longer a pass), and it must
  be the process that published it (it holds the other end of the very connection that carried
  it, on this host: a process elsewhere listening on the same port number does not pass).
"""
import fcntl
import json
import os
import stat
import tempfile
import time

import psutil
from aft_ftm.process_start import started as process_started

from .services import ServiceConfigError

START_TIME_SLACK = 0.005  # s: starts are in clock ticks since boot (aft_ftm.process_start), exact


def default_state_dir(environ=None):
    """$ROS_HOME/aft_service_state, or ~/.ros/aft_service_state: a directory of the user's own."""
    environ = os.environ if environ is None else environ
    return os.path.join(environ.get('ROS_HOME') or os.path.join(os.path.expanduser('~'), '.ros'),
                        'aft_service_state')


def ensure_private_dir(path):
    """Make path (0700) if missing; refuse it unless it is a directory, not a link, owned by this
    process's user and not writable by group or others. Returns the path."""
    if not os.path.lexists(path):
        try:
            os.makedirs(path, mode=0o700)
        except FileExistsError:
            pass   # made meanwhile: checked below like any other
        except OSError as e:
            raise ServiceConfigError('state_dir %s cannot be made: %s' % (path, e.strerror or e))
    info = os.lstat(path)
    if stat.S_ISLNK(info.st_mode):
        raise ServiceConfigError('state_dir %s is a symbolic link: the manager keeps its state only in a directory of '
                                 'its own' % path)
    if not stat.S_ISDIR(info.st_mode):
        raise ServiceConfigError('state_dir %s is not a directory' % path)
    if info.st_uid != os.geteuid():
        raise ServiceConfigError('state_dir %s belongs to uid %d, not to this manager (uid %d): another user could '
                                 'plant the pids it kills' % (path, info.st_uid, os.geteuid()))
    if info.st_mode & 0o022:
        raise ServiceConfigError('state_dir %s is writable by others (mode %03o): make it 0700 or choose another'
                                 % (path, stat.S_IMODE(info.st_mode)))
    return path


def write_private_json(path, data):
    """Write data as JSON to path atomically (a temporary file in the same directory, 0600, renamed).
    Returns the file's identity (:func:`identity`), so that only that very file is removed later."""
    handle, temporary = tempfile.mkstemp(dir=os.path.dirname(path) or '.', prefix='.tmp-')
    try:
        with os.fdopen(handle, 'w') as f:
            json.dump(data, f)
            info = os.fstat(f.fileno())
        os.replace(temporary, path)
        return info.st_dev, info.st_ino
    except BaseException:
        try:
            os.unlink(temporary)
        except OSError:
            pass
        raise


def read_private_json(path):
    """The JSON in path, or None if there is none; raises ValueError naming why a file that is there
    is not trusted (a link, not the manager's, writable by others, not JSON)."""
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        return None
    if not stat.S_ISREG(info.st_mode):
        raise ValueError('%s is not a regular file' % path)
    if info.st_uid != os.geteuid() or info.st_mode & 0o022:
        raise ValueError('%s is not the manager\'s own (uid %d, mode %03o)' % (path, info.st_uid,
                                                                               stat.S_IMODE(info.st_mode)))
    with open(path) as f:
        return json.load(f)


def identity(path):
    """(device, inode) of the file at path (not followed), or None if there is none."""
    try:
        info = os.lstat(path)
    except OSError:
        return None
    return info.st_dev, info.st_ino


def unlink_own(path, own):
    """Remove path only if it is still the file whose identity is ``own``: a manager's shutdown removed
    its successor's socket, pid file and record, whatever the order they ran in (review of session
    34). Returns whether it was removed."""
    if own is None or identity(path) != own:
        return False
    try:
        os.unlink(path)
    except OSError:
        return False
    return True


def hold_lock(path, wait=0.0, poll=0.05):
    """Take the exclusive lock (flock) of the file path, 0600, for the life of this process: the
    descriptor is returned, to be kept open (not inherited: Python's descriptors are not), and the
    kernel releases the lock when the process ends, however it ends. A holder is waited for up to
    ``wait`` s (a manager asked to stop, which takes up to its kill_timeout); then ServiceConfigError
    names it. Two managers of one name destroyed each other's state (review of session 34)."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, 'O_NOFOLLOW', 0), 0o600)
    deadline = time.monotonic() + wait
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except BlockingIOError:
            if time.monotonic() >= deadline:
                try:
                    holder = os.pread(fd, 32, 0).decode('ascii', 'replace').strip() or 'unknown'
                finally:
                    os.close(fd)
                raise ServiceConfigError('another service manager of this name (pid %s) holds %s: a second one '
                                         'would take over and destroy its services and state; stop it first'
                                         % (holder, path))
            time.sleep(poll)
        except BaseException:
            os.close(fd)
            raise
    os.ftruncate(fd, 0)
    os.pwrite(fd, b'%d\n' % os.getpid(), 0)
    return fd


def boot_id(path='/proc/sys/kernel/random/boot_id'):
    """This boot of the machine (Linux gives each boot a new random id), or '' where it cannot be read:
    a process recorded under another boot ended with that boot, not on its own."""
    try:
        with open(path) as f:
            return f.read().strip()
    except OSError:
        return ''


def describe(proc):
    """What names a process across a pid's reuse: {'pid', 'create_time', 'cmdline'} (proc: psutil); the
    start on the boot clock (aft_ftm.process_start), so that a manager started after a wall-clock step
    still knows the services its predecessor left (psutil's create_time moves with the clock)."""
    return {'pid': proc.pid, 'create_time': process_started(proc.pid, zombie=True), 'cmdline': command_line(proc)}


EXEC_WAIT = 0.2   # s: the longest describe() waits for an exec under way to give its process a command line


def command_line(proc, wait=EXEC_WAIT, poll=0.001):
    """proc's command line, once its exec is done. Popen returns as soon as the exec closes the
    child's descriptors, before the kernel has set up the new program's arguments: read then,
    /proc/PID/cmdline is empty. Recorded so, the next manager took the process for another one
    (its command line differed) and left a hung instance running unsignalled (seen in
    test_service_manager_lost, about one run in two on a loaded machine). Read again for up to
    ``wait`` seconds; a process that has none by then (a zombie) is recorded with none."""
    deadline = time.monotonic() + wait
    while True:
        cmdline = proc.cmdline()
        if cmdline or time.monotonic() >= deadline or _zombie(proc):
            return cmdline
        time.sleep(poll)


def _zombie(proc):
    """Whether proc has ended, unreaped: its command line stays empty, nothing to wait for."""
    try:
        return proc.status() == psutil.STATUS_ZOMBIE
    except (AttributeError, psutil.Error):
        return False


def well_formed(entry):
    """Whether a pid file's entry describes a process as describe() does (pid, start time, command line)."""
    try:
        int(entry['pid']), float(entry['create_time']), list(entry['cmdline'])
        return True
    except (KeyError, TypeError, ValueError, ArithmeticError):   # Infinity, 1e999: int() overflows
        return False


def same_process(entry, proc, command_line=True):
    """None if psutil process proc is the one entry describes; else why not. Without
    ``command_line``, by its pid and start time only (a service started through a wrapper that
    execs it may have been recorded before the exec)."""
    try:
        pid, started, cmdline = int(entry['pid']), float(entry['create_time']), list(entry['cmdline'])
    except (KeyError, TypeError, ValueError, ArithmeticError):   # Infinity, 1e999: int() overflows
        return 'the record %r is malformed' % (entry,)
    if proc.pid != pid:
        return 'pid %d is not %d' % (proc.pid, pid)
    now = process_started(proc.pid, zombie=True)
    if now is None or abs(now - started) > START_TIME_SLACK:
        return 'pid %d was started at %s, not %.2f s after boot: the pid was reused' % (
            pid, 'an unknown time' if now is None else '%.2f s after boot' % now, started)
    if command_line and proc.cmdline() != cmdline:
        return 'pid %d runs %r, not %r' % (pid, proc.cmdline()[:4], cmdline[:4])
    return None


class HeartbeatOrigins(object):
    """Judges where a heartbeat comes from. ``published_by(connection, pid)``: whether process pid is
    the one that published on that connection (True, False, or None if that cannot be told);
    ``owns(pid)`` (given to judge): the service's child or a descendant of it. A verified
    (connection, pid) pair is remembered (connections are told apart by identity: rospy gives every
    message of one connection the same header dict), and checked again for another pid."""

    def __init__(self, published_by):
        self.published_by = published_by
        self.verified = {}   # id(connection) -> (connection, pid); the connection kept so its id stays its own

    def judge(self, connection, pid, owns):
        """None if the beat is the service's own; else why it is refused."""
        if not pid or pid < 0:
            return 'it names no process (pid %r)' % pid
        if not owns(pid):
            return 'pid %d is not a process of this service' % pid
        known = self.verified.get(id(connection))
        if known is not None and known[0] is connection and known[1] == pid:
            return None
        sender = self.published_by(connection, pid)
        caller = connection.get('callerid', '?') if isinstance(connection, dict) else '?'
        if sender is None:
            return 'the connection that carried it (from node %s) cannot be found' % caller
        if not sender:
            return 'it claims pid %d, but node %s that published it is another process' % (pid, caller)
        if len(self.verified) > 256:
            self.verified.clear()   # bounded: connections come and go with restarts
        self.verified[id(connection)] = (connection, pid)
        return None
