"""The campaign (issue 15): the PBR (or LFR) bank with several clients, each through its own Proxy,
under a seeded schedule of faults (aft_examples.schedule), each fault healed and the failed site
re-joined before the next; at the end of each segment the clients' histories and the servers' final
states are checked (aft_examples.history).

Faults reach the deployment through a backend (FaultBackend): ProcessBackend injects those of one
host (signals to nodes found through the master's getPid, a site's process tree, its power loss);
HostsBackend adds the host-level ones (link down, partitions, rate limits) through
aft_ftm.hosts_exec.Hosts, for a deployment whose sites run on emulated hosts.
"""
import os
import signal
import threading
import time

import psutil
import rosgraph

from aft_ftm.hosts import FaultError
from aft_ftm.ros.deadline import Deadline
from aft_ftm.ros.fencing import node_api
from aft_ftm.ros.graph import clean_dead_nodes, master_answers, roslaunch, wait_for_graph
from aft_ftm.sites import Site, power_off_sites, power_off_trees, process_tree, wait_until
from aft_examples import history, schedule, suspicions
from aft_examples.ros.deployment import replica_services, witness_status

REPLICAS = ('master', 'slave')
CALL_TIMEOUT = 30.0     # a Proxy gives a call up after this long ("outcome UNKNOWN": a violation)
HEAL_TIMEOUT = 90.0     # the pair whole again within this, or the fault is 'unhealed'
JOIN_PATIENCE = 30.0
DETECTION_TIMEOUT = 0.03   # the crash detectors' (the product's default: aft_ftm.detector.DEFAULT_TIMEOUT)
INNER_NODES = ('protocol', 'before', 'proceed', 'after')   # the graph of a mechanism nested in Proceed
GUARD_SETTLE = 1.5         # a node an adaptation started, killed: its site fails within this (its guard)
MASTER_PATIENCE = 30.0     # a roscore started again answers within this
SETTLE = 0.3            # after a fault, before looking whether the deployment is whole    # a running replica site not joined after this is powered off and relaunched


def client_seed(seed, k):
    """Client k's seed in a segment of seed: a ROS parameter, so an XML-RPC int (under 2**31): a
    segment's seed (the schedule's seed * 1000 + its number) times 100 is past it from seed 21475 on,
    and the client died at init_node ("int exceeds XML-RPC limits"), serving nothing."""
    return (seed * 100 + k) % (2 ** 31 - 1)


class CampaignError(RuntimeError):
    """The campaign could not run (a deployment that does not start, a fault that cannot be injected)."""


def _pid_of(node, caller='/campaign', timeout=1.0):
    """The pid of a running node, asked through its XML-RPC API (None if it does not answer)."""
    try:
        uri = rosgraph.Master(caller).lookupNode(node)
        code, _, pid = node_api(uri, timeout).getPid(caller)
        return pid if code == 1 else None
    except Exception:   # not registered, or not answering (dead, frozen)
        return None


def _signal(pids, sig):
    for pid in pids:
        try:
            os.kill(pid, sig)
        except (ProcessLookupError, PermissionError):
            pass


CHUNK_BYTES = 16   # PBR After ~chunk_bytes in the campaign's replica sites (aft_ftm.transfer)


class CampaignDeployment(object):
    """The sites of a campaign segment, each its own roslaunch process tree: the witness (its record
    in a state file, so that it may be killed and restarted), the replicas MASTER and SLAVE, and per
    client a Proxy site (proxyK offering /accountK) and the client process (clientK)."""

    def __init__(self, log_dir, mechanism='pbr', clients=2, timeout=DETECTION_TIMEOUT, seed=0, env=None,
                 adaptable=False):
        if clients < 1:
            raise CampaignError('at least one client is needed, got %d' % clients)
        self.log_dir = log_dir
        self.engine = None    # the adaptation engine of an adaptable deployment (AdaptingBackend)
        # What the pair runs now, which adaptations change and a re-joining site must come back with:
        self.mechanism = mechanism   # pbr or lfr (a switch toggles it)
        self.inner = ''              # the mechanism standing in for Proceed ('' or tr: compose, decompose)
        self.suffix = {}      # (replica site, 'before' or 'after') -> suffix of that node, once replaced
        # Site name -> the nodes of its roslaunch an adaptation killed: their deaths (SIGKILL, when a
        # SIGINT was not enough) are no failure of the site (seed 36054: two sites taken for down
        # and relaunched, the new primary among them, and its state lost with it).
        self.retired = {}
        self.server_timeout = 1.0
        self.clients = clients
        self.env = env
        self.stop_file = os.path.join(log_dir, 'stop')
        self.launch = {
            'witness': ('aft_ftm', 'witness.launch', dict(state_file=os.path.join(log_dir, 'witness.state'))),
        }
        # A re-join's state transfer goes in parts of 16 bytes (4 per join: the bank's state is about 60
        # bytes), each acknowledged before more go: the faults drawn also hit transfers in parts.
        replica = dict(timeout=timeout, server_timeout=self.server_timeout, chunk_bytes=CHUNK_BYTES)
        if adaptable:
            replica['adaptable'] = 'true'   # Before, Proceed and After replaceable while the site serves
        if mechanism != 'pbr':
            replica['mechanism'] = mechanism
        for name, peer, role in (('master', 'slave', 'primary'), ('slave', 'master', 'backup')):
            self.launch[name] = ('aft_examples', 'demo_replica_site.launch', dict(replica, site=name, peer=peer,
                                                                                  role=role))
        for k in range(1, clients + 1):
            self.launch['proxy%d' % k] = ('aft_ftm', 'proxy.launch', dict(
                service='/account%d' % k, service_type='aft_msgs/Account', witness='false', name='proxy%d' % k,
                timeout=CALL_TIMEOUT))
        self.client_argv = {'client%d' % k: [
            'rosrun', 'aft_examples', 'campaign_client', '__name:=client%d' % k, 'account:=/account%d' % k,
            '_history:=%s' % self.history_path(k), '_stop_file:=%s' % self.stop_file, '_seed:=%d' % client_seed(seed, k)]
            for k in range(1, clients + 1)}
        self.sites = {}
        self.starts = {}

    def node(self, site, name):
        """The graph name of a replica site's node now ('after' is 'after_v2' once updated,
        'before' 'before_lfr3' once switched; 'tr/before': a node of the mechanism nested in Proceed)."""
        return '/%s/%s%s' % (site, name, self.suffix.get((site, name), ''))

    def shape(self):
        """What the pair runs now, in words: 'pbr', 'lfr+tr', ..."""
        return self.mechanism + ('+' + self.inner if self.inner else '')

    def shape_problem(self, site, master):
        """Why replica site does not run what the pair runs now (a re-joined site that came back
        with another mechanism than its peer's), or None. master: a rosgraph.Master."""
        after = self.node(site, 'after')
        try:
            mechanism = master.getParam(after + '/mechanism')
        except Exception as e:   # its parameters not set: not launched as expected
            return '%s has no mechanism parameter (%s)' % (after, e)
        if mechanism != self.mechanism:
            return '%s runs %s, the pair %s' % (after, mechanism, self.shape())
        proceed = '/%s/%s/protocol/rebind' % (site, self.inner) if self.inner else '/%s/proceed/rebind' % site
        try:
            master.lookupService(proceed)
        except Exception:
            return '%s is not offered: %s does not run %s' % (proceed, site, self.shape())
        return None

    def started_by_engine(self, node):
        """Whether node was started by an adaptation (its launch's guard fails its site if it dies)."""
        return self.engine is not None and any(launched.alive() and node in launched.nodes
                                               for launched in self.engine.sites)

    def launched_of(self, site):
        """The pids of the launches an adaptation started into site (their nodes are the site's,
        though not in its launcher's process tree)."""
        if self.engine is None:
            return []
        return [launched.pid for launched in self.engine.sites if launched.alive()
                and launched.nodes and all(n.startswith('/%s/' % site) for n in launched.nodes)]

    def history_path(self, k):
        return os.path.join(self.log_dir, 'client%d.history' % k)

    def _site(self, name):
        """Site ``name`` (not started), its log numbered by how often it was started."""
        if name in self.client_argv:
            argv = self.client_argv[name]
        else:
            pkg, launch_file, args = self.launch[name]
            argv = roslaunch(pkg, launch_file, **args)
        self.starts[name] = self.starts.get(name, 0) + 1
        return self._make_site(name, argv, os.path.join(self.log_dir, '%s.%d.log' % (name, self.starts[name])))

    def _make_site(self, name, argv, log_path):
        return Site(name, argv, self.env, log_path)

    def start(self, timeout=120.0):
        os.makedirs(self.log_dir, exist_ok=True)
        clean_dead_nodes()
        started = time.monotonic()
        for name in ('witness', 'master', 'slave'):
            self.sites[name] = self._site(name).start()
        left = lambda: timeout - (time.monotonic() - started)   # noqa: E731
        for name in REPLICAS:
            missing = wait_for_graph(replica_services(name), timeout=left(), abort=self._exited)
            if missing:
                raise CampaignError('replica %s did not come up: missing %s (logs in %s)'
                                    % (name, ', '.join(missing)[:300], self.log_dir))
        if not wait_until(lambda: (witness_status() or _Status).backup, max(5.0, left()), 0.05):
            raise CampaignError('the pair did not form: witness %s (logs in %s)' % (witness_status(), self.log_dir))
        for k in range(1, self.clients + 1):
            self.sites['proxy%d' % k] = self._site('proxy%d' % k).start()
        missing = wait_for_graph(['/account%d' % k for k in range(1, self.clients + 1)], timeout=max(5.0, left()),
                                 abort=self._exited)
        if missing:
            raise CampaignError('Proxies did not come up: missing %s (logs in %s)' % (missing, self.log_dir))
        clients_started = time.time()
        for name in sorted(self.client_argv):
            self.sites[name] = self._site(name).start()
        # Up only once each client runs its calls (it writes its first call's start to its history): a
        # fault drawn at once (the ROS master killed) found both clients in rospy's init_node, which
        # cannot survive a master that does not answer: they died, their histories empty, and the
        # segment's check counted 4 violations (the 1000-fault run of session 35, segment 18).
        histories = [self.history_path(k) for k in range(1, self.clients + 1)]

        def written(path):   # since the clients started (a replay into the same directory appends)
            try:
                return os.stat(path).st_mtime >= clients_started - 0.01
            except OSError:
                return False
        wait_until(lambda: all(written(path) for path in histories) or self._exited(), max(5.0, left()), 0.05)
        why = self._exited()
        missing = [path for path in histories if not written(path)]
        if why or missing:
            raise CampaignError('clients did not start: %s (logs in %s)' % (why or 'no history %s' % missing,
                                                                          self.log_dir))
        return time.monotonic() - started

    def _exited(self):
        for name, site in sorted(self.sites.items()):
            why = site.failure()
            if why:
                return why + ' while starting'
        return None

    def relaunch(self, name):
        """Start site name again; a replica comes back as a backup and joins the primary by itself."""
        old = self.sites.get(name)
        if old is not None:
            old.stop(grace=1.0)
        clean_dead_nodes('/campaign')
        if name in REPLICAS:
            self.comes_back(name)
        self.retired.pop(name, None)
        self.sites[name] = self._site(name).start()
        return self.sites[name]

    def retire(self, node):
        """node (a graph name: /site/name) was killed on purpose by an adaptation."""
        self.retired.setdefault(node.split('/')[1], set()).add(node)

    def comes_back(self, name):
        """Replica name is launched again: as a backup, with the launch file's node names, running
        what the pair runs now (it re-joins its peer, which may have been switched or composed)."""
        for key in [key for key in self.suffix if key[0] == name]:
            del self.suffix[key]
        pkg, launch_file, args = self.launch[name]
        self.launch[name] = (pkg, launch_file, dict(args, role='backup', mechanism=self.mechanism, inner=self.inner))

    def stop_clients(self, timeout=CALL_TIMEOUT + 10.0):
        """Ask the clients to stop after their call in flight; those still running after timeout are
        killed (their last call is then unfinished). Returns the names killed."""
        with open(self.stop_file, 'w'):
            pass
        clients = [self.sites[name] for name in sorted(self.client_argv) if name in self.sites]
        wait_until(lambda: not any(site.alive() for site in clients), timeout, 0.05)
        killed = [site.name for site in clients if site.alive()]
        power_off_sites([site for site in clients if site.alive()])
        return killed

    def teardown(self):
        power_off_sites(list(self.sites.values()))
        if self.engine is not None:
            self.engine.stop_all()
        clean_dead_nodes('/campaign')


class _Status(object):
    epoch, primary, backup = 0, '', ''


class FaultBackend(object):
    """Injects a fault of the schedule into a deployment. ``offered`` names what it can inject
    (aft_examples.schedule.NEEDS). inject() returns when the fault itself is over (a freeze thawed, a
    partition healed, a node killed); healing what it broke (re-joins, restarts) is the runner's."""
    offered = ()

    def inject(self, fault, deployment, site_of, rng):
        """Inject fault; site_of(role) -> site name now. Returns a dict: start (wall clock), end, what
        (the processes or links hit, in words), proxy_killed (the client whose Proxy died, or None)."""
        raise NotImplementedError

    def deployment(self, log_dir, mechanism, clients, seed, timeout=DETECTION_TIMEOUT):
        """The deployment a segment runs (the sites of one host by default); timeout: the crash
        detectors'."""
        return CampaignDeployment(log_dir, mechanism, clients, timeout=timeout, seed=seed)


class ProcessBackend(FaultBackend):
    """The faults of one host: signals to processes (nodes found through the master's getPid, sites
    by their process trees), and, given the campaign's roscore (``core``, an aft_ftm.sites.Site),
    the ROS master's death: its whole roscore killed, down for the fault's duration, started again
    on its port; the nodes register again by themselves (aft_ftm.ros.rejoin)."""
    offered = ('process', 'master')

    def __init__(self, core=None):
        self.core = core

    def _node(self, fault, site_of, rng, deployment):
        target = fault.target
        if target == 'proxy':
            k = rng.randint(1, deployment.clients)
            return '/proxy%d' % k, 'client%d' % k
        if target == 'witness':
            return '/aft/witness', None
        role, _, node = target.partition('/')
        if node == 'proceed' and deployment.inner:   # composed: a node of the graph standing in for it
            node = '%s/%s' % (deployment.inner, rng.choice(INNER_NODES))
        return deployment.node(site_of(role), node), None

    def kill_master(self, fault):
        if getattr(self, 'core', None) is None:
            raise CampaignError('fault %d: the campaign has no roscore of its own to kill' % fault.index)
        start = time.time()
        count = self.core.power_off()
        time.sleep(fault.duration)
        self.core.start()
        if not wait_until(lambda: master_answers(2.0, '/campaign')[0], MASTER_PATIENCE, 0.05):
            raise CampaignError('fault %d: the roscore started again did not answer within %.0f s (log %s)'
                                % (fault.index, MASTER_PATIENCE, self.core.log_path))
        return dict(start=start, end=time.time(), proxy_killed=None,
                    what='the ROS master killed (%d processes), down %.2f s, started again on its port'
                    % (count, fault.duration))

    def inject(self, fault, deployment, site_of, rng):
        kind = fault.kind
        if (kind, fault.target) == ('kill', 'ros_master'):
            return self.kill_master(fault)
        if kind in ('kill', 'freeze_node'):
            node, client = self._node(fault, site_of, rng, deployment)
            pid = _pid_of(node)
            if pid is None:
                raise CampaignError('fault %d: node %s has no pid (not running?)' % (fault.index, node))
            guarded = deployment.started_by_engine(node)
            start = time.time()
            if kind == 'kill':
                _signal([pid], signal.SIGKILL)
                signalled = time.time()
                if guarded:
                    # A node an adaptation started fails its site through its guard: its roslaunch
                    # notices the death, exits, and the guard fail-stops the site.
                    time.sleep(GUARD_SETTLE)
                return dict(start=start, end=time.time(), signalled=signalled, what='%s (pid %d) killed' % (node, pid),
                            proxy_killed=client)
            _signal([pid], signal.SIGSTOP)
            time.sleep(fault.duration)
            _signal([pid], signal.SIGCONT)
            return dict(start=start, end=time.time(), what='%s (pid %d) frozen %.2f s' % (node, pid, fault.duration),
                        proxy_killed=None)
        if kind in ('freeze_site', 'power_loss'):
            name = site_of(fault.target)
            site = deployment.sites[name]
            if not site.alive():
                raise CampaignError('fault %d: site %s is not running' % (fault.index, name))
            launched = deployment.launched_of(name)
            if kind == 'power_loss':
                start = time.time()
                count = power_off_trees([site.pid] + launched,
                                        on_stopped=lambda: setattr(site, 'powered_off_at', time.time()))
                site.proc.wait()
                # From the power-off's start (its first SIGSTOP; every process stopped at stopped_at):
                # detection times measured from it are upper bounds.
                return dict(start=start, end=time.time(), stopped_at=site.powered_off_at,
                            what='site %s powered off (%d processes)' % (name, count), proxy_killed=None)
            tree = [p.pid for pid in [site.pid] + launched for p in process_tree(pid)]
            start = time.time()
            _signal(tree, signal.SIGSTOP)
            time.sleep(fault.duration)
            _signal(tree, signal.SIGCONT)
            return dict(start=start, end=time.time(), what='site %s frozen %.2f s (%d processes)'
                        % (name, fault.duration, len(tree)), proxy_killed=None)
        raise CampaignError('fault %d: %s is not a fault of one host (offered: %s)'
                            % (fault.index, kind, ', '.join(self.offered)))


class AdaptingBackend(ProcessBackend):
    """The faults of one host, plus adaptations of adaptable sites by the adaptation engine
    (aft_ftm.ros.adaptation_engine), under load, in the prepared order:
    - update: the primary's After (PBR, or LFR leader's) replaced by a new version (update_after.yaml);
    - switch: PBR <-> LFR on both replicas (switch.yaml);
    - compose: TR stands in for each replica's Proceed (compose.yaml), or, where it already does, a
      plain Proceed again (decompose.yaml).
    The deployment keeps what the pair runs now: a site that fails afterwards comes back with that
    mechanism (its launch file's node names), and heal() checks that it does. The engine's
    replacement nodes belong to their site (a power loss kills them, a freeze stops them, and the
    site fail-stops if one dies)."""
    offered = ('process', 'master', 'adapt', 'adapt_mechanism')

    def deployment(self, log_dir, mechanism, clients, seed, timeout=DETECTION_TIMEOUT):
        return CampaignDeployment(log_dir, mechanism, clients, timeout=timeout, seed=seed, adaptable=True)

    def inject(self, fault, deployment, site_of, rng):
        if fault.kind != 'adapt':
            return super(AdaptingBackend, self).inject(fault, deployment, site_of, rng)
        from aft_ftm.errors import AftError
        from aft_ftm.ros.adapt_command import load_script
        from aft_ftm.ros.adaptation_engine import Engine
        primary, backup = site_of('primary'), site_of('backup')
        if not primary or not backup:
            raise CampaignError('fault %d: no pair to adapt (primary %r, backup %r)' % (fault.index, primary, backup))
        plan = adaptation_plan(fault, deployment, primary, backup)
        if deployment.engine is None:
            log_dir = os.path.join(deployment.log_dir, 'adapt')
            os.makedirs(log_dir, exist_ok=True)
            deployment.engine = Engine(log=_appender(os.path.join(log_dir, 'engine.log')), log_dir=log_dir)
        start = time.time()
        try:
            report = deployment.engine.run(load_script(plan.script, plan.overrides), 'prepared')
        except AftError as e:   # refused before anything changed (a script the graph does not allow now)
            raise CampaignError('fault %d: %s refused: %s' % (fault.index, plan.what, e))
        for step in report['steps']:
            if step['action'] == 'kill' and step['ok']:   # killed even if rolled back (respawned elsewhere)
                deployment.retire(step['target'])
        if report['ok']:
            plan.apply(deployment)
        return dict(start=start, end=time.time(), proxy_killed=None, adapted=bool(report['ok']),
                    what='%s: %s (pause %.1f ms)' % (
                        plan.what, 'done' if report['ok'] else 'rolled back: %s' % report['error'],
                        (report.get('pause_s') or 0.0) * 1e3))


def _appender(path):
    """A log function that appends each line, stamped, to path (the engine's warnings and steps)."""
    def log(text):
        with open(path, 'a') as f:
            f.write('%.3f %s\n' % (time.time(), text))
    return log


class Plan(object):
    """One adaptation of the campaign: the script (a name of aft_ftm/adaptations), its arguments,
    what it is in words, and apply(deployment): the deployment's record of what the pair runs,
    changed once the adaptation is done."""

    def __init__(self, script, overrides, what, apply):
        self.script, self.overrides, self.what, self.apply = script, overrides, what, apply


def adaptation_plan(fault, deployment, primary, backup):
    """The adaptation fault (target update, switch or compose) stands for, given what the pair runs
    now (deployment.mechanism, .inner, .suffix). Raises CampaignError for an adaptation not offered. No ROS."""
    index, suffix = fault.index, deployment.suffix
    if fault.target == 'update':
        old, new = suffix.get((primary, 'after'), ''), '_v%d' % (index + 2)

        def apply(d):
            d.suffix[(primary, 'after')] = new
        # An LFR leader's new After drives the Before that runs (it did not start one of its own).
        before = 'before%s' % suffix.get((primary, 'before'), '')
        return Plan('update_after', ['site:=%s' % primary, 'peer:=%s' % backup, 'old:=%s' % old, 'new:=%s' % new,
                                     'mechanism:=%s' % deployment.mechanism, 'before:=%s' % before],
                    'update of %s/after%s to after%s (%s)' % (primary, old, new, deployment.mechanism), apply)
    if fault.target == 'switch':
        to = 'lfr' if deployment.mechanism == 'pbr' else 'pbr'
        new = '_%s%d' % (to, index)
        olds = ['%s_%s_old:=%s' % (role, stage, suffix.get((site, stage), ''))
                for role, site in (('primary', primary), ('backup', backup)) for stage in ('before', 'after')]

        def apply(d):
            d.mechanism = to
            for site in (primary, backup):
                for stage in ('before', 'after'):
                    d.suffix[(site, stage)] = new
        return Plan('switch', ['to:=%s' % to, 'new:=%s' % new, 'primary:=%s' % primary, 'backup:=%s' % backup] + olds,
                    'switch %s -> %s' % (deployment.mechanism, to), apply)
    if fault.target == 'compose':
        sites = 'site:=%s,%s' % (primary, backup)
        timeout = 'server_timeout:=%s' % deployment.server_timeout
        if deployment.inner:
            inner = deployment.inner

            def apply(d):
                d.inner = ''
            return Plan('decompose', [sites, 'mechanism:=%s' % inner, timeout],
                        'decompose %s+%s -> %s' % (deployment.mechanism, inner, deployment.mechanism), apply)

        def apply(d):
            d.inner = 'tr'
        return Plan('compose', [sites, 'mechanism:=tr', timeout],
                    'compose %s -> %s+tr' % (deployment.mechanism, deployment.mechanism), apply)
    raise CampaignError('fault %d: adaptation %s is not offered (offered: update, switch, compose)'
                        % (index, fault.target))


class HostsBackend(ProcessBackend):
    """The process faults, plus those of emulated hosts (aft_ftm.hosts_exec.Hosts): a host's power loss
    by its link down first, partitions of a host or a pair and their healing, rate limits.

    hosts: an entered Hosts; host_of: {site name: host name} for the deployment's sites, e.g. the
    hosted PBR deployment's (branch wt_hostsites), which places every site on a host of its own.
    """
    offered = ('process', 'hosts')
    RATE_KBIT = 200

    def __init__(self, hosts, host_of):
        self.hosts = hosts
        self.host_of = dict(host_of)

    def _host(self, role, site_of, rng):
        if role == 'client':   # one of the client hosts
            clients = sorted(name for name in self.host_of if name.startswith('proxy'))
            return self.host_of[clients[rng.randrange(len(clients))]]
        if role == 'witness':
            return self.host_of['witness']
        return self.host_of[site_of(role)]

    def inject(self, fault, deployment, site_of, rng):
        kind = fault.kind
        if kind == 'power_loss':
            name = site_of(fault.target)
            start = time.time()
            self.hosts.power_off(self.host_of[name])
            return dict(start=start, end=time.time(), what='host %s powered off' % self.host_of[name],
                        proxy_killed=None)
        if kind in ('partition', 'partition_pair'):
            ends = fault.target.split('-')
            hosts = [self._host(role, site_of, rng) for role in ends]
            start = time.time()
            self.hosts.partition(*hosts)
            time.sleep(fault.duration)
            fenced = self._heal(*hosts)
            return dict(start=start, end=time.time(), what='%s cut %.2f s%s' % (
                '|'.join(hosts), fault.duration, ' (%s)' % fenced if fenced else ''), proxy_killed=None)
        if kind == 'bandwidth':
            host = self._host(fault.target, site_of, rng)
            start = time.time()
            self.hosts.rate(host, self.RATE_KBIT)
            time.sleep(fault.duration)
            unrated = self._unrate(host)
            return dict(start=start, end=time.time(), what='%s at %d kbit/s %.2f s%s' % (
                host, self.RATE_KBIT, fault.duration, ' (%s)' % unrated if unrated else ''),
                        proxy_killed=None)
        return super(HostsBackend, self).inject(fault, deployment, site_of, rng)

    def _heal(self, *hosts):
        """Heal a partition; returns what else was found ('' here)."""
        self.hosts.heal(*hosts)
        return ''

    def _unrate(self, host):
        self.hosts.unrate(host)
        return ''


def _down(deployment, name):
    """Why a site is down (its roslaunch exited, or a node of it died, other than one an adaptation
    retired: a Proxy is not required by its roslaunch, which then lives on without it), or None."""
    site = deployment.sites[name]
    return site.failure(deployment.retired.get(name, ())) if site.proc is not None else 'never started'


def whole(deployment):
    """Why the deployment is not whole yet (a site down, the pair not formed, a replica that runs
    another mechanism than the pair), or None."""
    for name, site in sorted(deployment.sites.items()):
        why = None if name.startswith('client') else _down(deployment, name)
        if why:
            return why
    status = witness_status()
    if status is None:
        return 'the witness does not answer'
    if not status.primary or not status.backup:
        return 'the pair is not whole (epoch %d, primary %r, backup %r)' % (status.epoch, status.primary,
                                                                            status.backup)
    master = rosgraph.Master('/campaign')
    for name in (status.primary, status.backup):
        why = deployment.shape_problem(name, master)
        if why:
            return why
    for name in sorted(deployment.sites):
        if name.startswith('proxy'):   # a relaunched Proxy up, not only its roslaunch (seed 2411, fault 92:
            service = '/account%s' % name[len('proxy'):]   # the master killed between them; no fault then)
            try:
                master.lookupService(service)
            except Exception:
                return '%s does not offer %s yet' % (name, service)
    return None


def heal(deployment, log=print, fail_stopped=None, acted=None):
    """Bring the deployment back whole: relaunch every site that is down (a replica re-joins as the
    backup), power off and relaunch a replica that runs but does not join: at once if it said it
    fail-stopped since it was started (fail_stopped: {site name: monotonic time a fail_stop alarm
    named it}, filled as they are heard; a fail-stopped backup is nobody's to fence, its launcher
    lives on), else after JOIN_PATIENCE. The wall-clock time of each of those actions is appended to
    acted (a list), so that what the fault cost the clients can be told from what its repair (a
    relaunch, the re-join's state transfer) cost them. Returns (what was done, None) once whole, or
    (what was done, why not) after HEAL_TIMEOUT."""
    fail_stopped = {} if fail_stopped is None else fail_stopped
    acted = [] if acted is None else acted
    started_at = {}
    done = []
    started = time.monotonic()
    waiting_since = {}
    time.sleep(SETTLE)   # a detection, a roslaunch seeing its node die
    steady = 0
    while True:
        why = whole(deployment)
        steady = steady + 1 if why is None else 0
        if steady >= 3:   # whole on three looks 0.05 s apart: not a site on its way down
            return done, None
        if time.monotonic() - started > HEAL_TIMEOUT:
            return done, why
        for name, site in sorted(deployment.sites.items()):
            if name.startswith('client'):
                continue
            if _down(deployment, name):
                started_at[name] = time.monotonic()
                acted.append(time.time())
                deployment.relaunch(name)
                done.append('%s relaunched' % name)
                waiting_since[name] = time.monotonic()
        status = witness_status()
        if status is None:
            # The master or the witness does not answer: whom it names is unknown, and a site powered
            # off on that guess could be the one holding the state (seed 15 segment 20, in a stall).
            # A joiner's patience starts again once it can be asked.
            waiting_since.clear()
            time.sleep(0.05)
            continue
        for name in REPLICAS:
            if name in (status.primary, status.backup):
                waiting_since.pop(name, None)
                continue
            since = waiting_since.setdefault(name, time.monotonic())
            if fail_stopped.get(name, -1.0) > started_at.get(name, 0.0) and deployment.sites[name].alive():
                started_at[name] = time.monotonic()
                acted.append(time.time())
                deployment.sites[name].power_off()
                done.append('%s fail-stopped, relaunched' % name)
            elif time.monotonic() - since > JOIN_PATIENCE and deployment.sites[name].alive():
                log('%s runs but did not join in %.0f s: powered off, relaunched' % (name, JOIN_PATIENCE))
                acted.append(time.time())
                deployment.sites[name].power_off()
                done.append('%s stuck, relaunched' % name)
        time.sleep(0.05)


def final_states(deployment, settle=5.0, quiet=1.0):
    """The (balance, count, digest) of every replica in the pair, once they agree and stay the same for
    ``quiet`` s (or after settle s)."""
    import rospy
    from aft_msgs.srv import GetState
    from aft_examples.bank import Account

    def states():
        status = witness_status()
        if status is None:   # no pair known: unreadable, never "no servers" (an empty list checks nothing)
            return [('unreadable: the witness did not answer', -1, '')]
        found = []
        for name in (status.primary, status.backup):
            if not name:
                continue
            try:
                data = _STATE_CALLS.call(rospy.ServiceProxy('/%s/bank_server/get_state' % name, GetState), 5.0).state
                model = Account()
                model.set_state(data)
                found.append(model.snapshot())
            except Exception as e:   # reported: a final state that cannot be read is no pass
                found.append(('unreadable: %s' % e, -1, ''))
        return found
    got = []
    deadline = time.monotonic() + settle
    while True:
        wait_until(lambda: got.append(states()) or (len(set(got[-1])) == 1 and got[-1][0][1] != -1),
                   max(0.1, deadline - time.monotonic()), 0.1)
        # Quiescent: the same state a little later (a late copy of a request, resent or queued, that
        # executes after the agreement would otherwise go unseen by the checker).
        time.sleep(quiet)
        again = states()
        if again == got[-1] or time.monotonic() >= deadline:
            return again   # (still changing past settle: the latest read, which the checker judges)
        got.append(again)


_STATE_CALLS = Deadline('final-state', exclusive=True)   # a hung server: 'unreadable', never a hung campaign


class Segment(object):
    """One deployment's share of the schedule, run and checked."""
    START_TRIES = 3   # fresh deployments at most to start a segment

    def __init__(self, faults, log_dir, backend, clients=2, seed=0, log=print, progress=None,
                 timeout=DETECTION_TIMEOUT):
        self.faults = faults
        self.log_dir = log_dir
        self.backend = backend
        self.clients = clients
        self.seed = seed
        self.log = log
        self.progress = progress or (lambda record: None)
        self.records = []
        self.kills = {}
        self.alarms = []   # (kind, detail) of every aft_msgs/Alarm heard on /aft/alarms
        self.rejoins = []   # (wall clock, site) of every re-join a crash detector announced
        self.heard_again = []   # (wall clock, site, detail) of every peer_back alarm: a failed site heard again
        self.fail_stopped = {}   # replica site -> when a fail_stop alarm last named it (monotonic)
        self.verdicts = []   # suspicions.Verdict: every crash detector's verdict heard
        self.timeout = timeout
        self.skipped = 0   # faults not run: an earlier one left the deployment unhealed

    def run(self):
        import rospy
        from aft_msgs.msg import Alarm, Failure
        heard = [rospy.Subscriber('/aft/alarms', Alarm, self._alarm)]
        for site in REPLICAS:
            heard.append(rospy.Subscriber('/%s/failures' % site, Failure, self._verdict, callback_args=site,
                                          queue_size=None))
        try:
            return self._run()
        finally:
            for subscriber in heard:
                subscriber.unregister()

    def _alarm(self, alarm):
        self.alarms.append((alarm.kind, alarm.detail))
        joined = suspicions.rejoin_of(alarm.kind, alarm.detail)
        if joined:
            self.rejoins.append((alarm.stamp.to_sec() or time.time(), joined))   # the detector's clock, as verdicts
        back = suspicions.heard_again_of(alarm.kind, alarm.detail)
        if back:
            self.heard_again.append((alarm.stamp.to_sec() or time.time(), back, alarm.detail))
        if alarm.kind == 'fail_stop':   # the crash detector's 'site NAME stops heartbeating: why'
            words = alarm.detail.split()
            if len(words) > 1 and words[0] == 'site' and words[1] in REPLICAS:
                self.fail_stopped[words[1]] = time.monotonic()

    def _verdict(self, failure, reporter):
        self.verdicts.append(suspicions.Verdict(failure.detected.to_sec(), reporter, failure.site, failure.reason))

    SETTLE_BUSY, SETTLE_LIMIT = 50.0, 20.0   # CPU % over a second, and the longest wait (s)

    def _settle(self):
        """Before a new start: wait (at most SETTLE_LIMIT s) until the machine's CPU use over a second falls
        below SETTLE_BUSY %: a start under the load a teardown (or the step before) leaves is what failed."""
        import psutil
        end = time.monotonic() + self.SETTLE_LIMIT
        busy = psutil.cpu_percent(interval=1.0)
        while busy >= self.SETTLE_BUSY and time.monotonic() < end:
            busy = psutil.cpu_percent(interval=1.0)
        self.log('segment %d: CPU %.0f %% before the new start' % (self.faults[0].segment, busy))

    def alarm_counts(self):
        counts = {}
        for kind, _ in self.alarms:
            counts[kind] = counts.get(kind, 0) + 1
        return counts

    def _run(self):
        mechanism = self.faults[0].mechanism
        deployment = self.backend.deployment(self.log_dir, mechanism, self.clients, self.seed, self.timeout)
        rng = __import__('random').Random(self.seed * 7919 + self.faults[0].index)
        try:
            # A start can fail under load: a 30 ms detector suspects a peer still starting, and the witness
            # deposes a site before the clients are up (a clean-clone CI, session 46: twice in a row). Each
            # new start is a fresh deployment, at most START_TRIES in all, each said.
            for attempt in range(1, self.START_TRIES + 1):
                try:
                    deployment.start()
                    break
                except CampaignError as e:
                    if attempt == self.START_TRIES:
                        raise
                    self.log('segment %d: start %d of %d failed, starting afresh: %s' % (
                        self.faults[0].segment, attempt, self.START_TRIES, e))
                    deployment.teardown()
                    self._settle()
                    deployment = self.backend.deployment('%s.%d' % (self.log_dir, attempt + 1), mechanism,
                                                         self.clients, self.seed, self.timeout)
            self.began = time.time()
            for fault in self.faults:
                self.records.append(self._one(fault, deployment, rng))
                self.progress(self.records[-1])
                if self.records[-1]['outcome'].startswith('unhealed'):
                    # Never a fault on a deployment that is not whole: a second replica down loses the
                    # state (the witness then rightly refuses to serve). The segment ends here.
                    self.skipped = len(self.faults) - len(self.records)
                    self.log('segment %d: fault %d left the deployment unhealed; its %d remaining faults are '
                             'skipped' % (fault.segment, fault.index, self.skipped))
                    break
            time.sleep(0.5)   # load after the last fault
            self.stopped = time.time()   # the clients are told to stop: each called until now (checked)
            unfinished = deployment.stop_clients()
            self.finals = final_states(deployment)
            self.ended = time.time()
            self.ops, self.missing = [], []
            for k in range(1, self.clients + 1):
                path = deployment.history_path(k)
                if os.path.exists(path):
                    self.ops += history.read_history(path, 'client%d' % k)
                else:   # its operations, lost ones too, would go unchecked
                    self.missing.append('client%d wrote no history (%s)' % (k, path))
            self.unfinished_clients = unfinished
        finally:
            deployment.teardown()
        # A verdict the runner could not hear (a partitioned site's) is in that site's own log.
        self.verdicts = suspicions.merge(self.verdicts, suspicions.logged_verdicts(_log_lines(self.log_dir)))
        self.result = history.check(self.ops, self.finals, self.kills, self.ended, self.unfinished_clients,
                                    call_limit=CALL_TIMEOUT, clients=['client%d' % k for k in range(1, self.clients + 1)],
                                    stopped=self.stopped)
        for missing in self.missing:
            self.result.add('history_missing', missing)
        windows = [r['start'] for r in self.records[1:]] + [self.ended]
        for record, stop in zip(self.records, windows):
            record.update(history.unavailability_split(self.ops, record['start'], record.get('repaired_from'), stop))
        return self

    def _one(self, fault, deployment, rng):
        time.sleep(fault.gap)
        unhealed = None
        if whole(deployment) is not None:
            # The last fault's effect came after its heal looked (an exclusion late on a loaded machine): the
            # pair is made whole first, never hit a second time meanwhile (test campaign seed 26369: a lone
            # primary's node killed 0.2 s after its backup was excluded lost the only state).
            done, unhealed = heal(deployment, self.log, self.fail_stopped, [])
            self.log('fault %d: the pair was not whole before it; healed first (%s)%s'
                     % (fault.index, ', '.join(done) or 'it re-joined by itself', ': ' + unhealed if unhealed else ''))
        status = witness_status() or _Status
        roles = {'primary': status.primary, 'backup': status.backup}
        record = dict(index=fault.index, segment=fault.segment, mechanism=fault.mechanism, running=deployment.shape(),
                      kind=fault.kind,
                      target=fault.target, duration=fault.duration, epoch_before=status.epoch,
                      primary_before=status.primary,
                      sites=sorted(suspicions.sites_touched(fault.target, status.primary, status.backup)))
        self.fail_stopped.clear()

        def site_of(role):
            if not roles[role]:
                # The pair was whole when the last fault healed, but not now (a false suspicion in the
                # gap, say): no site plays the role, so the fault is not injected (it crashed the
                # 1000-fault hosts run, seed 2611, at fault 690: KeyError '').
                raise CampaignError('fault %d: no site is the %s now (witness: epoch %d, primary %r, backup %r)'
                                    % (fault.index, role, status.epoch, status.primary, status.backup))
            return roles[role]
        if unhealed:
            record.update(start=time.time(), end=time.time(), what='not injected: the pair was not whole before it',
                          outcome='unhealed: %s' % unhealed, healed=[])
            return record
        try:
            injected = self.backend.inject(fault, deployment, site_of, rng)
        except (CampaignError, FaultError) as e:   # (a host fault refused: recorded, not a traceback; session 34)
            record.update(start=time.time(), end=time.time(), what=str(e), outcome='not_injected', healed=[])
            return record
        record.update(injected)
        if injected.get('proxy_killed'):
            # (stamped before the signal, and after it: a call cut by the kill may start between)
            self.kills.setdefault(injected['proxy_killed'], []).append(
                (injected['start'], injected.get('signalled', injected['end'])))
        acted = []
        done, why = heal(deployment, self.log, self.fail_stopped, acted)
        after = witness_status() or _Status
        record.update(healed=done, healed_at=time.time(), epoch_after=after.epoch, primary_after=after.primary,
                      repaired_from=acted[0] if acted else None)
        if why:
            record['outcome'] = 'unhealed: %s' % why
        elif after.primary != status.primary:
            record['outcome'] = 'failover'
        elif done:
            record['outcome'] = 'restarted'
        elif 'adapted' in injected:
            record['outcome'] = 'adapted' if injected['adapted'] else 'rolled_back'
        else:
            record['outcome'] = 'absorbed'
        return record


def _log_lines(log_dir):
    """Every line of the sites' logs of a segment (its directory, and those of its later starts: .2, .3)."""
    import glob
    for path in sorted(glob.glob(os.path.join(log_dir, '*.log')) + glob.glob(os.path.join(log_dir + '.[0-9]', '*.log'))):
        with open(path, errors='replace') as f:
            for line in f:
                yield line


def in_background(function):
    """Run function in a daemon thread; returns the thread (for the progress bar while a segment runs)."""
    thread = threading.Thread(target=function, daemon=True)
    thread.start()
    return thread


def kill_leftovers(root_pid):
    """SIGKILL every descendant of root_pid (a campaign's end, whatever happened)."""
    procs = process_tree(root_pid)[1:]
    for proc in procs:
        try:
            proc.kill()
        except psutil.NoSuchProcess:
            pass
    return len(procs)


__all__ = ['CampaignDeployment', 'FaultBackend', 'ProcessBackend', 'AdaptingBackend', 'HostsBackend', 'Segment', 'heal', 'whole',
           'schedule']
