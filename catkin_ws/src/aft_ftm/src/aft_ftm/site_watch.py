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

import psutil

from .errors import AftError


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


def children_nodes(launcher_pid):
    """[(pid, node name)] of the ROS nodes the launcher process started (its direct children)."""
    found = []
    try:
        children = psutil.Process(launcher_pid).children()
    except psutil.Error:
        return found
    for child in children:
        try:
            name = node_name(child.cmdline(), child.environ())
        except psutil.Error:
            continue   # gone meanwhile, or unreadable: looked at again at the next scan
        if name:
            found.append((child.pid, name))
    return found


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

    def close(self):
        for fd in list(self.watched):
            self.poller.unregister(fd)
            os.close(fd)
        self.watched.clear()
