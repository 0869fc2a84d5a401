"""The campaign on emulated hosts (``scripts/campaign --hosts``): every site on a host of its own.

Hosts (:class:`aft_ftm.hosts_exec.Hosts`): ``rosmaster`` (the roscore and the campaign's own ROS
calls), ``witness``, ``master`` and ``slave`` (the replicas, each fenced through the hosts' power
switch), and one host per client, ``clientK``, running the Proxy ``proxyK`` and the client process
``clientK`` (whose history goes to the shared filesystem).

The orchestrator is one process, split between two network namespaces (a network namespace is a
property of each thread on Linux): its main thread, and so every thread rospy starts, enters the
``rosmaster`` host once the hosts are up (the campaign's graph checks, witness status, getPid and
final states cross a real interface, as the clients' do); the hosts' faults (links, rates, power)
are carried out by a thread kept in the root namespace (:class:`RootHosts`), where the links are.
The hosts' power switch serves from threads of the root namespace too.

Pure part: :func:`plan` (the hosts and which site runs on which).
"""
import ctypes
import os
import queue
import threading
import time

from aft_ftm.hosts import FaultError
from aft_ftm.sites import Site, wait_until
from aft_examples.ros.campaign import DETECTION_TIMEOUT, CampaignDeployment, CampaignError, HostsBackend

MASTER_PORT = 11311
CLONE_NEWNET = 0x40000000


def plan(clients):
    """(hosts, host_of): the host names of a campaign with ``clients`` clients and the host of every
    site (proxyK and clientK on host clientK). Raises ValueError for fewer than one client."""
    if not isinstance(clients, int) or clients < 1:
        raise ValueError('at least one client is needed, got %r' % (clients,))
    host_of = {'witness': 'witness', 'master': 'master', 'slave': 'slave'}
    for k in range(1, clients + 1):
        host_of['proxy%d' % k] = host_of['client%d' % k] = 'client%d' % k
    hosts = ('rosmaster', 'witness', 'master', 'slave') + tuple('client%d' % k for k in range(1, clients + 1))
    return hosts, host_of


def enter_namespace(path):
    """Move the calling thread into the network namespace of ``path`` (/run/netns/NAME or
    /proc/self/ns/net). Raises OSError."""
    libc = ctypes.CDLL(None, use_errno=True)
    fd = os.open(path, os.O_RDONLY)
    try:
        if libc.setns(fd, CLONE_NEWNET) != 0:
            errno = ctypes.get_errno()
            raise OSError(errno, 'setns(%s): %s' % (path, os.strerror(errno)))
    finally:
        os.close(fd)


class RootHosts(object):
    """A Hosts whose every method runs in one thread that stays in the root network namespace
    (where the hosts' links are): the campaign's main thread lives in the rosmaster host."""

    def __init__(self, hosts):
        self._hosts = hosts
        self._calls = queue.Queue()
        self._thread = threading.Thread(target=self._serve, name='root-hosts', daemon=True)
        self._thread.start()

    def _serve(self):
        while True:
            item = self._calls.get()
            if item is None:
                return
            function, args, kwargs, box, done = item
            try:
                box['value'] = function(*args, **kwargs)
            except BaseException as e:   # handed back to the caller
                box['error'] = e
            done.set()

    def __getattr__(self, name):
        attribute = getattr(self._hosts, name)
        if not callable(attribute):
            return attribute

        def call(*args, **kwargs):
            if threading.current_thread() is self._thread:
                return attribute(*args, **kwargs)
            box, done = {}, threading.Event()
            self._calls.put((attribute, args, kwargs, box, done))
            if not done.wait(120.0):
                raise CampaignError('hosts.%s did not return within 120 s' % name)
            if 'error' in box:
                raise box['error']
            return box.get('value')
        return call

    def stop(self):
        self._calls.put(None)
        self._thread.join(5.0)


class HostsCampaign(object):
    """The hosts of a campaign, their power switch, the roscore in the rosmaster host, and this
    process's main thread in that host (module docstring). A context manager; on exit the main
    thread returns to the root namespace and everything is removed (even after a failure).
    Raises aft_ftm.hosts.HostsError (e.g. PlatformError: no namespaces here) from __enter__."""

    def __init__(self, clients, log_dir, log=print):
        self.hosts_names, self.host_of = plan(clients)
        self.log_dir = log_dir
        self.log = log
        self.hosts = None
        self.root = None
        self.core = None
        self._root_ns = None

    def __enter__(self):
        from aft_ftm.hosts_exec import Hosts
        os.makedirs(self.log_dir, exist_ok=True)
        hosts = Hosts(list(self.hosts_names), log=self.log).__enter__()
        try:
            self.hosts = hosts
            self.switch = hosts.power_switch()      # its threads in the root namespace
            self.root = RootHosts(hosts)
            self.master_uri = 'http://%s:%d' % (hosts.ip('rosmaster'), MASTER_PORT)
            self.core = self.site('rosmaster', 'rosmaster', ['roscore', '-p', str(MASTER_PORT)]).start()
            self._root_ns = os.open('/proc/self/ns/net', os.O_RDONLY)
            enter_namespace('/run/netns/%s' % hosts.topology.host('rosmaster').namespace)
            os.environ.update(ROS_IP=hosts.ip('rosmaster'), ROS_HOSTNAME=hosts.ip('rosmaster'),
                              ROS_MASTER_URI=self.master_uri)
            import rosgraph
            if not wait_until(lambda: _online(rosgraph), 30.0, 0.1):
                raise CampaignError('the roscore of the rosmaster host did not come up in 30 s (log %s)'
                                    % self.core.log_path)
        except BaseException:
            self.__exit__()
            raise
        return self

    def env(self, host):
        ip = self.hosts.ip(host)
        return dict(os.environ, ROS_IP=ip, ROS_HOSTNAME=ip, ROS_MASTER_URI=self.master_uri)

    def site(self, name, host, argv, log_path=None):
        """A Site (not started) running argv in host. Refused for a host that is off (review of session
        34: a site started there lived on in the old namespace once the host was made again)."""
        if self.hosts.state(host) == 'off':
            raise CampaignError('site %s cannot start on host %s: it is off' % (name, host))
        namespace = self.hosts.topology.host(host).namespace
        return Site(name, ['ip', 'netns', 'exec', namespace] + list(argv), self.env(host),
                    log_path or os.path.join(self.log_dir, '%s.log' % name))

    def backend(self):
        return HostedBackend(self)

    def __exit__(self, *exc):
        if self._root_ns is not None:
            try:
                os.setns(self._root_ns, CLONE_NEWNET) if hasattr(os, 'setns') else \
                    enter_namespace('/proc/%d/fd/%d' % (os.getpid(), self._root_ns))
            finally:
                os.close(self._root_ns)
                self._root_ns = None
        if self.core is not None:
            self.core.power_off()
        if self.root is not None:
            self.root.stop()
        if self.hosts is not None:
            self.hosts.close()
        return False


def _online(rosgraph):
    try:
        return rosgraph.Master('/campaign').is_online()
    except Exception:   # not up yet
        return False


class HostedCampaignDeployment(CampaignDeployment):
    """A CampaignDeployment whose sites run on the campaign's hosts; the replicas fence each other
    through the hosts' power switch; a site whose host is off is relaunched after powering it on."""

    def __init__(self, campaign, log_dir, mechanism='pbr', clients=2, timeout=DETECTION_TIMEOUT, seed=0):
        super(HostedCampaignDeployment, self).__init__(log_dir, mechanism, clients, timeout, seed)
        self.campaign = campaign
        for name in ('master', 'slave'):
            pkg, launch_file, args = self.launch[name]
            self.launch[name] = (pkg, launch_file, dict(args, power_switch='unix:' + campaign.switch.path,
                                                        peer_host=args['peer']))

    def _make_site(self, name, argv, log_path):
        host = self.campaign.host_of[name]
        if self.campaign.root.state(host) == 'off':
            self.campaign.root.power_on(host)
        return self.campaign.site(name, host, argv, log_path)


class HostedBackend(HostsBackend):
    """HostsBackend for a HostsCampaign: faults through the root-namespace thread; a host partitioned
    and meanwhile powered off by the power switch (fenced by the peer's Recovery) stays off, to be
    powered on by the relaunch of its site. The ROS master's death kills the roscore of the rosmaster
    host (not the host: this runner's main thread lives there) and starts it again."""

    offered = HostsBackend.offered + ('master',)

    def __init__(self, campaign):
        super(HostedBackend, self).__init__(campaign.root, campaign.host_of)
        self.campaign = campaign
        self.core = campaign.core   # the ROS master's death: the rosmaster host's roscore killed, started again

    def deployment(self, log_dir, mechanism, clients, seed, timeout=DETECTION_TIMEOUT):
        return HostedCampaignDeployment(self.campaign, log_dir, mechanism, clients, timeout=timeout, seed=seed)

    def _heal(self, *hosts):
        return self._unless_fenced(hosts, lambda: self.hosts.heal(*hosts))

    def _unrate(self, host):
        return self._unless_fenced((host,), lambda: self.hosts.unrate(host))

    def _unless_fenced(self, hosts, action):
        """action(), or 'fenced: ...' if a host of ``hosts`` is off, before it or by the time it is
        refused (review of session 34: the switch powering a host off between the look and the heal
        aborted the campaign with a FaultError). Another refusal is raised (the segment records it)."""
        off = [h for h in hosts if self.hosts.state(h) == 'off']
        if not off:
            try:
                action()
                return ''
            except FaultError:
                off = [h for h in hosts if self.hosts.state(h) == 'off']
                if not off:
                    raise
        return 'fenced: %s powered off by the switch' % ','.join(off)

    def inject(self, fault, deployment, site_of, rng):
        if fault.kind == 'power_loss':
            name = site_of(fault.target)
            host = self.host_of[name]
            start = time.time()
            # if_on: the switch may have powered it off already (review of session 34: that aborted the campaign)
            killed = self.hosts.power_off(host, if_on=True)
            at = self.hosts.powered_off_at.get(host)
            if at is None or at < start:
                return dict(start=start, end=time.time(), proxy_killed=None,
                            what='host %s already off (fenced by the power switch before the fault)' % host)
            return dict(start=at, end=time.time(), proxy_killed=None,
                        what='host %s powered off (link down, %d processes killed)' % (host, len(killed)))
        return super(HostedBackend, self).inject(fault, deployment, site_of, rng)
