"""The local supervision channel between the service manager and the services it spawned on its
host (issue 17), as systemd's ``sd_notify`` and s6's readiness notification do, made cheap enough
to supervise at a 1 ms period. No rospy.

Two parts, both in the manager's private state directory (0700, its own):

- a **beat slot** per service (``<name>.beat``, 64 bytes, mapped by both sides): the service writes
  its beat count, the CLOCK_MONOTONIC time of its last beat and its status there (a sequence lock:
  the count is odd while it writes). A beat is one memory write, about a microsecond: no message,
  no system call, and the manager is not woken by it. The manager reads the slot when it would
  declare the service hung (its last beat plus the timeout): one read per timeout per service.
- the **manager's socket** (``<manager>.sock``, a Unix datagram socket with SO_PASSCRED): what must
  wake the manager goes there: the first beat of an instance (it is running), an error the service
  reports, a warm spare's readiness. The kernel stamps each datagram with the sender's pid, which
  the manager checks against the service's own process tree (nobody else can write in the
  directory, and a pid cannot be forged).

- a **watchdog timer** per service with a heartbeat timeout (a Linux timerfd the manager makes and
  the service inherits, ``AFT_WATCHDOG_FD``): each beat re-arms it for the timeout (one system
  call, under a microsecond); it fires, and wakes the manager, only when the service has not beaten
  for the timeout. So a healthy service costs the manager no wake at all: hangs are watched by the
  kernel, as systemd's ``WatchdogSec`` and a hardware watchdog are.

A warm spare (``AFT_SPARE=1``) sets itself up, says ``ready``, and waits for a byte on the pipe the
manager gave it (``AFT_PROMOTE_FD``; the thread that waits wakes at once), or for SIGUSR1 (a
manager that adopted the spare has no pipe to it), the manager's
promotion; then it restores the saved state and starts its cycle.

Both ends are plain Python; :class:`ServiceEnd` is what a service uses (through
``aft_service_manager.ros.service_heartbeat.Heartbeat``, or directly).
"""
import ctypes
import ctypes.util
import mmap
import os
import select
import signal
import socket
import stat
import struct
import threading
import time

SLOT_SIZE = 64
_SLOT = struct.Struct('<QqB')      # sequence (odd while written), monotonic ns of the last beat, status
STATUS = {'ok': 0, 'error': 1}
MAX_DATAGRAM = 4096

ENV_SLOT, ENV_SOCKET, ENV_SPARE = 'AFT_BEAT_FILE', 'AFT_MANAGER_SOCKET', 'AFT_SPARE'
ENV_WATCHDOG, ENV_WATCHDOG_TIMEOUT = 'AFT_WATCHDOG_FD', 'AFT_WATCHDOG_TIMEOUT'
ENV_PROMOTE = 'AFT_PROMOTE_FD'


class _Timespec(ctypes.Structure):
    _fields_ = [('tv_sec', ctypes.c_long), ('tv_nsec', ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [('it_interval', _Timespec), ('it_value', _Timespec)]


_LIBC = None


def _libc():
    global _LIBC
    if _LIBC is None:
        _LIBC = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6', use_errno=True)
    return _LIBC


class Watchdog(object):
    """A timerfd on CLOCK_MONOTONIC (Python before 3.13 has no binding: libc through ctypes).
    ``arm(seconds)`` (re)starts it, 0 stops it; the descriptor is readable once it fired."""
    CLOCK_MONOTONIC, TFD_NONBLOCK = 1, os.O_NONBLOCK

    def __init__(self, fd=None):
        if fd is None:
            fd = _libc().timerfd_create(self.CLOCK_MONOTONIC, self.TFD_NONBLOCK)
            if fd < 0:
                raise OSError(ctypes.get_errno(), 'timerfd_create: %s' % os.strerror(ctypes.get_errno()))
        self.fd = fd
        self._spec = _Itimerspec()

    def fileno(self):
        return self.fd

    def arm(self, seconds):
        whole = int(seconds)
        self._spec.it_value.tv_sec, self._spec.it_value.tv_nsec = whole, int((seconds - whole) * 1e9)
        if seconds > 0 and not (whole or self._spec.it_value.tv_nsec):
            self._spec.it_value.tv_nsec = 1
        if _libc().timerfd_settime(self.fd, 0, ctypes.byref(self._spec), None) != 0:
            raise OSError(ctypes.get_errno(), 'timerfd_settime: %s' % os.strerror(ctypes.get_errno()))

    def armed(self):
        """Whether it is set to fire (someone armed it and it has not fired yet). The manager relies on a
        service's watchdog only once it sees it armed: a service that did not inherit the descriptor
        (roslaunch closes them) beats into its slot but never arms it."""
        current = _Itimerspec()
        if _libc().timerfd_gettime(self.fd, ctypes.byref(current)) != 0:
            return False
        return bool(current.it_value.tv_sec or current.it_value.tv_nsec)

    def fired(self):
        """Whether it fired since the last call (its count read and cleared)."""
        try:
            return struct.unpack('Q', os.read(self.fd, 8))[0] > 0
        except BlockingIOError:
            return False

    def close(self):
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def slot_path(state_dir, name):
    return os.path.join(state_dir, '%s.beat' % name)


def socket_path(state_dir, prefix):
    """The manager's socket in its state directory; in the abstract namespace (a leading NUL, no
    file) when that path is too long for a Unix socket (108 bytes), the senders checked by pid all
    the same."""
    path = os.path.join(state_dir, '%s.sock' % prefix)
    if len(path.encode()) <= 100:
        return path
    import hashlib
    return '\0aft_service_manager_%s' % hashlib.sha256(path.encode()).hexdigest()[:24]


class BeatSlot(object):
    """One service's slot, mapped. ``write`` is the service's side, ``read`` the manager's."""

    def __init__(self, path, create=False):
        self.path = path
        flags = os.O_RDWR | (os.O_CREAT if create else 0) | getattr(os, 'O_NOFOLLOW', 0)
        fd = os.open(path, flags, 0o600)
        try:
            if create:
                os.ftruncate(fd, 0)
                os.ftruncate(fd, SLOT_SIZE)    # zeroed: no beat yet
            elif os.fstat(fd).st_size < SLOT_SIZE:
                raise ValueError('%s is not a beat slot (%d bytes)' % (path, os.fstat(fd).st_size))
            self.map = mmap.mmap(fd, SLOT_SIZE)
        finally:
            os.close(fd)
        self.seq = _SLOT.unpack_from(self.map, 0)[0] & ~1

    def write(self, status='ok', now_ns=None):
        """A beat: seq odd, the fields, seq even (a reader retries a torn read)."""
        self.seq += 1
        struct.pack_into('<Q', self.map, 0, self.seq)
        struct.pack_into('<qB', self.map, 8, time.monotonic_ns() if now_ns is None else now_ns, STATUS.get(status, 1))
        self.seq += 1
        struct.pack_into('<Q', self.map, 0, self.seq)

    def read(self):
        """(beats, monotonic seconds of the last, status) or None before any beat."""
        for _ in range(100):
            seq, ns, status = _SLOT.unpack_from(self.map, 0)
            if seq & 1:
                continue
            if _SLOT.unpack_from(self.map, 0)[0] == seq:
                return None if seq == 0 else (seq // 2, ns / 1e9, 'ok' if status == 0 else 'error')
        return None   # a writer stuck mid-beat (stopped there): no beat seen

    def close(self):
        try:
            self.map.close()
        except (ValueError, BufferError):
            pass


class ManagerSocket(object):
    """The manager's end: a Unix datagram socket at ``path``; each datagram comes with its sender's pid."""

    def __init__(self, path):
        self.path = path
        self.abstract = path.startswith('\0')
        if not self.abstract and os.path.lexists(path):
            os.unlink(path)   # a socket left by an earlier manager (the directory is the manager's own)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
        self.sock.bind(path)
        self.own = None
        if not self.abstract:
            os.chmod(path, 0o600)
            info = os.lstat(path)
            self.own = (info.st_dev, info.st_ino)   # what close() may remove
        self.sock.setblocking(False)

    def fileno(self):
        return self.sock.fileno()

    def address(self):
        """The socket's address as an environment variable can carry it ('@' for the leading NUL)."""
        return '@' + self.path[1:] if self.abstract else self.path

    def receive(self, limit=1000):
        """The datagrams waiting: [(sender pid or None, text)], at most ``limit``."""
        out = []
        space = socket.CMSG_SPACE(struct.calcsize('3i'))
        while len(out) < limit:
            try:
                data, ancillary, _, _ = self.sock.recvmsg(MAX_DATAGRAM, space)
            except (BlockingIOError, InterruptedError):
                break
            pid = None
            for level, kind, payload in ancillary:
                if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS and len(payload) >= 4:
                    pid = struct.unpack_from('i', payload)[0]
            out.append((pid, data.decode('utf-8', 'replace')))
        return out

    def close(self):
        """Close it, and remove its file only if it is still this socket's: a manager whose shutdown ran
        after its successor had started removed the successor's socket (review of session 34)."""
        self.sock.close()
        if not self.abstract:
            try:
                info = os.lstat(self.path)
                if (info.st_dev, info.st_ino) == self.own:
                    os.unlink(self.path)
            except OSError:
                pass


def parse(text):
    """A datagram's (verb, service name, detail): 'started NAME', 'error NAME DETAIL', 'ok NAME',
    'ready NAME'; None if it is none of them."""
    parts = text.split(' ', 2)
    if len(parts) < 2 or parts[0] not in ('started', 'error', 'ok', 'ready') or not parts[1]:
        return None
    return parts[0], parts[1], parts[2] if len(parts) > 2 else ''


def _inherited(number, kind):
    """The descriptor an environment variable names, if this process really holds one of that kind
    (a 'pipe', or a /proc link such as 'anon_inode:[timerfd]'); None otherwise. The variable passes
    to descendants that the descriptor did not (roslaunch and subprocess close descriptors), where
    the number names something else."""
    if not number.isdigit():
        return None
    fd = int(number)
    try:
        if kind == 'pipe':
            return fd if stat.S_ISFIFO(os.fstat(fd).st_mode) else None
        return fd if os.readlink('/proc/self/fd/%d' % fd) == kind else None
    except OSError:
        return None


class ServiceEnd(object):
    """The service's end, from its environment (None from :meth:`from_environment` when the manager
    gave it no channel: a service started by hand, or on another host, beats on the ROS topic)."""

    def __init__(self, name, slot_file, socket_path, spare=False, watchdog=None):
        self.name = name
        self.watchdog = watchdog   # (Watchdog, timeout): re-armed at each beat
        self.slot = BeatSlot(slot_file)
        self.socket_path = socket_path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        # Never blocking: the manager's queue holds 10 datagrams (net.unix.max_dgram_qlen) for every
        # service; a manager stopped 1.5 s with it full blocked the service's own cycle in its beat
        # (review of stop 39). A message that does not fit is sent again at the next beat.
        self.sock.setblocking(False)
        self.spare = spare
        self.promoted = threading.Event()
        self.promote_fds = []   # readable once promoted: the manager's pipe, and this process's own
        if not spare:
            self.promoted.set()
        elif threading.current_thread() is threading.main_thread():
            # before 'ready': SIGUSR1 would otherwise end the process. Its handler writes to a pipe
            # of this process's own, so the waiting thread wakes as for the manager's byte.
            own_r, own_w = os.pipe()
            self.promote_fds.append(own_r)
            signal.signal(signal.SIGUSR1, lambda *_: os.write(own_w, b'p'))
            promote = _inherited(os.environ.pop(ENV_PROMOTE, ''), 'pipe')
            if promote is not None:
                self.promote_fds.append(promote)
        else:
            raise RuntimeError('a warm spare\'s channel must be made in its main thread (its SIGUSR1 handler)')
        self.status = None

    @classmethod
    def from_environment(cls, name, environ=None):
        environ = os.environ if environ is None else environ
        if not environ.get(ENV_SLOT) or not environ.get(ENV_SOCKET):
            return None
        address = environ[ENV_SOCKET]
        address = '\0' + address[1:] if address.startswith('@') else address   # the abstract namespace
        watchdog = None
        fd = _inherited(environ.pop(ENV_WATCHDOG, ''), 'anon_inode:[timerfd]')
        if fd is not None and environ.get(ENV_WATCHDOG_TIMEOUT):
            watchdog = (Watchdog(fd), float(environ[ENV_WATCHDOG_TIMEOUT]))
        return cls(name, environ[ENV_SLOT], address, environ.get(ENV_SPARE) == '1', watchdog)

    def send(self, verb, detail=''):
        try:
            self.sock.sendto(('%s %s %s' % (verb, self.name, detail)).encode()[:MAX_DATAGRAM], self.socket_path)
            return True
        except OSError:   # (BlockingIOError: its queue is full)
            return False   # the manager is gone, restarting or stopped: the slot still carries the beats

    def beat(self, status='ok', detail=''):
        """Each cycle. The first beat, and any change of status, also wake the manager."""
        self.slot.write(status)
        if self.watchdog is not None:
            try:
                self.watchdog[0].arm(self.watchdog[1])
            except OSError:   # supervision never stops the service's cycle: the manager's deadline remains
                self.watchdog = None
        if status != self.status:
            if self.send('started' if self.status is None and status == 'ok' else status, detail):
                self.status = status   # else told again at the next beat: a change is never lost

    def wait_promoted(self, timeout=None):
        """A warm spare, set up (its publishers made): say it is ready, then wait for the manager's
        SIGUSR1. True once promoted (at once for an instance that is no spare)."""
        if self.promoted.is_set():
            return True
        said = self.send('ready')
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.promoted.is_set():
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                break
            if not said:   # the manager's queue was full: said again until it fits (else replaced as hung)
                said = self.send('ready')
                left = 0.1 if said is False and (left is None or left > 0.1) else left
            for fd in select.select(self.promote_fds, [], [], left)[0]:
                if os.read(fd, 1):
                    self.promoted.set()
                else:   # the manager's end closed (it died): not a promotion; its successor signals
                    self.promote_fds.remove(fd)
                    os.close(fd)
        return self.promoted.is_set()
