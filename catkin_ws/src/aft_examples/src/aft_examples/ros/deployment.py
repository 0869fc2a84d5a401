"""Launching the PBR demo's three sites as separate roslaunch processes, for the demo, the
integration tests and the benchmarks. Uses the master API only (no rospy node)."""
import os
import time

from aft_ftm import security
from aft_ftm.ros.deadline import Deadline
from aft_ftm.ros.graph import clean_dead_nodes, roslaunch, wait_for_graph, wired
from aft_ftm.sites import Site, power_off_sites, stop_sites, wait_until

REPLICA_SERVICES = ('protocol/set_role', 'protocol/rebind', 'after/set_role', 'after/rebind',
                    'before/rebind', 'crash_detector/rebind', 'recovery/rebind',
                    'bank_server/get_state', 'bank_server/set_state', 'account')
GRAPH_SERVICES = ('protocol/rebind', 'before/rebind', 'proceed/rebind', 'after/rebind')
CLIENT_SERVICES = ('/account', '/proxy/rebind')


def nested_services(outer_ns, inner):
    """The services of mechanisms nested in an outer one's Proceed (inner: 'tr', 'tr+ad', ...)."""
    names, ns = [], outer_ns
    for mechanism in inner.split('+'):
        ns = '%s/%s' % (ns, mechanism)
        names += ['%s/%s' % (ns, s) for s in GRAPH_SERVICES if not s.startswith('proceed')]
    return names + ['%s/proceed/rebind' % ns]


def replica_services(site, inner='', faulty=False, sec=False):
    """The services a replica site of the demo offers once every node is set up."""
    names = ['/%s/%s' % (site, s) for s in REPLICA_SERVICES]
    if sec:
        names.append('/%s/sec_gate/rebind' % site)
    names += nested_services('/' + site, inner) if inner else ['/%s/proceed/rebind' % site]
    if faulty:
        names.append('/%s/fault_injector/inject' % site)
    return names


def start_retrying(deployment, attempts=2, log=print):
    """deployment.start(); if it does not come up, stop it and start it afresh (attempts in all).

    On a loaded 2-core machine a node's set-up has been seen to hang on a subscriber's handshake
    for 30 s, and the stall of many nodes starting at once to get a replica fenced on a false
    suspicion (scripts/bench_heartbeats). What a benchmark measures starts once the sites are up,
    so a second start hides nothing it measures; each failed try is logged. Returns what start()
    returned; raises the last try's error.
    """
    for attempt in range(1, attempts + 1):
        try:
            return deployment.start()
        except RuntimeError as e:
            if attempt == attempts:
                raise
            log('deployment start %d of %d failed, starting afresh: %s' % (attempt, attempts, e))
            deployment.stop()


def _while_starting(site):
    """Why site, being started, will not come up (Site.failure), or None."""
    why = site.failure()
    return why + ' while starting' if why else None


class _NoPair(object):
    backup = ''


class PbrDeployment(object):
    """The bank demo under PBR (or mechanism='lfr'). By default three sites, CLIENT, MASTER and SLAVE, each its own
    roslaunch process tree; with one_host=True a single roslaunch of demo_one_host.launch (site
    'all'), as a user of pbr.launch runs it."""

    def __init__(self, log_dir, period=0.01, timeout=0.03, env=None, one_host=False, inner='', faulty=False,
                 mechanism='pbr', sec=False, adaptable=False, witness=True, server_timeout=None, ballast_bytes=0,
                 cache_bytes=None, link_monitor=False, watch_required=True, tls_policy=None, incremental=True,
                 max_batch=None, ca_validity=None, chunk_bytes=None, catch_up=True,
                 state_changes=True, power_switch=None, witness_ns='aft', keys_from=None,
                 replay_log=None):
        self.log_dir = log_dir
        self.one_host = one_host
        self.witness = witness
        self.launch_args = {}
        self.inner = inner
        self.faulty = faulty
        self.sec = sec
        replica = dict(period=period, timeout=timeout)
        if server_timeout is not None:
            replica['server_timeout'] = server_timeout
        if ballast_bytes:
            replica['ballast_bytes'] = ballast_bytes
        if cache_bytes is not None:
            replica['cache_bytes'] = cache_bytes
        if not incremental:
            replica['incremental'] = 'false'   # every checkpoint carries the whole state (issue 18's baseline)
        if chunk_bytes is not None:
            replica['chunk_bytes'] = chunk_bytes   # a join's state transfer in parts of this many bytes
        if not catch_up:
            replica['catch_up'] = 'false'   # every reply waits from a join's state transfer on (the baseline)
        if not state_changes:
            replica['state_changes'] = 'false'   # the server offers getState alone: PBR computes the deltas
        if max_batch is not None:
            replica['max_batch'] = max_batch   # group commit's bound (1: one request at a time; default: auto)
        if not watch_required:
            replica['watch_required'] = 'false'   # a node's death is then told by roslaunch's shutdown only
        if link_monitor:
            replica['link_monitor'] = 'true'   # the bandwidth between the sites, measured, for the monitor
        client = {}
        # keys_from: the SEC keys directory of an earlier deployment (its CA's state and the gates' replay
        # logs with them): this one is that deployment started again.
        self.keys_dir = (keys_from or os.path.join(log_dir, 'keys')) if sec else None
        if sec:
            keys = self.keys_dir
            # client2: a second certified party (the policy gives it no Proxy of the demo): what an
            # attacker holding a valid certificate of its own can try
            for party in ('ca', 'client', 'client2', 'server') if not keys_from else ():
                security.write_party(keys, security.Party.generate(party))
            replica.update(sec='true', keys_dir=keys)
            if replay_log is not None:   # 'none': the gates' floors in memory only (a path would be the
                if replay_log != 'none':   # two sites' one log, which the second gate refuses)
                    raise ValueError("replay_log: 'none' or None (each gate's own log), got %r" % replay_log)
                replica['sec_replay_log'] = replay_log
            client = dict(sec='true', keys_dir=keys, sec_parties='[client, client2, server]')
            if ca_validity is not None:
                client['ca_validity'] = ca_validity   # a certificate's life (s; the CA's default: 24 h)
        if mechanism != 'pbr':
            replica['mechanism'] = mechanism
        # The witness's service (its configurations beside it, /NS/witness/configuration).
        self.witness_service = '/%s/witness/request' % witness_ns
        if not self.witness:
            replica['witness'] = 'none'   # roslaunch drops an empty name:= value
            client['witness'] = 'false'
        elif witness_ns != 'aft':
            if one_host:
                raise ValueError('the one-host demo runs the default witness (/aft/witness): no witness_ns')
            replica['witness'] = self.witness_service
            client['witness_ns'] = witness_ns
        self.replica_args = dict(replica)
        if adaptable:
            replica['adaptable'] = 'true'   # Before, Proceed and After replaceable without stopping a site
        if power_switch and one_host:
            raise ValueError('the one-host demo fences by pid: no power switch')
        if inner or faulty:
            if one_host:
                raise ValueError('the one-host demo has no nested mechanism nor fault injector')
            replica.update(inner=inner, faulty=str(bool(faulty)).lower())

        self.env = env
        # Mutual TLS on every TCPROS connection (issue 16): each site's nodes are its party; 'operator'
        # (the process that drives and checks), 'engine' (adapt, the Monitoring Engine) and 'client2'
        # (a certified party the policy trusts with nothing) are made too. tls_env(party) is the
        # environment a process of that party needs.
        self.tls_dir = os.path.join(log_dir, 'tls') if tls_policy else None
        self.tls_policy = tls_policy
        if tls_policy:
            from aft_ftm import tls
            authority = os.path.join(self.tls_dir, 'authority')   # the CA's key stays here, given to nobody
            tls.make_authority(authority)
            for party in ('master', 'slave', 'client', 'app', 'witness', 'operator', 'engine', 'client2'):
                tls.issue(authority, party)
                tls.export_party(authority, party, os.path.join(self.tls_dir, party))
            if not one_host and self.witness:
                client['witness_tls_dir'] = os.path.join(self.tls_dir, 'witness')   # a party of its own
            if not one_host:
                client['app_tls_dir'] = os.path.join(self.tls_dir, 'app')   # the bank_client's, where it runs

        def site(name, launch_file, **args):
            self.launch_args[name] = (launch_file, args)
            return Site(name, roslaunch('aft_examples', launch_file, **args), self.site_env(name),
                        os.path.join(log_dir, name + '.log'))
        if one_host:
            self.sites = {'all': site('all', 'demo_one_host.launch', **replica)}
        else:
            # Each site's Recovery fences its peer by this switch (its host named as the peer site).
            fence = {peer: dict(power_switch=power_switch, peer_host=peer) if power_switch else {}
                     for peer in ('master', 'slave')}
            self.sites = {
                'master': site('master', 'demo_replica_site.launch', site='master', peer='slave', role='primary',
                               **dict(replica, **fence['slave'])),
                'slave': site('slave', 'demo_replica_site.launch', site='slave', peer='master', role='backup',
                              **dict(replica, **fence['master'])),
                'client': site('client', 'demo_client_site.launch', **client),
            }

    def tls_env(self, party, base=None):
        """The environment of a process of party under this deployment's TLS (base, default os.environ)."""
        env = dict(os.environ if base is None else base)
        env.update(AFT_TLS_DIR=os.path.join(self.tls_dir, party), AFT_TLS_PARTY=party, AFT_TLS_POLICY=self.tls_policy)
        return env

    def site_env(self, name):
        if not self.tls_policy:
            return self.env
        return self.tls_env('master' if name == 'all' else name, self.env)

    def _site_exited(self):
        """Why a started site is not coming up (its roslaunch exited, or a node of it died in its
        set-up), or None: waiting for its services is then pointless."""
        for _, site in sorted(self.sites.items()):
            why = _while_starting(site)
            if why:
                return why
        return None

    def start(self, timeout=120.0):
        """Start the replicas, then the client site; raise RuntimeError naming what did not come up."""
        os.makedirs(self.log_dir, exist_ok=True)
        clean_dead_nodes()   # registrations a killed node left behind would stop our new nodes
        started = time.monotonic()
        replicas = ['all'] if self.one_host else ['slave', 'master']
        if not self.one_host:
            # The witness and the CA are on the client site: the replicas ask them at set-up.
            self.sites['client'].start()
        for name in replicas:
            self.sites[name].start()
        for site in ('master', 'slave'):
            missing = wait_for_graph(replica_services(site, self.inner, self.faulty, self.sec),
                                     timeout=timeout - (time.monotonic() - started), abort=self._site_exited)
            if missing:
                raise RuntimeError('replica %s did not come up: missing %s (logs in %s)'
                                   % (site, ', '.join(missing), self.log_dir))
        client_services = list(CLIENT_SERVICES) + (['/aft/ca/certificate', '/sec_gate/rebind'] if self.sec else [])
        replies = '/sec_plain/pro2pxy' if self.sec else '/ftm/pro2pxy'
        missing = wait_for_graph(client_services, [(replies, '/proxy')], timeout - (time.monotonic() - started),
                                 abort=self._site_exited)
        if missing:
            raise RuntimeError('the Proxy did not come up: missing %s (logs in %s)' % (', '.join(missing),
                                                                                      self.log_dir))
        # Registered is not connected: the first reply must find the Proxy connected.
        entry = '/master/%s' % ('sec_gate' if self.sec else 'protocol')
        if not wait_until(lambda: wired(entry), max(5.0, timeout - (time.monotonic() - started)), 0.05):
            raise RuntimeError('%s is not connected to its subscribers (logs in %s)' % (entry, self.log_dir))
        if self.witness and not wait_until(lambda: (witness_status(self.witness_service) or _NoPair).backup,
                                           max(5.0, timeout - (time.monotonic() - started)), 0.05):
            raise RuntimeError('the backup did not join the primary: witness %s (logs in %s)'
                               % (witness_status(self.witness_service), self.log_dir))
        status = witness_status(self.witness_service) if self.witness else None
        if status is not None and (status.epoch, status.primary, status.backup) != (2, 'master', 'slave'):
            # A detector timed out while the sites were starting (a loaded machine): not the pair asked for.
            raise RuntimeError('the pair did not hold through the start: epoch %d, primary %r, backup %r (logs in %s)'
                               % (status.epoch, status.primary, status.backup, self.log_dir))
        return time.monotonic() - started

    def relaunch(self, name, **overrides):
        """Start site name again (a repaired machine coming back), with its launch arguments and overrides
        (e.g. role='backup'). Returns the new Site; it joins the primary by itself."""
        launch_file, args = self.launch_args[name]
        args = dict(args, **overrides)
        old = self.sites[name]
        old.stop(grace=2.0)
        clean_dead_nodes()   # the dead site's registrations would stall the new nodes' connections
        site = Site(name, roslaunch('aft_examples', launch_file, **args), self.site_env(name),
                    os.path.join(self.log_dir, '%s.%d.log' % (name, int(time.time() * 1000))))
        self.sites[name] = site
        return site.start()

    def stop(self):
        stop_sites(list(self.sites.values()), grace=10.0)
        clean_dead_nodes()

    def teardown(self):
        """The end of a test: every site powered off at once (0.1 s where a clean stop takes 1.5 s),
        and the dead nodes' registrations forgotten."""
        power_off_sites(list(self.sites.values()))
        clean_dead_nodes()


class MechanismDeployment(object):
    """One site: the bank server, a fault injector (faulty=True), one mechanism and the Proxy."""

    def __init__(self, log_dir, mechanism, faulty=True, executions=3, env=None, inner=''):
        self.log_dir = log_dir
        self.mechanism = mechanism
        self.faulty = faulty
        self.inner = inner
        args = dict(mechanism=mechanism, faulty=str(bool(faulty)).lower(), executions=executions)
        if inner:
            args['inner'] = inner
        self.sites = {'site': Site('site', roslaunch('aft_examples', 'demo_mechanism_site.launch', **args),
                                   env, os.path.join(log_dir, 'site.log'))}

    def start(self, timeout=120.0):
        os.makedirs(self.log_dir, exist_ok=True)
        clean_dead_nodes()   # registrations a killed node left behind would stop our new nodes
        started = time.monotonic()
        self.sites['site'].start()
        ns = '/site/%s' % self.mechanism
        services = ['%s/%s' % (ns, s) for s in GRAPH_SERVICES if not s.startswith('proceed')] + list(CLIENT_SERVICES)
        services += nested_services(ns, self.inner) if self.inner else ['%s/proceed/rebind' % ns]
        if self.faulty:
            services.append('/site/fault_injector/inject')
        site = self.sites['site']
        missing = wait_for_graph(services, [('/ftm/pro2pxy', '/proxy')], timeout,
                                 abort=lambda: _while_starting(site))
        if missing:
            raise RuntimeError('the %s site did not come up: missing %s (logs in %s)'
                               % (self.mechanism, ', '.join(missing), self.log_dir))
        return time.monotonic() - started

    def stop(self):
        self.sites['site'].stop(grace=10.0)
        clean_dead_nodes()

    def teardown(self):
        """The end of a test: the site powered off, the dead nodes' registrations forgotten."""
        power_off_sites(list(self.sites.values()))
        clean_dead_nodes()


_WITNESS_CALLS = Deadline('witness-status', exclusive=True)


def witness_status(service='/aft/witness/request', timeout=5.0):
    """The witness's configuration (aft_msgs/WitnessResponse: epoch, primary, backup), or None (not up
    yet, gone, or no answer within timeout: a frozen or wedged witness; while such a call hangs, the
    next ones answer None at once instead of piling up)."""
    import rospy
    from aft_msgs.srv import Witness
    try:
        return _WITNESS_CALLS.call(lambda: rospy.ServiceProxy(service, Witness)(op=0, site='deployment'), timeout)
    except Exception:   # not up yet, gone, or not answering
        return None


def current_pair(log_dir, service='/aft/witness/request'):
    """(primary, backup, epoch) of the witness's configuration; RuntimeError naming it if there is no pair."""
    conf = witness_status(service)
    if conf is None or not conf.primary or not conf.backup:
        raise RuntimeError('the witness has no pair (%s; logs in %s)' % (
            'no answer' if conf is None else 'epoch %d: %r/%r' % (conf.epoch, conf.primary, conf.backup), log_dir))
    return conf.primary, conf.backup, conf.epoch


def pair_change(pair, service='/aft/witness/request'):
    """None while the witness's configuration is still pair (current_pair's: a backup excluded and admitted
    again has a new epoch, so it counts too); otherwise what it is now, said with pair for an error."""
    now = witness_status(service)
    if now is not None and (now.primary, now.backup, now.epoch) == tuple(pair):
        return None
    return '%s/%s, epoch %d, then %s' % (pair[0], pair[1], pair[2], 'no answer from the witness' if now is None else
                                        '%s/%s, epoch %d' % (now.primary, now.backup, now.epoch))


def require_same_pair(pair, log_dir, service='/aft/witness/request'):
    """Raise RuntimeError, naming both, unless the witness's configuration is still pair (current_pair's):
    a benchmark whose pair changed under it, or was excluded and admitted again (a false suspicion under
    load), measured something else."""
    change = pair_change(pair, service)
    if change:
        raise RuntimeError('the pair changed during the run (%s): a false suspicion? (logs in %s)' % (change, log_dir))


class PairChanged(RuntimeError):
    """The witness's pair changed before a benchmark's fault: a false suspicion at the timeout measured."""


def unless_pair_changed(fault, pair, service='/aft/witness/request'):
    """fault (a drive_through_fault fault()) run only while the witness's configuration is still pair
    (current_pair's); otherwise PairChanged, naming both, and no fault: with the backup fenced by a
    false suspicion, powering off the primary leaves nobody to serve, and the benchmark's calls wait
    for ever (a clean-clone CI, session 46)."""
    def guarded():
        change = pair_change(pair, service)
        if change:
            raise PairChanged('the pair changed before the fault (%s): a false suspicion' % change)
        return fault()
    return guarded


_PEER_CALLS = Deadline('peer-status', exclusive=True)


def peer_suspicion(sites=('master', 'slave'), timeout=2.0):
    """None while each site's crash detector holds its peer alive (aft_msgs/PeerStatus); otherwise what the
    first that does not says. Without a witness this is how a benchmark knows a false suspicion came
    before its fault: a pair whose detectors declared each other failed while they started (30 ms, a
    loaded machine) waits for a re-join that never comes, and powering off the primary then leaves
    nobody promoted (session 48's clean-clone CI: the healing benchmark's calls waited for ever)."""
    import rospy
    from aft_msgs.srv import PeerStatus
    for site in sites:
        service = '/%s/crash_detector/peer_status' % site
        try:
            status = _PEER_CALLS.call(lambda: rospy.ServiceProxy(service, PeerStatus)(), timeout)
        except Exception as e:   # not up, gone, or not answering
            return '%s did not answer: %s' % (service, e)
        if not status.alive:
            return '%s: %s' % (service, status.why or status.state)
    return None


def unless_peer_suspected(fault, sites=('master', 'slave')):
    """fault (a drive_through_fault fault()) run only while no crash detector of sites suspects its peer
    (peer_suspicion); otherwise PairChanged, naming it, and no fault."""
    def guarded():
        said = peer_suspicion(sites)
        if said:
            raise PairChanged('a crash detector suspected its peer before the fault (%s): a false suspicion' % said)
        return fault()
    return guarded


SAMPLE_TRIES = 3   # deployments per failover sample at most: a false suspicion before the fault draws it again


def redrawn_sample(draw, log_dir, tries=SAMPLE_TRIES):
    """draw(directory) in a fresh deployment each time, until it gives a sample (not None: None says a
    false suspicion came before the fault, which was then not injected): log_dir, then log_dir_again1,
    and so on. Returns (the sample, the directories drawn again). RuntimeError after tries."""
    again = []
    for attempt in range(tries):
        directory = log_dir + ('_again%d' % attempt if attempt else '')
        sample = draw(directory)
        if sample is not None:
            return sample, again
        again.append(directory)
    raise RuntimeError('%d deployments in a row had a false suspicion before the fault (logs in %s*)' % (
        tries, log_dir))


def last_failover(site, timeout=10.0):
    """The last failover record of site's Recovery (its latched ~events: the other records, starts,
    configurations and alarms, carry it as ``last_recovery``). Raises RuntimeError if there is none."""
    import json
    import rospy
    from std_msgs.msg import String
    deadline = time.monotonic() + timeout
    while True:
        data = json.loads(rospy.wait_for_message('/%s/recovery/events' % site, String, timeout=timeout).data)
        record = data if 'failed_site' in data else data.get('last_recovery')
        if record:
            return record
        if time.monotonic() > deadline:
            raise RuntimeError('%s/recovery recorded no failover within %.0f s' % (site, timeout))
        time.sleep(0.1)
