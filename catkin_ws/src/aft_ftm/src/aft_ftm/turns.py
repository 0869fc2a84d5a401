"""One adaptation at a time on a ROS master: the Adaptation Engines of one machine take turns.

The monitor's engine and an operator's ``adapt`` each suspend, launch, rebind and kill on the same
graph. Run at once, each found the other's suspensions (a node suspended by another owner refuses a
second suspension) and rolled back, after launching, or worse rebound ports the other had just
moved (review of session 35). An engine only kills and starts nodes of its own machine, so a lock
of that machine is enough: :class:`Turn` is an exclusive ``flock`` on a file named after the ROS
master's URI. The kernel releases it when its holder exits, however it exits, so a killed engine
never keeps the turn. A waiting engine waits at most ``timeout`` seconds, and stops waiting as
soon as ``stop()`` names a reason (an interrupt); either way it raises :class:`Busy`, naming the
holder, which wrote who it is into the file.
Plain Python, no ROS.
"""
import fcntl
import hashlib
import os
import socket
import time
import urllib.parse


class Busy(Exception):
    """The turn was not had: the holder, and why the wait ended, are in the message."""


def master_key(uri):
    """One name for one master however its URI is spelt: localhost or its address, a trailing slash,
    the case of the host (two spellings took two turns; review of session 36)."""
    try:
        parsed = urllib.parse.urlparse(uri)
        host = (parsed.hostname or '').lower()
        try:
            host = socket.gethostbyname(host) if host else host
        except OSError:   # not resolvable here: as written
            pass
        if host.startswith('127.'):
            host = '127.0.0.1'
        return '%s:%s' % (host, parsed.port or 11311)
    except ValueError:
        return uri


class Turn(object):
    DIRECTORY = '/tmp'   # not $TMPDIR: two engines with different ones took two turns

    def __init__(self, key, directory=None):
        name = 'aft_adaptation_%s.lock' % hashlib.sha256(master_key(key).encode()).hexdigest()[:16]
        self.path = os.path.join(directory or self.DIRECTORY, name)
        self.fd = None

    def holder(self):
        """Who holds the turn, as it wrote it (or '' if nobody said)."""
        try:
            with open(self.path, errors='replace') as f:
                return f.read(500).strip() or 'an engine that did not say who it is'
        except OSError:
            return 'unknown'

    def take(self, who, timeout, stop=lambda: '', waiting=None, poll=0.05):
        """Take the turn, waiting up to ``timeout`` s; ``who`` is written for the others to read.
        ``waiting(holder)`` is called once if it has to wait. Returns the seconds waited; raises
        Busy past the timeout or once stop() returns a reason."""
        if self.fd is not None:
            raise RuntimeError('the turn is held already')
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:   # another user's file, a read-only /tmp: said, and nothing changed
            raise Busy('cannot take the adaptation turn (%s): %s' % (self.path, e))
        started = time.monotonic()
        told = False
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    why = stop()
                    if why:
                        raise Busy('%s while waiting for the adaptation in progress (%s)' % (why, self.holder()))
                    if time.monotonic() - started >= timeout:
                        raise Busy('another adaptation has held the turn for %.0f s and still does: %s'
                                   % (timeout, self.holder()))
                    if waiting is not None and not told:
                        told = True
                        waiting(self.holder())
                    time.sleep(poll)
            os.ftruncate(fd, 0)
            os.pwrite(fd, ('%s (since %s)' % (who, time.strftime('%H:%M:%S'))).encode(), 0)
        except BaseException:
            os.close(fd)
            raise
        self.fd = fd
        return time.monotonic() - started

    def give(self):
        """Give the turn back (once; nothing if not held)."""
        fd, self.fd = self.fd, None
        if fd is None:
            return
        try:
            os.ftruncate(fd, 0)
        finally:
            os.close(fd)   # (closing releases the flock)
