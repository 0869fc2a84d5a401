"""The PBR bank deployment on emulated hosts: every connection crosses a real interface.

Hosts (:class:`aft_ftm.hosts_exec.Hosts`): ``rosmaster`` (the roscore), ``client`` (the Proxy and
the bank client), ``witness`` (the witness), ``master`` and ``slave`` (the replicas), each its own
network namespace with ``ROS_IP``/``ROS_HOSTNAME`` its address and ``ROS_MASTER_URI`` the rosmaster
host's. Recovery fences a failed peer through the hosts' power switch (an agent outside every host,
on a Unix-domain socket: a management network no partition cuts) before it promotes anything.

The orchestrator (this module, in the root namespace) cannot reach the hosts' network: it asks a
:class:`Driver`, the ``bank_driver`` node it starts in the client host, for everything that needs
ROS (graph checks, the client's calls, states, failover records, alarms).

API (also for fault campaigns): :meth:`HostedDeployment.start`, :meth:`~HostedDeployment.stop`,
:meth:`~HostedDeployment.node_pids`, :meth:`~HostedDeployment.power_off`,
:meth:`~HostedDeployment.partition`, :meth:`~HostedDeployment.heal`,
:meth:`~HostedDeployment.freeze`, :meth:`~HostedDeployment.relaunch`, and ``driver``.
"""
import json
import os
import queue
import subprocess
import threading
import time

from aft_ftm.hosts_exec import Hosts
from aft_ftm.ros.graph import roslaunch
from aft_ftm.sites import Site, power_off_sites
from aft_examples.ros.deployment import CLIENT_SERVICES, PbrDeployment, replica_services

HOSTS = ('client', 'master', 'slave', 'witness', 'rosmaster')
MASTER_PORT = 11311


class DriverError(RuntimeError):
    """The bank driver refused a command, did not answer in time, or exited."""


class Driver(object):
    """The orchestrator's end of a ``bank_driver`` process (aft_examples.ros.bank_driver)."""

    def __init__(self, popen, log_path=None):
        self.popen = popen
        self.log_path = log_path
        self.lines = queue.Queue()
        self._reader = threading.Thread(target=self._read, name='driver-reader', daemon=True)
        self._reader.start()

    def _read(self):
        for raw in self.popen.stdout:
            line = raw.decode(errors='replace').strip()
            if line.startswith('{'):
                try:
                    self.lines.put(json.loads(line))
                except ValueError:
                    pass
        self.lines.put(None)   # end of output: the driver exited

    def _next(self, deadline, what):
        try:
            item = self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            raise DriverError('the bank driver did not answer %s within its deadline (its log: %s)' % (
                what, self.log_path))
        if item is None:
            raise DriverError('the bank driver exited (code %s) during %s' % (self.popen.poll(), what))
        return item

    def wait_ready(self, timeout):
        answer = self._next(time.monotonic() + timeout, 'its start')
        if not answer.get('ready'):
            raise DriverError('the bank driver started with %r' % answer)

    def request(self, limit, on_event=None, **command):
        """Send one command, return its answer (a dict) if it comes within ``limit`` seconds; events
        before it go to on_event(event). Raises DriverError."""
        if self.popen.poll() is not None:
            raise DriverError('the bank driver exited (code %s)' % self.popen.returncode)
        self.popen.stdin.write((json.dumps(command) + '\n').encode())
        self.popen.stdin.flush()
        deadline = time.monotonic() + limit
        while True:
            item = self._next(deadline, command.get('op'))
            if 'event' in item:
                if on_event is not None:
                    on_event(item)
                continue
            if not item.get('ok'):
                raise DriverError('bank driver, %s: %s' % (command.get('op'), item.get('error')))
            return item

    def close(self):
        """Ask it to quit; kill it if it does not within 2 s. Never raises."""
        try:
            if self.popen.poll() is None:
                self.popen.stdin.write(b'{"op": "quit"}\n')
                self.popen.stdin.flush()
                self.popen.wait(2.0)
        except Exception:   # shutdown paths never raise: killed below
            pass
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait(5.0)


class HostedDeployment(object):
    """The bank under PBR on emulated hosts (module docstring).

    ``hosts``: a :class:`Hosts` already entered (it must have the hosts of :data:`HOSTS`), or None
    to make one for the deployment (removed by :meth:`stop`). ``power_switch``: True for the hosts'
    switch, a spec string (``command:...``, e.g. ``command:false`` for a switch that never confirms),
    or '' for none. Other keyword arguments are those of :class:`PbrDeployment`.
    """

    def __init__(self, log_dir, hosts=None, power_switch=True, monitor=False, **pbr_args):
        plan = PbrDeployment(log_dir, **pbr_args)   # its launch arguments, not started
        self.tls = plan if plan.tls_policy else None   # its TLS files: each host's processes get its party's
        self.monitor = monitor    # the Monitoring Engine (monitor.launch, running pbr) in the witness host
        self.log_dir = log_dir
        self.launch_args = dict(plan.launch_args)
        self.witness = plan.witness
        self.inner, self.faulty, self.sec = plan.inner, plan.faulty, plan.sec
        self.power_switch = power_switch
        self.hosts = hosts
        self._own_hosts = hosts is None
        self.sites = {}
        self.driver = None
        self.switch = None        # the hosts' SwitchServer (power_switch=True)
        self.master_uri = None

    # -- start and stop ----------------------------------------------------------------------------
    # the TLS party of each host's processes (the driver on the client host is the operator)
    TLS_PARTIES = {'client': 'client', 'master': 'master', 'slave': 'slave', 'witness': 'witness'}

    def _env(self, host, party=None):
        ip = self.hosts.ip(host)
        env = dict(os.environ, ROS_IP=ip, ROS_HOSTNAME=ip, ROS_MASTER_URI=self.master_uri)
        party = party or self.TLS_PARTIES.get(host)
        if self.tls and party:
            env = self.tls.tls_env(party, env)
        return env

    def _site(self, name, host, argv, party=None):
        if self.hosts.state(host) == 'off':   # review of session 34: it lived on in the old namespace
            raise RuntimeError('site %s cannot start on host %s: it is off (relaunch powers it on)' % (name, host))
        host_ns = self.hosts.topology.host(host).namespace
        site = Site(name, ['ip', 'netns', 'exec', host_ns] + argv, self._env(host, party),
                    os.path.join(self.log_dir, '%s.%d.log' % (name, int(time.time() * 1000))))
        self.sites[name] = site
        return site.start()

    def _switch_spec(self):
        if self.power_switch is True:
            self.switch = self.hosts.power_switch()
            return 'unix:' + self.switch.path
        return self.power_switch or ''

    def _site_args(self, name):
        launch_file, args = self.launch_args[name]
        args = dict(args)
        if name in ('master', 'slave'):
            spec = self._switch_spec()
            if spec:
                args.update(power_switch=spec, peer_host=args['peer'])
        if name == 'client':
            args['witness'] = 'false'   # the witness has a host of its own
        return launch_file, args

    def start(self, timeout=120.0):
        """Hosts (if owned), the power switch, the roscore, the sites and the driver; waits until the
        pair is up (the backup joined). Raises RuntimeError naming what did not come up; on failure
        everything started is stopped."""
        os.makedirs(self.log_dir, exist_ok=True)
        started = time.monotonic()
        try:
            if self._own_hosts:
                self.hosts = Hosts(list(HOSTS)).__enter__()
            missing_hosts = [h for h in HOSTS if h not in self.hosts.topology.hosts]
            if missing_hosts:
                raise RuntimeError('the hosts lack %s' % ', '.join(missing_hosts))
            self.master_uri = 'http://%s:%d' % (self.hosts.ip('rosmaster'), MASTER_PORT)
            self._site('rosmaster', 'rosmaster', ['roscore', '-p', str(MASTER_PORT)])
            if self.witness:
                self._site('witness', 'witness', roslaunch('aft_ftm', 'witness.launch'))
            if self.monitor:
                # A third machine's: the engine starts each site's new nodes on that site's host.
                # Under TLS as the party engine: the nodes it starts take their site's party (aft_ftm.where).
                self._site('monitor', 'witness', roslaunch('aft_ftm', 'monitor.launch', running='pbr'), party='engine')
            for name in ('client', 'slave', 'master'):
                launch_file, args = self._site_args(name)
                self._site(name, name, roslaunch('aft_examples', launch_file, **args))
            self._start_driver(timeout)
            self._wait_up(started + timeout)
        except BaseException:
            self.stop()
            raise
        return time.monotonic() - started

    def _start_driver(self, timeout):
        log_path = os.path.join(self.log_dir, 'bank_driver.log')
        log = open(log_path, 'ab')
        try:
            popen = self.hosts.run_in('client', ['rosrun', 'aft_examples', 'bank_driver'],
                                      env=self._env('client', party='operator'),
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log)
        finally:
            log.close()
        self.driver = Driver(popen, log_path)
        self.driver.wait_ready(timeout)

    def why_down(self):
        """Why a started site is not coming up (Site.failure), or None."""
        for name, site in sorted(self.sites.items()):
            why = site.failure()
            if why:
                return why
        return None

    def _wait_up(self, deadline):
        services = replica_services('master', self.inner, self.faulty, self.sec) + \
            replica_services('slave', self.inner, self.faulty, self.sec) + list(CLIENT_SERVICES)
        replies = '/sec_plain/pro2pxy' if self.sec else '/ftm/pro2pxy'
        entry = '/master/%s' % ('sec_gate' if self.sec else 'protocol')
        status = None
        while True:
            why = self.why_down()
            if why:
                raise RuntimeError('%s while starting (logs in %s)' % (why, self.log_dir))
            status = self.driver.request(10.0, op='check', services=services, subscriptions=[[replies, '/proxy']],
                                         wired=entry, witness=self.witness)
            pair = status['witness'] if self.witness else [2, 'master', 'slave']
            if not status['missing'] and status['wired'] and pair and pair[2]:
                break
            if time.monotonic() > deadline:
                raise RuntimeError('the hosted deployment did not come up: missing %s, %s wired %s, witness %s '
                                   '(logs in %s)' % (status['missing'], entry, status['wired'], status['witness'],
                                                     self.log_dir))
            time.sleep(0.2)
        if self.witness and tuple(status['witness']) != (2, 'master', 'slave'):
            raise RuntimeError('the pair did not hold through the start: witness %s (logs in %s)'
                               % (status['witness'], self.log_dir))

    def stop(self):
        """Everything stopped: the driver, every site powered off, the hosts removed if this deployment
        made them. Idempotent; never raises."""
        try:
            if self.driver is not None:
                self.driver.close()
                self.driver = None
            power_off_sites(list(self.sites.values()))
        finally:
            if self._own_hosts and self.hosts is not None:
                self.hosts.close()
                self.hosts = None

    teardown = stop

    # -- the client ----------------------------------------------------------------------------------
    def drive(self, count, first=0, fault_after=None, fault=None, rng=None, max_delay=0.003, timeout=None):
        """The client in the client host sends operations first .. first+count-1 and checks each
        reply; once ``fault_after`` replies came back, after a random delay of up to max_delay (so the
        fault lands anywhere inside the next request), ``fault()`` runs here (it returns (processes
        affected, wall time of the fault)). Returns (records [index, sent, replied, ok], the checker's
        summary, {'processes', 'wall'} or None)."""
        injected = {}

        def on_event(event):
            if event.get('event') == 'fault_point' and fault is not None and not injected:
                if rng is not None:
                    time.sleep(rng.uniform(0, max_delay))
                injected['processes'], injected['wall'] = fault()
        answer = self.driver.request(timeout or 60.0 + 0.5 * count, on_event=on_event, op='drive', count=count,
                                     first=first, fault_after=fault_after if fault is not None else None)
        if fault is not None and not injected:
            raise RuntimeError('the fault was never injected (fault_after=%s, count=%d)' % (fault_after, count))
        return answer['records'], answer['summary'], injected or None

    def server_state(self, site):
        """The bank server state of site (bytes), read by the client host's driver."""
        return bytes.fromhex(self.driver.request(10.0, op='state', site=site)['state'])

    def last_failover(self, site, timeout=10.0):
        return self.driver.request(timeout + 5.0, op='failover', site=site, timeout=timeout)['record']

    def alarms(self):
        return self.driver.request(10.0, op='alarms')['alarms']

    def witness_pair(self):
        """The witness's [epoch, primary, backup] now, asked from the client host."""
        return self.driver.request(10.0, op='check', services=[], subscriptions=[], wired=None, witness=True)['witness']

    def strings(self, topic, last=0):
        """Every std_msgs/String heard on topic since the first call for it (which subscribes: a
        latched topic gives its last message at once), each parsed as JSON; the ``last`` ones only if > 0."""
        return self.driver.request(10.0, op='strings', topic=topic, last=last)['messages']

    # -- faults and observations, by host --------------------------------------------------------------
    def node_pids(self, host):
        """pids of every process of the host (its site's roslaunch and nodes, anything else in it)."""
        return self.hosts.processes(host)

    def power_off(self, host):
        """The faithful power loss: the host's link down first, then every process of it killed.
        Returns (processes killed, wall time the link went down). A host already off (e.g. fenced through
        the power switch after a false suspicion, a detector timing out under load) is left off:
        (0, the wall time its link went down then)."""
        killed = self.hosts.power_off(host, if_on=True)
        return len(killed), self.hosts.powered_off_at.get(host)

    def partition(self, host, other=None):
        self.hosts.partition(host, other)

    def heal(self, host, other=None):
        self.hosts.heal(host, other)

    def freeze(self, target, seconds):
        return self.hosts.freeze(target, seconds)

    def relaunch(self, name, **overrides):
        """Start site ``name`` again in its host (powered on first if off), with its launch arguments
        and overrides (e.g. role='backup'); it re-joins by itself. Returns the new Site."""
        if self.hosts.state(name) == 'off':
            self.hosts.power_on(name)
        old = self.sites.get(name)
        if old is not None:
            old.stop(grace=2.0)
        launch_file, args = self._site_args(name)
        return self._site(name, name, roslaunch('aft_examples', launch_file, **dict(args, **overrides)))
