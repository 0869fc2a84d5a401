"""Fail-silence by name space: kill the nodes of a failed site, learned while they were healthy.

A frozen node (a stopped process, a hung machine) answers no XML-RPC call, so its pid must be
known before it fails: :class:`NamespaceFence` asks every node under a name space for its pid
periodically, and at failure kills those that run on this host. A pid is taken only if that process
is the node (aft_ftm.process_identity): a forged registration at the master names any pid it likes.
Nodes on other hosts can only be asked to shut down (a real deployment adds a power switch there;
under TLS they refuse, and the switch is the only way).
"""
import ipaddress
import os
import signal
import threading
import time
import xmlrpc.client
from urllib.parse import urlparse

import psutil
import rosgraph

from ..process_identity import addresses_of, names_itself, node_process_problem
from ..sites import this_host


class _TimeoutTransport(xmlrpc.client.Transport):
    def __init__(self, timeout):
        super(_TimeoutTransport, self).__init__()
        self.timeout = timeout

    def make_connection(self, host):
        connection = super(_TimeoutTransport, self).make_connection(host)
        connection.timeout = self.timeout
        return connection


def node_api(uri, timeout):
    """An XML-RPC proxy to a node's API that gives up after timeout seconds."""
    return xmlrpc.client.ServerProxy(uri, transport=_TimeoutTransport(timeout))


def _here(address, own=()):
    """Whether an address is this host's: loopback, a wildcard (0.0.0.0 reaches this host), or one of
    ``own`` (this host's name resolved); an IPv4-mapped IPv6 address as its IPv4 one."""
    try:
        ip = ipaddress.ip_address(address)
    except ValueError:
        return False
    if ip.version == 6 and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_loopback or ip.is_unspecified or str(ip) in own


def is_local(uri):
    """Whether a URI names this host, however it is spelt (its name, localhost, 127.x, 0.0.0.0,
    ::ffff:127.0.0.1, a number)."""
    try:
        host = urlparse(uri).hostname or ''
    except ValueError:
        return False
    if host in (this_host(), 'localhost') or host.startswith('127.'):
        return True
    own = addresses_of(this_host())
    return any(_here(a, own) for a in addresses_of(host))


class NotTheNode(Exception):
    """The pid a node's XML-RPC API gave is not that node's process (a forged registration)."""


def visible_pid(uri, caller_id, node, timeout=1.0):
    """The pid of node ``node`` at ``uri`` if its process runs on this machine, else None: a node of
    this host, or of an emulated host of this machine (a network name space: its process is here,
    with the URI's address as its ROS_IP or ROS_HOSTNAME). A node of another machine has no process
    here. Raises NotTheNode if a process of this machine is named but is not the node
    (:func:`aft_ftm.process_identity.node_process_problem`): nobody may signal it on that word."""
    code, _, pid = node_api(uri, timeout).getPid(caller_id)
    if code != 1:
        return None
    if not is_local(uri):
        try:
            env = psutil.Process(pid).environ()
        except (psutil.Error, OSError, TypeError, ValueError):
            return None
        if urlparse(uri).hostname not in (env.get('ROS_IP'), env.get('ROS_HOSTNAME')):
            return None
    why = node_process_problem(pid, node, uri)
    if why:
        raise NotTheNode(why)
    return pid


class NamespaceFence(object):
    """The nodes under ``namespace``: learn their pids, kill them, forget them at the master."""

    def __init__(self, namespace, caller_id, timeout=0.5):
        self.prefix = namespace.rstrip('/') + '/'
        self.caller_id = caller_id
        self.timeout = timeout
        self.master = rosgraph.Master(caller_id)
        self.known = {}        # node name -> (pid, create_time) for nodes on this host
        self.remote = {}       # node name -> API uri, for nodes on other hosts
        self.unlearned = []    # nodes under the name space the last learn() could not learn
        self.refused = {}      # node name -> why the pid its API gave is not its process (never signalled)
        self.aliases = []      # names the last shut_down_the_rest did not ask: their URI is another node's
        self.lineage = {}      # node name -> [(pid, create_time)] of its parent, if that is not above this process
        self.uris = {}         # node name -> the API uri its known process was learned at
        self.stale = {}        # node name -> why: its known process died, its registration (same uri) stayed
        self.closing = {}      # node name -> (uri, pid, first seen): a refusal that waits CLOSING_GRACE
        self.clock = time.monotonic
        self.lock = threading.Lock()

    def node_names(self):
        pubs, subs, srvs = self.master.getSystemState()
        names = {n for _, nodes in list(pubs) + list(subs) + list(srvs) for n in nodes}
        return sorted(n for n in names if n.startswith(self.prefix))

    # A node shutting down closes its API before its process ends: asked in between, the pid it gave
    # listens nowhere (a rollback stopping the nodes it launched while a fence learned them raised a false
    # fence_refused). A process whose command line names the node gets this long to be gone before the
    # registration is refused; it is never learned (a launch guard carries its node's command line too).
    CLOSING_GRACE = 2.0

    def learn(self):
        """Ask every node under the name space for its pid. Returns the number of local nodes known;
        ``unlearned`` names the nodes it could not learn this time."""
        unlearned = []
        current = self.node_names()
        with self.lock:   # a refused, remote or learned registration gone from the master is forgotten
            for table in (self.refused, self.remote, self.lineage, self.stale, self.uris, self.closing):
                for name in [n for n in table if n not in current]:
                    del table[name]
        for name in current:
            if name in self.known and self._still(self.known[name]):
                continue
            unlearned.append(name)
            try:
                uri = self.master.lookupNode(name)
                if not is_local(uri):
                    with self.lock:
                        self.remote[name] = uri
                        self.lineage.pop(name, None)
                    unlearned.pop()
                    continue
                code, _, pid = node_api(uri, self.timeout).getPid(self.caller_id)
                if code == 1:
                    why = node_process_problem(pid, name, uri)
                    if why and self.uris.get(name) == uri:
                        # The node learned there died (a power loss: nobody unregistered it), its registration
                        # stayed all along, and its port now reaches another process of this busy host: no
                        # forgery, nothing to signal (``stale``: logged by the caller, no alarm).
                        with self.lock:
                            self.stale[name] = why
                        unlearned.pop()
                        continue
                    if why and self._closing(name, uri, pid):
                        continue   # stays unlearned, asked again soon; nothing refused, nothing learned
                    if why:   # a forged registration: that process is never killed for this name space
                        with self.lock:
                            self.refused[name] = why
                        unlearned.pop()
                        continue
                    created = psutil.Process(pid).create_time()
                    lineage = _lineage(pid)
                    with self.lock:
                        self.known[name] = (pid, created)
                        self.uris[name] = uri
                        self.lineage[name] = lineage
                        self.remote.pop(name, None)
                        self.refused.pop(name, None)
                        self.stale.pop(name, None)
                    unlearned.pop()
            except Exception:   # a node going away while we ask: learned next time, or never needed
                continue
        self.unlearned = unlearned
        return len(self.known)

    def _closing(self, name, uri, pid):
        """Whether the refusal of name (its pid ``pid`` not the node at ``uri``) waits: the process's command
        line names the node, and it was first seen so less than CLOSING_GRACE ago."""
        if not names_itself(pid, name):
            return False
        now = self.clock()
        with self.lock:
            seen = self.closing.get(name)
            if seen is None or seen[:2] != (uri, pid):
                seen = self.closing[name] = (uri, pid, now)
        return now - seen[2] < self.CLOSING_GRACE

    def started(self, pid, created):
        """The name of a node of the name space, learned and still registered, whose parent is the
        process ``pid`` (created at ``created``), or None. Only such a process is the name space's
        launcher (roslaunch starts its nodes itself): a heartbeat or a failure report naming any other
        pid (forged, or a pid reused since; a daemon further up, as sshd or a tmux server) never has its
        process tree killed. A parent above this process too is nobody's launcher."""
        with self.lock:
            lineage = dict(self.lineage)
        for name, above in sorted(lineage.items()):
            if any(p == pid and abs(c - created) < 0.01 for p, c in above):
                return name
        return None

    @staticmethod
    def _still(entry):
        """Whether a learned (pid, create_time) is still that process (a node started again has a new pid)."""
        try:
            return psutil.Process(entry[0]).create_time() == entry[1]
        except psutil.NoSuchProcess:
            return False

    def processes(self):
        """{name: psutil.Process} of every known local node still running as the same process (not this
        one). A psutil.Process checks, before each signal, that its pid was not reused since."""
        with self.lock:
            known = dict(self.known)
        procs = {}
        for name, (pid, created) in sorted(known.items()):
            try:
                proc = psutil.Process(pid)
                if proc.create_time() == created and pid != os.getpid():
                    procs[name] = proc
            except psutil.NoSuchProcess:
                continue
        return procs

    def kill(self):
        """SIGKILL every known local node still running as the same process. Returns their names."""
        killed = []
        for name, proc in sorted(self.processes().items()):
            try:
                proc.send_signal(signal.SIGKILL)
                killed.append(name)
            except psutil.NoSuchProcess:
                continue
        return killed

    def shut_down_the_rest(self):
        """Ask the remaining nodes to shut down, and unregister the dead ones from the master. Not asked:
        a name whose pid was refused, or whose URI is the ROS master's or that of a node outside the name
        space (a forged registration, an alias: the request would reach that other process), or a node
        of this host whose pid is not that node's now. The request names the node it is meant for (a
        node started by run_node ignores one naming another). Returns how many were asked."""
        names = self.node_names()
        if not names:
            return 0
        uris, failed = {}, []
        for name in names:
            try:
                uris[name] = self.master.lookupNode(name)
            except Exception:   # unknown meanwhile, or the master does not answer
                failed.append(name)
        others = set(endpoints(rosgraph.get_master_uri()))
        pubs, subs, srvs = self.master.getSystemState()
        for other in {n for _, nodes in list(pubs) + list(subs) + list(srvs) for n in nodes}:
            if not other.startswith(self.prefix):
                try:
                    others |= endpoints(self.master.lookupNode(other))
                except Exception:
                    continue
        with self.lock:
            refused = set(self.refused)
        self.aliases = sorted(n for n, uri in uris.items() if endpoints(uri) & others or n in refused)
        asked = 0
        for name, uri in sorted(uris.items()):
            if name in self.aliases:
                continue
            try:
                api = node_api(uri, self.timeout)
                if is_local(uri):   # a node of this host is asked only if its pid is that node's
                    code, _, pid = api.getPid(self.caller_id)
                    if code != 1 or node_process_problem(pid, name, uri):
                        continue
                elif _not_a_node(api, self.caller_id):
                    continue
                api.shutdown(self.caller_id, '[%s] Reason: fail-silence of %s' % (
                    name, self.prefix.rstrip('/')))
            except Exception:   # gone, or tearing down while it answered: asked all the same
                pass
            asked += 1
        if failed:   # each registration on its own: one gone meanwhile no longer raises out of the fencing
            from .graph import unregister
            unregister(self.master, failed, uris)
        return asked


def is_launcher(argv):
    """Whether a command line runs a launcher: roslaunch, or aft_ftm's guard around a launch. Only
    such a process is taken for a site's launcher on what /proc says of its children: any process
    that started a node could pass otherwise (the adaptation engine starts guards that carry their
    node's command line: review of session 35)."""
    argv = list(argv or ())
    return 'roslaunch' in {os.path.basename(a) for a in argv[:2]} or (
        '-m' in argv[:3] and 'aft_ftm.ros.guarded_launch' in argv[:4])


def launcher_children(children, prefix):
    """(the nodes of name space ``prefix`` among a launcher's direct children, the others), from
    [(pid, node name or None)] as /proc names them (site_watch.node_name: its command line and
    environment, which a heartbeat cannot forge). A child that names no node counts among the others:
    a launcher's children are its nodes."""
    inside = [(pid, name) for pid, name in children if name and name.startswith(prefix)]
    outside = sorted(name or 'pid %d (no node)' % pid for pid, name in children
                     if not (name and name.startswith(prefix)))
    return inside, outside


def launcher_roots(pid, site, namespace, learned, program, children):
    """What fail-silence does to a launcher ``pid`` a heartbeat named (alive, not reused, not above the
    asker: checked before): (the pids whose process trees are killed, what was decided, refused: whether
    it is nobody's launcher, partial: whether it runs more than the failed site).

    - ``learned``: the node of ``namespace`` learned by pid whose parent it is (NamespaceFence.started),
      or None; ``program``: whether its command line is a launcher's (is_launcher); ``children``:
      launcher_children's split of its direct children.
    - A launcher of the name space (a node learned there, or a launcher program with a child naming
      itself a node there) that runs nothing else has its whole tree killed, learned or not: a site that
      fails before its peer's fence has asked its nodes for their pids (within a second of its start,
      on a busy host) is still silenced, its frozen nodes included (healing.test in CI).
    - One that runs other nodes too (another site, a service of the board) is partial: only its
      nodes of the name space are killed, each with its tree (the caller keeps the launcher stopped, so
      that it starts none of them again).
    - Neither: a forged heartbeat naming any pid; nothing is killed (refused)."""
    inside, outside = children
    if learned is None and not (program and inside):
        return [], ('pid %d, named as the launcher of %s, started no node of %s%s: its process tree is not '
                    'killed' % (pid, site, namespace, '' if program else ' and runs no launcher')), True, False
    if outside:
        return [p for p, _ in inside], ('launcher %d of %s also runs %s: stopped, and only its %d nodes of %s '
                                        'killed' % (pid, site, ', '.join(outside), len(inside), namespace)), \
            False, True
    return [pid], 'launcher %d of %s (it started %s)' % (pid, site, learned or inside[0][1]), False, False


def _lineage(pid):
    """[(pid, create_time)] of the parent of ``pid``, if it is not this process or above it; else []."""
    mine = {p.pid for p in psutil.Process().parents()} | {os.getpid()}
    parent = psutil.Process(pid).parent()
    return [(parent.pid, parent.create_time())] if parent is not None and parent.pid not in mine else []


def endpoints(uri):
    """{(address, port)} of an XML-RPC URI, its host resolved, this host's addresses all as 'here':
    two spellings of one server share one."""
    try:
        parsed = urlparse(uri)
        host, port = parsed.hostname or '', parsed.port
    except ValueError:
        return {(uri, None)}
    own = addresses_of(this_host())
    found = {('here' if _here(a, own) else a, port) for a in addresses_of(host)}
    return found or {(host, port)}


def _not_a_node(api, caller_id):
    """Whether an XML-RPC server answers as a ROS master (getSystemState) or a roslaunch (list_processes):
    both have a shutdown that stops far more than a node."""
    for probe in (lambda: api.getSystemState(caller_id), lambda: api.list_processes()):
        try:
            probe()
            return True
        except xmlrpc.client.Fault:   # no such method: not that kind of server
            continue
        except Exception:   # no answer: asking it to shut down does no harm then
            continue
    return False


def named_launcher(pid, site, namespace, prefix, since_heard, learned=lambda pid, created: None):
    """What fail-silence may do to the launcher ``pid`` that a heartbeat of ``site`` named, on this host:
    (its psutil.Process or None, the pids whose trees are killed, what was decided, refused, partial).

    None, and nothing killed, when it is gone, when its pid was taken by a process started after the
    site was last heard (``since_heard``, seconds on a clock that does not step), or when it is an
    ancestor of the caller (a launcher that also runs the caller). Otherwise launcher_roots decides,
    from ``learned(pid, created)`` (the node of ``namespace`` learned by pid whose parent it is, or
    None), whether its command line is a launcher's, and its direct children as /proc names them.
    Recovery and the board watchdog both ask it: the watchdog killed the tree of whatever pid the
    last heartbeat named, pid 1 (its own ancestor) included (review of session 36)."""
    from ..process_start import started
    from ..recovery import same_process
    from ..site_watch import children_named
    try:
        launcher = psutil.Process(pid)
        created = launcher.create_time()
        start = started(pid)
    except psutil.NoSuchProcess:
        start = None
    if start is None:
        return None, [], 'launcher of %s (pid %d) already gone' % (site, pid), False, False
    if not same_process(time.clock_gettime(time.CLOCK_BOOTTIME) - start, since_heard):
        return None, [], 'pid %d now belongs to another process: not killed' % pid, False, False
    if pid in [p.pid for p in psutil.Process().parents()]:   # a few reads, not a scan of /proc
        return None, [], 'launcher %d also runs this process: only the name space is killed' % pid, False, False
    try:
        program = is_launcher(launcher.cmdline())
    except psutil.Error:
        program = False
    pids, why, refused, partial = launcher_roots(pid, site, namespace, learned(pid, created), program,
                                                 launcher_children(children_named(pid), prefix))
    return launcher, pids, why, refused, partial
