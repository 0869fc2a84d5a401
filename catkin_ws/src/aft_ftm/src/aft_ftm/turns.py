"""One adaptation at a time on a ROS master: the Adaptation Engines of one machine take turns.

The monitor's engine and an operator's ``adapt`` each suspend, launch, rebind and kill on the same
graph. Run at once, each found the other's suspensions (a node suspended by another owner refuses a
second suspension) and rolled back, after launching, or worse rebound ports the other had just
moved (review of session 35). An engine only kills and starts nodes of its own machine, so a lock
of that machine is enough: :class:`Turn` is an exclusive ``flock`` on a file named after the ROS
master (:func:`master_key`: one name however its URI spells it). The kernel releases it when its
holder exits, however it exits, so a killed engine never keeps the turn. A waiting engine waits at
most ``timeout`` seconds, and stops waiting as soon as ``stop()`` names a reason (an interrupt);
either way it raises :class:`Busy`, naming the holder, which wrote who it is into the file.
Plain Python, no ROS.
"""
import fcntl
import hashlib
import ipaddress
import os
import socket
import time
import urllib.parse

import psutil


class Busy(Exception):
    """The turn was not had: the holder, and why the wait ended, are in the message."""


DEFAULT_PORT = 11311   # a master URI's port when it names none (ROS's default)


def _addresses(host):
    """The IP addresses host resolves to here (ipaddress objects, scope ids dropped); [] if it does not."""
    try:
        infos = socket.getaddrinfo(host, None, proto=socket.IPPROTO_TCP)
    except (OSError, UnicodeError):   # not resolvable here (UnicodeError: not even a valid name)
        return []
    found = set()
    for info in infos:
        try:
            found.add(ipaddress.ip_address(info[4][0].split('%')[0]))
        except ValueError:
            continue
    return sorted(found, key=_order)


def _local_addresses():
    """The addresses of this machine's interfaces (of this network namespace: an emulated host's own)."""
    found = set()
    try:
        interfaces = psutil.net_if_addrs()
    except (OSError, psutil.Error):   # not readable here: loopback addresses are still known as such
        return found
    for addresses in interfaces.values():
        for address in addresses:
            if address.family in (socket.AF_INET, socket.AF_INET6):
                try:
                    found.add(ipaddress.ip_address(address.address.split('%')[0]))
                except ValueError:
                    continue
    return found


def _order(address):
    return address.version, int(address)


def _this_host(local):
    """The one name of this machine in a key: its first address that is neither loopback nor link-local,
    IPv4 first (the same whichever of its addresses or names a URI gives), 127.0.0.1 if it has none."""
    routable = [a for a in local if not (a.is_loopback or a.is_link_local or a.is_unspecified)]
    return min(routable, key=_order) if routable else ipaddress.ip_address('127.0.0.1')


def master_key(uri):
    """One name for one master however its URI is spelt (two spellings took two turns; reviews of sessions
    36 and 48): the scheme (http:// when none is given) and a trailing slash left out, the port 11311 when
    none is given, the host resolved to its addresses. A host that is this machine, by any of its names
    or addresses (localhost, 127.0.0.1, ::1, its name, the address of one of its interfaces), is one
    host; another by the first of its addresses. A name that cannot be resolved here stays as written
    (in lower case): the turn is then that name's, and nothing is said. A URI that cannot be parsed at
    all is its own key."""
    text = uri.strip()
    if '://' not in text:
        text = 'http://' + text
    try:
        parsed = urllib.parse.urlsplit(text)
        port = parsed.port or DEFAULT_PORT
    except ValueError:   # a port that is no number, or out of range
        return uri
    host = (parsed.hostname or '').lower()
    addresses = _addresses(host) if host else []
    if not addresses:   # not resolvable here: as written
        return '%s:%d' % (host, port)
    local = _local_addresses()
    if any(a.is_loopback or a.is_unspecified or a in local for a in addresses):
        address = _this_host(local)
    else:
        address = addresses[0]
    return ('[%s]:%d' if address.version == 6 else '%s:%d') % (address, port)


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
