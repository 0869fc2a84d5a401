"""The Adaptation Engine: runs an adaptation script against the live ROS graph.

Validate, plan, execute. It checks the whole script against the graph before touching anything
(launch files exist and load with their arguments; :func:`aft_ftm.adaptation.check_fit`: nodes
exist and offer the services the steps need, the nodes launched do not clash with running ones;
every rebind of an existing node would be accepted: the node itself answers a dry run, naming
both types when a topic has the wrong one). It plans the steps (:func:`aft_ftm.adaptation.plan`)
and runs them as a transaction (:class:`aft_ftm.transaction.Transaction`, an explicit state
machine without ROS): the transaction decides what comes next, the engine carries it out; when a
step fails, what was done is undone in reverse order, everything suspended resumed, and reported.

An adaptation cannot strand the system:

- every suspension carries a lease (``lease``), renewed from a thread of the engine's own while
  it holds nodes suspended (:class:`LeaseKeeper`): a live engine keeps its pause through a long
  step (the paper order's launch), a dead or stopped one leaves nodes that resume by themselves;
  a node that resumed by itself (its lease ran out) fails the adaptation, which is rolled back;
- :meth:`Engine.interrupt` (the ``adapt`` command's SIGINT and SIGTERM) stops it between steps,
  or in the wait for launched nodes, and rolls back what was done;
- the nodes it launches (and the nodes a rollback starts again) run under a guard
  (:mod:`aft_ftm.ros.guarded_launch`) that stops them when the launcher of the site they join
  stops (:mod:`aft_ftm.site_guard`); they outlive the engine, as before.

Uses the master API, the nodes' services and XML-RPC, psutil and roslaunch processes; it needs
an initialised rospy node (the ``adapt`` command and the monitor are ones).
"""
import collections
import itertools
import os
import signal
import socket
import threading
import time

import psutil
import rosgraph
import rospkg
import rospy
from aft_msgs.srv import Rebind, RebindRequest, SetNodes, Suspend

from .. import adaptation, site_guard
from ..adaptation import ScriptError, StepError
from ..process_start import started
from ..suspension import MAX_LEASE
from ..transaction import ABANDONED, TERMINAL, UNKNOWN, Action, Outcome, State, Transaction, stop_reason
from ..turns import Busy, Turn
from ..site_watch import mark_retired
from ..sites import Site, last_errors, launch_failure, process_tree, wait_dead, wait_until
from ..where import WhereError, process_setting, run_where, site_tls, with_tls
from .graph import roslaunch, unregister, unwired
from .fencing import NotTheNode, node_api, visible_pid
from .guarded_launch import disarm_guard_of, guarded
from .launch_files import launch_nodes, resolve_launch_file, stopped_with


def services_called_by(config):
    """({node: the services it will call or needs offered}, {node: (its ~witness, its ~site)}) for the
    aft_ftm nodes of a loaded launch configuration."""
    def value(name):
        param = config.params.get(name)
        return param.value if param is not None else ''
    calls, witnesses = {}, {}
    for node in config.nodes:
        if node.package != 'aft_ftm':
            continue
        name = rosgraph.names.ns_join(node.namespace, node.name)
        witness, site, mechanism = value(name + '/witness'), value(name + '/site'), value(name + '/mechanism')
        follows = adaptation.follows_witness(node.type, mechanism, site, value(name + '/follow_witness'))
        # A node outside a replica (no site) follows no witness, whatever its parameter says.
        called = adaptation.services_called(name, node.type, mechanism, dict(node.remap_args),
                                            witness if follows else '')
        if called:
            calls[name] = called
        if follows:
            witnesses[name] = (witness, site)
    return calls, witnesses


def owners_of_process(pid):
    """The site launchers (aft_ftm.site_guard.Owner) a node's process belongs to: those its
    environment names (a node an adaptation launched or started again), else the nearest roslaunch
    above it. Empty if there is none, or the process cannot be read."""
    try:
        proc = psutil.Process(pid)
        try:
            text = proc.environ().get(site_guard.OWNERS_ENV)
        except psutil.AccessDenied:
            text = None
        if text:
            return site_guard.parse_owners(text)
        chain = [(p.pid, started(p.pid, zombie=True), p.cmdline()) for p in [proc] + proc.parents()]
    except (psutil.Error, site_guard.GuardError):
        return []
    owner = site_guard.launcher_among(chain)
    return [owner] if owner is not None else []


def wait_for_service(name, timeout):
    """Wait until the service answers a probe: None once it does, else why not (no provider registered
    with the master, or the registered provider not answering). The deadline is on the monotonic clock:
    rospy.wait_for_service counts on the wall clock, and gives up at once when it jumps forward."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            rospy.wait_for_service(name, max(0.05, min(1.0, deadline - time.monotonic())))
            return None
        except rospy.ROSException:
            if rospy.is_shutdown():
                return 'this node is shutting down'
            time.sleep(0.02)   # a wall clock that jumped makes rospy give up at once: no busy loop
        if time.monotonic() >= deadline:
            try:
                uri = rosgraph.Master(rospy.get_name()).lookupService(name)
            except Exception as e:   # rosgraph.MasterError: no provider; OSError: no master
                return 'no provider registered with the ROS master (%s)' % e
            return 'its provider %s does not answer' % uri


class _Probe(object):
    """What _bounded names in its error for a call before the pause: the action and its node."""
    __slots__ = ('action', 'target')

    def __init__(self, action, target):
        self.action, self.target = action, target


class LeaseKeeper(object):
    """Renews the leases of the nodes an engine holds suspended, every ``lease / 4`` seconds, so
    that no step, however long, loses the engine its pause.

    Each held node has a thread of its own (a node that hangs in its answer delays no other
    node's renewal) and a service connection of its own (rospy's are not shared across threads),
    opened before the pause (:meth:`connect`): a renewal then needs neither the ROS master nor a
    new connection, which on a loaded machine may take longer than the lease (the master, busy
    with the paper order's new nodes, was seen not to answer for seconds). Only a connection lost
    in the pause is opened again, through the master.

    A node that refuses a renewal is no longer suspended (its lease ran out: the engine was
    stopped, or starved, for longer than the lease; or its buffer filled): it is reported by
    :meth:`lost` and no longer renewed. A renewal that cannot be sent (connection lost) is tried
    again at the next period, on a new connection. A node that hangs in its answer holds its own
    thread only (rospy waits for an answer for ever: :meth:`stop` cuts the connection)."""

    def __init__(self, lease, log, owner=''):
        self.lease = lease
        self.owner = owner           # the engine's run that holds the nodes (aft_msgs/Suspend owner)
        self.period = lease / 4.0
        self._log = log
        self._lock = threading.Lock()
        self._held = set()
        self._lost = {}              # node -> why it is no longer suspended
        self._stop = threading.Event()
        self._ready = {}             # node -> a connection opened before the pause, not yet used
        self._threads = {}           # node -> its renewing thread
        self._active = {}            # renewing thread -> the connection it uses

    def connect(self, node):
        """Open the connection node's renewals will use (a probe: it changes nothing). Called
        before the pause; a node not reachable now is connected at its first renewal."""
        proxy = rospy.ServiceProxy(node + '/suspend', Suspend, persistent=True)
        try:
            proxy(probe=True)
        except Exception:   # rospy raises several kinds: connect later
            proxy.close()
            return
        with self._lock:
            stale = self._ready.pop(node, None)
            self._ready[node] = proxy
        if stale is not None:
            stale.close()

    def hold(self, node):
        """node is suspended by the engine (with this lease): keep it so."""
        with self._lock:
            self._held.add(node)
            if self._stop.is_set() or node in self._threads:   # a thread leaves the table as it decides to end
                return
            thread = self._threads[node] = threading.Thread(target=self._run, args=(node,),
                                                            name='lease_keeper %s' % node, daemon=True)
        thread.start()

    def release(self, node):
        """node is about to be resumed by the engine: renew it no more."""
        with self._lock:
            self._held.discard(node)

    def lost(self):
        with self._lock:
            return dict(self._lost)

    def held(self):
        """The nodes held suspended now (neither released nor lost)."""
        with self._lock:
            return set(self._held)

    def stop(self):
        """Renew nothing more (the nodes still held then resume by themselves). Never raises."""
        self._stop.set()
        with self._lock:
            threads = list(self._threads.values())
            ready, self._ready = list(self._ready.values()), {}
            active = list(self._active.values())
        for proxy in active:   # a thread waiting for a hung node's answer: its connection cut, it ends
            _cut(proxy)
        deadline = time.monotonic() + 5.0   # one still running is left behind (a daemon)
        for thread in threads:
            thread.join(timeout=max(0.0, deadline - time.monotonic()))
        for proxy in ready:
            proxy.close()

    def _run(self, node):
        with self._lock:
            proxy = self._ready.pop(node, None)
            self._active[threading.current_thread()] = proxy
        try:
            while not self._stop.wait(self.period):
                with self._lock:
                    if node not in self._held:
                        self._threads.pop(node, None)
                        return
                why, proxy = self._renew(node, proxy)
                with self._lock:
                    self._active[threading.current_thread()] = proxy
                if why is None:
                    continue
                with self._lock:
                    self._threads.pop(node, None)
                    if node not in self._held:   # resumed by the engine meanwhile: nothing lost
                        return
                    self._held.discard(node)
                    self._lost[node] = why
                self._log('%s is no longer suspended: %s' % (node, why))
                return
        finally:
            with self._lock:
                if self._threads.get(node) is threading.current_thread():
                    del self._threads[node]
                self._active.pop(threading.current_thread(), None)
            if proxy is not None:
                proxy.close()

    def _renew(self, node, proxy):
        """(None if renewed or not reachable now, else why the node refused; the connection to use next)."""
        try:
            if proxy is None:
                proxy = rospy.ServiceProxy(node + '/suspend', Suspend, persistent=True)
                with self._lock:
                    self._active[threading.current_thread()] = proxy
            answer = proxy(renew=True, lease=self.lease, owner=self.owner)
        except Exception as e:   # rospy raises several kinds for a lost connection: try again later
            if proxy is not None:
                proxy.close()
            self._log('warning: lease renewal of %s not sent (%s): trying again in %.2f s' % (node, e, self.period))
            return None, None
        return (None if answer.success else answer.message), proxy


def _cut(proxy):
    """Shut a persistent service proxy's socket: a thread waiting for its answer gets an error."""
    sock = getattr(getattr(proxy, 'transport', None), 'socket', None)
    try:
        if sock is not None:
            sock.shutdown(socket.SHUT_RDWR)
    except OSError:   # closed meanwhile
        pass


def _never_raises(log):
    """The engine's log: a line that cannot be written (a closed pipe, a full disk, an ssh session
    gone) must not abandon a transaction half-way, nor cut its rollback short (review of stop 39)."""
    def write(text):
        try:
            log(text)
        except Exception:   # nothing better to do than go on: the report still says everything
            pass
    return write


RESPAWN_TIMEOUT = 30.0   # s a node a rollback starts again has to be set up (Engine._respawn_lacks)

LaunchPlan = collections.namedtuple('LaunchPlan', 'path nodes owners tls')
LaunchPlan.__doc__ = """A launch entry as validated: its file, the nodes it starts, the launchers
of the sites they join (their guard stops them with those)."""

Killed = collections.namedtuple('Killed', 'pid cmdline cwd env owners')
Killed.__doc__ = """How to start a retired node again (a rollback): its process's command line,
working directory and environment, and the site launchers it belongs to (it stops with them)."""


class LaunchedSite(object):
    """A roslaunch the engine started, and the nodes it starts (a record of the engine's own)."""

    def __init__(self, site, nodes):
        self.site = site
        self.nodes = list(nodes)

    @property
    def pid(self):
        return self.site.pid

    @property
    def log_path(self):
        return self.site.log_path

    def alive(self):
        return self.site.alive()

    def ended(self):
        """{node: how it ended}: its nodes whose process ended while the launch runs on (Site.ended)."""
        return self.site.ended()

    def output(self):
        """What its roslaunch wrote so far (Site.output)."""
        return self.site.output()

    def set_niceness(self, niceness):
        return self.site.set_niceness(niceness)

    def stop(self, grace=5.0):
        """Never raises (Site.stop)."""
        self.site.stop(grace=grace)


def site_of_launch(args):
    """The replica site a launch's nodes belong to, from its arguments: ``site``, else the first
    name of ``ns`` (mechanism.launch: /master/tr is site master); '' if neither says."""
    site = str(args.get('site', '')).strip('/')
    if not site:
        site = str(args.get('ns', '')).strip('/').split('/')[0]
    return site


class Engine(object):
    """Runs scripts. ``log`` is a function of one string (the ``adapt`` command prints).

    ``lease`` (s): the lease of each suspension (renewed while held). ``guard_poll`` and
    ``guard_grace`` (s): how often a launched node's guard looks at its site's launcher, and
    how long the launch has to stop after SIGINT before it is killed.

    State: what the engine started (``sites``, ``respawned``), the interrupt, and what the run
    in progress needs (its checked launches, its lease keeper, its service connections); the
    transaction's own state is in :attr:`transaction` (that of the last run)."""

    SILENT_AFTER = 2.0   # s: from then on, a launched node is not kept waiting by subscribers that do not answer

    def __init__(self, log=None, quiesce_timeout=5.0, launch_timeout=60.0, service_timeout=5.0,
                 connect_timeout=2.0, log_dir=None, launch_niceness=5, lease=5.0, guard_poll=0.2,
                 guard_grace=5.0, turn_timeout=120.0):
        if not 0 < lease <= MAX_LEASE:
            raise ValueError('the lease must be > 0 s and at most %g s, got %r' % (MAX_LEASE, lease))
        self.log = _never_raises(log or (lambda text: rospy.loginfo(text)))
        self.lease = lease
        self.guard_poll = guard_poll
        self.guard_grace = guard_grace
        self.turn_timeout = turn_timeout   # s an adaptation waits for another one of this master (aft_ftm.turns)
        self.quiesce_timeout = quiesce_timeout
        self.launch_timeout = launch_timeout
        self.service_timeout = service_timeout
        self.connect_timeout = connect_timeout
        self.launch_niceness = launch_niceness
        self.log_dir = log_dir or os.path.join(rospkg.get_log_dir(), 'aft_adaptations')
        self.sites = []            # LaunchedSite: the roslaunch processes started and still running
        self.committed = []        # those of them whose run is done: the sites' nodes now (shutdown leaves them)
        self.respawned = []        # Site: nodes started again from their command line by a rollback
        self.transaction = None    # the Transaction of the last run
        self._interrupted = ''     # set by interrupt() (from a signal handler: a plain assignment)
        self._launch_count = itertools.count()
        self._run_count = itertools.count(1)
        # The script validated last (the run in progress):
        self._launches = {}        # Launch entry -> LaunchPlan
        self._launched_names = []  # the nodes its launches start
        self._proxies = {}         # service name -> persistent proxy
        self._proxies_lock = threading.Lock()
        self._prepared_kills = {}  # node -> (process, Killed) or StepError: a kill group's, recorded first
        self._nodes_seen = (None, frozenset())   # (when, the running nodes): _graph_nodes' cache
        self._script = None   # the script being run (validate): its binds and retirements
        self._keeper = None        # the LeaseKeeper of the run in progress
        self._run_sites = []       # the LaunchedSites it started
        self._owner = ''           # the run in progress's name on the nodes it suspends (aft_msgs/Suspend owner)

    def interrupt(self, why):
        """Stop the run in progress and roll it back (from a signal handler, or another thread):
        the step in progress ends first (a wait for launched nodes ends at once). It holds for the
        engine's later runs too: an interrupted engine changes nothing more. Returns False if it
        was already interrupted (a second signal: the rollback goes on)."""
        first = not self._interrupted
        self._interrupted = self._interrupted or why
        return first

    @property
    def interrupted(self):
        return self._interrupted

    def _lost(self):
        return self._keeper.lost() if self._keeper is not None else {}

    # -- the graph ----------------------------------------------------------------------------
    @property
    def master(self):
        """A master proxy of its own for each use: XML-RPC proxies are not shared across threads."""
        return rosgraph.Master(rospy.get_name())

    def _graph(self):
        try:
            pubs, subs, srvs = self.master.getSystemState()
        except Exception as e:
            raise ScriptError('the ROS master cannot be asked: %s' % e)
        nodes = {n for _, names in list(pubs) + list(subs) + list(srvs) for n in names}
        return nodes, {name for name, _ in srvs}

    def _site_witnesses(self, sites):
        """{site: the witness its Recovery follows (its ~witness on the parameter server)} for the sites
        whose Recovery's parameter is there."""
        found = {}
        for site in set(s for s in sites if s):
            try:
                found[site] = self.master.getParam('/%s/recovery/witness' % site.strip('/'))
            except Exception:   # no such parameter (no Recovery there), or the master not answering
                continue
        return found

    def _graph_nodes(self):
        when = self._nodes_seen[0]
        if when is None or time.monotonic() - when > 0.5:
            self._nodes_seen = (time.monotonic(), frozenset(self._graph()[0]))
        return self._nodes_seen[1]

    # -- validation -----------------------------------------------------------------------------
    def validate(self, script, mode):
        """Check script against the live graph; returns the plan. Raises ScriptError naming the
        problem; nothing is changed."""
        steps = adaptation.plan(script, mode)
        self._script = script
        self._close_proxies()
        self._launches, self._launched_names = {}, []
        nodes, services = self._graph()
        loaded = collections.OrderedDict()
        calls, witnesses = {}, {}
        for entry in script.launch:
            path = resolve_launch_file(entry.file)
            names, config = launch_nodes(path, entry.args)
            loaded[entry] = (path, names)
            calls[entry], followed = services_called_by(config)
            witnesses.update(followed)
        adaptation.check_fit(script, nodes, services, {entry: names for entry, (_, names) in loaded.items()}, calls,
                             witnesses, self._site_witnesses(site for _, site in witnesses.values()))
        launches = {}
        for entry, (path, names) in loaded.items():
            owners, neighbours = self._site_owners(names, nodes)
            if not owners:
                self.log('warning: no site launcher on this host runs nodes of the namespace of %s: they will '
                         'not stop with a site (stop them by hand)' % ', '.join(names))
            launches[entry] = LaunchPlan(path, names, owners, self._launch_tls(names, neighbours))
        launched = [name for entry in script.launch for name in launches[entry].nodes]
        for node in script.retire:
            try:
                uri = self.master.lookupNode(node)
            except Exception as e:
                raise ScriptError('node %s (to retire) cannot be looked up: %s' % (node, e))
            try:
                here = visible_pid(uri, rospy.get_name(), node)
            except NotTheNode as e:
                raise ScriptError('node %s (to retire) is registered at %s, but %s: nothing is killed on that '
                                  'word (a forged registration?)' % (node, uri, e))
            except Exception as e:
                raise ScriptError('node %s (to retire) does not answer at %s: %s' % (node, uri, e))
            if here is None:
                raise ScriptError('node %s (to retire) runs on another machine (%s): the engine kills, and '
                                  'restarts on a rollback, only nodes of its own machine (its host or '
                                  'emulated hosts of it)' % (node, uri))
            stopped = [n for n in stopped_with(here, node) if n in nodes and n not in script.retire]
            if stopped:
                raise ScriptError('node %s (to retire) is required by the roslaunch that started it: its death '
                                  'stops that roslaunch, and with it %s, which the script does not retire '
                                  '(start the nodes an adaptation may retire one by one in launches of their '
                                  'own, or with required false)' % (node, ', '.join(sorted(stopped))))
        for bind in script.bind:
            if bind.node not in launched:
                try:   # bounded: a node hung in its answer held the engine (and the monitor) for ever
                    self._bounded(_Probe('rebind', bind.node), lambda bind=bind: self._rebind(bind, dry_run=True),
                                  2 * self.service_timeout)
                except (StepError, rospy.ServiceException, rospy.ROSException) as e:
                    raise ScriptError('%s does not answer its rebind service: %s' % (bind.node, e))
        self._launches, self._launched_names = launches, launched
        return steps

    def _rebind(self, bind, dry_run=False):
        rebind = self._proxy(bind.node + '/rebind', Rebind)
        direction = RebindRequest.SUBSCRIBE if bind.direction == 'subscribe' else RebindRequest.PUBLISH
        answer = rebind(port=bind.port, topic=bind.topic, direction=direction, activate=bind.activate,
                        dry_run=dry_run, connect_timeout=0 if dry_run or not bind.activate else self.connect_timeout)
        if not answer.success:
            what = 'bind %s.%s to %s' % (bind.node, bind.port, bind.topic) if bind.activate else \
                'unbind %s.%s' % (bind.node, bind.port)
            error = ScriptError if dry_run else StepError
            raise error('cannot %s: %s' % (what, answer.message))
        return answer.previous_topic

    # -- sites ----------------------------------------------------------------------------------
    def _site_owners(self, names, running):
        """(the launchers of the sites new nodes join, {new node: the pid of the running node those
        were found from}): of the running nodes nearest in the name space
        (:func:`aft_ftm.site_guard.neighbours`), on this host. Empty if none is found."""
        owners, found, neighbours = [], {}, {}
        for name in names:
            candidates = tuple(site_guard.neighbours(name, running, exclude=names))
            if candidates not in found:
                found[candidates] = self._owners_of_nodes(candidates)
            its_owners, pid = found[candidates]
            owners += [o for o in its_owners if o not in owners]
            if pid is not None:
                neighbours[name] = pid
        return owners, neighbours

    def _owners_of_nodes(self, nodes, tries=3):
        """(the site launchers of the first of nodes found on this host, that node's pid)."""
        for node in nodes[:tries]:
            try:
                pid = visible_pid(self.master.lookupNode(node), rospy.get_name(), node)
                if pid is None:
                    continue
            except Exception:   # gone meanwhile, or not answering: try the next one
                continue
            owners = owners_of_process(pid)
            if owners:
                return owners, pid
        return [], None

    @staticmethod
    def _launch_tls(names, neighbours):
        """The TLS variables of a launch's nodes (None without TLS here): the party of the running
        nodes of their site, each checked against this engine's policy and CA (aft_ftm.where.site_tls).
        ScriptError, nothing changed, if a node's site is not found, or its party cannot run them all."""
        if not os.environ.get('AFT_TLS_DIR'):
            return None
        missing = [name for name in names if name not in neighbours]
        if missing:
            raise ScriptError('%s joins no site found on this host: under TLS it would run as this engine\'s '
                              'party (%s), which may not run a site\'s nodes' % (missing[0], os.environ.get('AFT_TLS_PARTY')))
        by_process = collections.OrderedDict()   # each running node's process read and checked once
        for name in names:
            by_process.setdefault(neighbours[name], []).append(name)
        chosen = []
        for pid, group in by_process.items():
            try:
                their_env, their_cwd = process_setting(pid)
                chosen.append(site_tls(their_env, their_cwd, group, os.environ))
            except WhereError as e:
                raise ScriptError('%s: %s' % (', '.join(group), e))
        settings = {tuple(sorted(v.items())) for v in chosen}
        if len(settings) > 1:   # one roslaunch, one environment
            raise ScriptError('the nodes of one launch, %s, join sites of different TLS parties (%s): give each '
                              'site its own launch' % (', '.join(names), ', '.join(sorted(v['AFT_TLS_PARTY'] for v in chosen))))
        return dict(settings.pop()) if settings else None

    # -- running --------------------------------------------------------------------------------
    def run(self, script, mode='prepared'):
        """Validate, then run the script. Returns a report (dict). Raises ScriptError (invalid:
        nothing changed); a failed step, a lost suspension or an interrupt (:meth:`interrupt`)
        is rolled back and reported with ok=False (``interrupted`` names the interrupt). A
        rollback that could not undo everything is reported with ``state`` FAILED and an
        ``alarm`` naming what is left.

        Consecutive steps of the same action run in parallel, except suspensions, which follow
        the script's order (a backup's After is suspended after the primary's Protocol is
        quiescent, so the last checkpoint is in when it applies it).
        """
        t0 = time.monotonic()
        tx = self.transaction = Transaction(script.name, t0)
        turn = Turn(rosgraph.get_master_uri())
        try:   # one adaptation at a time on this master: validated once the other one is done
            waited = turn.take('pid %d, %s, running %s' % (os.getpid(), rospy.get_name(), script.name),
                               self.turn_timeout, stop=lambda: self._interrupted,
                               waiting=lambda holder: self.log('waiting for the adaptation in progress: %s' % holder))
        except Busy as e:
            tx.refused(str(e), time.monotonic())
            raise ScriptError(str(e))
        try:
            return self._run(script, mode, tx, t0, waited)
        finally:
            turn.give()

    def _run(self, script, mode, tx, t0, waited):
        try:
            steps = self.validate(script, mode)
        except ScriptError as e:
            tx.refused(str(e), time.monotonic())
            raise
        tx.validated(steps, time.monotonic())
        report = {'script': script.name, 'kind': script.kind, 'mode': mode, 'ok': True, 'steps': [],
                  'rolled_back': False, 'error': '', 'interrupted': '', 'validated_s': time.monotonic() - t0,
                  'waited_turn_s': waited}
        self.log('adaptation %s (%s, %s order): %d steps' % (script.name, script.kind, mode, len(steps)))
        self._run_sites = []
        self._owner = '%s/%d/%s/%d' % (rospy.get_name(), os.getpid(), script.name, next(self._run_count))
        self._keeper = LeaseKeeper(self.lease, self.log, self._owner)
        try:
            self._execute(tx, report['steps'])
        finally:
            self._keeper.stop()
        if tx.state == State.DONE:   # what it launched is the sites' now: shutdown() leaves it running
            self.committed += [site for site in self._run_sites if site in self.sites]
        report.update(tx.summary())
        report['duration_s'] = time.monotonic() - t0
        report['nodes_touched'] = script.nodes_touched(self._launched_names)
        report['launched_pids'] = [s.pid for s in self._run_sites if s.alive()]
        if tx.alarm:
            self.log('ALARM: %s' % tx.alarm)
        self.log('adaptation %s %s: pause %.1f ms, %.2f s in all, %d nodes touched' % (
            script.name, {State.DONE: 'done', State.ROLLED_BACK: 'ROLLED BACK'}.get(tx.state, 'ROLLBACK FAILED'),
            report['pause_s'] * 1e3, report['duration_s'], len(report['nodes_touched'])))
        return report

    def _execute(self, tx, records):
        """Carry out the transaction's decisions until it ends; each step's record into records."""
        tx.start(time.monotonic())
        while True:
            decision = tx.next(time.monotonic(), self._interrupted, self._lost())
            if decision.failure:
                self.log('FAILED: %s: rolling back' % decision.failure)
            if decision.action is Action.END:
                return
            if decision.action is Action.UNDO:
                step = decision.steps[0]
                try:
                    detail, ok = self._undo(step), True
                except Exception as e:   # keep undoing the rest: each failure is reported
                    detail, ok = str(e), False
                self.log('  rollback %s %s: %s%s' % (step.action, step.target, 'ok: ' if ok else 'FAILED: ', detail))
                tx.undone(step, ok, detail, time.monotonic())
                continue
            group = decision.steps
            self.log('step %s: %s' % (group[0].action, ', '.join(str(s.target) for s in group)))
            if decision.opens_pause:
                self._connect(tx.steps)   # persistent connections, opened before the pause
            outcomes = self._run_group(group)
            for o in outcomes:
                records.append(self._record(o.step, o.started, o.error is None,
                                            self._describe(o.step, o.info) if o.error is None else o.error))
                if decision.action is Action.CLEAN and o.error is not None:
                    # Resumed: the new configuration serves. Undoing it now would rebind a live
                    # graph: a failure here is reported, not rolled back.
                    self.log('cleanup step %s %s failed: %s (the adaptation stands)' % (
                        o.step.action, o.step.target, o.error))
            tx.ran(outcomes, time.monotonic(), self._interrupted)

    def _call_limit(self, action):
        """How long a step's service calls may take (None: the step bounds itself: launches, kills).
        A node that hangs in its answer (stopped, its master call hung) held the whole pause for ever
        while the lease keeper renewed every other node's suspension (review of stop 39)."""
        if action == 'suspend':
            return 2 * self.service_timeout + self.quiesce_timeout
        if action == 'rebind':
            return 2 * self.service_timeout + self.connect_timeout
        if action in ('resume', 'promote'):
            return 2 * self.service_timeout
        return None

    def _bounded(self, step, function, limit):
        """function() for ``step``, or StepError past ``limit`` s (None: unbounded). Past it the call
        is abandoned: its connections to the node are cut (the thread waiting in it ends) and
        forgotten. The node may still carry it out later (a rollback undoes what may have been done)."""
        if limit is None:
            return function()
        box = {}

        def run():
            try:
                box['value'] = function()
            except BaseException as e:   # handed to the caller
                box['error'] = e
        thread = threading.Thread(target=run, name='adapt %s %s' % (step.action, step.target), daemon=True)
        thread.start()
        thread.join(limit)
        if thread.is_alive():
            self._forget_proxies(step.target, cut=True)
            raise StepError('%s did not answer its %s within %.1f s (stopped or hung): %s'
                            % (step.target, step.action, limit, ABANDONED))
        if 'error' in box:
            raise box['error']
        return box.get('value')

    def _run_group(self, group):
        """Run steps (in parallel if more than one); returns an Outcome per step, in order.

        The group that ends the pause (the last resumes) first checks that every node is still
        suspended by this run (:meth:`_pause_intact`): if one is not, none is resumed and every
        step fails, so that the rollback runs on a graph still paused."""
        results = [None] * len(group)
        s0 = time.monotonic()
        last_resumes = group[0].action == 'resume' and self.transaction is not None and \
            self.transaction.index == self.transaction.last_resume
        if last_resumes:
            broken = self._pause_intact()
            if broken:
                return [Outcome(step, s0, 'not resumed: %s' % broken, None) for step in group]
        if group[0].action == 'rebind':
            unconnected = self._unconnected_binds([step.detail for step in group])
            if unconnected:
                return [Outcome(step, s0, 'not rebound: %s' % '; '.join(unconnected), None) for step in group]
        if group[0].action == 'kill' and len(group) > 1:
            # Every node of the group recorded before any is signalled: nodes of one required launch go
            # down together, and one recorded after another's kill was found dead, its kill "failed" and
            # the rollback did not start it again (review of session 35).
            for step in group:
                try:
                    self._prepared_kills[step.target] = self._kill_record(step.target)
                except StepError as e:
                    self._prepared_kills[step.target] = e

        def one(i, step):
            s0 = time.monotonic()
            try:
                results[i] = Outcome(step, s0, None, self._bounded(step, lambda: self._do(step),
                                                                   self._call_limit(step.action)))
            except (StepError, ScriptError, rospy.ServiceException, rospy.ROSException) as e:
                results[i] = Outcome(step, s0, str(e), None)
                try:
                    self._forget_proxies(step.target)   # rospy keeps a broken persistent connection
                except Exception:   # the step's outcome stands: a group always has every outcome
                    pass
            except Exception as e:   # an unexpected error is still a failed step, rolled back
                results[i] = Outcome(step, s0, '%s: %s' % (type(e).__name__, e), None)
        if len(group) == 1:
            one(0, group[0])
        else:
            threads = [threading.Thread(target=one, args=(i, s)) for i, s in enumerate(group)]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
        if last_resumes:
            results = [self._resumed_all_the_same(o) for o in results]
        return results

    def _unconnected_binds(self, binds):
        """What adaptation.unconnected_binds says of these binds, against the master's graph now (the
        launches are up: every order launches before it rebinds); [] when they all have a peer. A
        master that cannot be asked is said too: a rebind would not connect without it either."""
        script = self._script
        if script is None:
            return []
        try:
            pubs, subs, _ = self.master.getSystemState()
        except Exception as e:
            return ['the ROS master cannot be asked who publishes and subscribes: %s' % e]
        return adaptation.unconnected_binds(script, dict(pubs), dict(subs), only=binds)

    def _resumed_all_the_same(self, outcome):
        """A last resume whose answer did not come in time (the engine stalled, or the node delivered a
        large held buffer before it answered) may have resumed the node all the same: it was taken as
        not done, and the rollback undid an adaptation already serving (review of session 35). Its
        gate is asked over a new connection: open (or opening), the resume stands, said in the step's
        record; otherwise (closed, or no answer) the step stays failed."""
        if outcome.error is None or ABANDONED not in outcome.error:
            return outcome
        step = outcome.step
        try:
            state = self._bounded(_Probe('resume', step.target), lambda: self._proxy(
                step.target + '/resume', Suspend)(probe=True).message, self._call_limit('resume'))
        except Exception:   # no answer again: it stays failed, and the rollback resumes it
            return outcome
        if state not in ('OPEN', 'OPENING'):
            return outcome
        self._keeper.release(step.target)
        return Outcome(step, outcome.started, None, 'its answer was lost (%s), but its gate says %s: resumed' % (
            outcome.error, state))

    def _pause_intact(self):
        """'' if every node this run suspended is still suspended by it, else which are not and why.
        A node resumed by someone else (an operator, another engine) or by itself (its lease ran out
        while this engine was stopped) ran while the bindings changed: requests may have gone to
        both mechanisms or neither. Said, and rolled back while the others are still paused."""
        held = sorted(self._keeper.held())
        lost = dict(self._lost())
        answers = {}

        def check(node):
            step = adaptation.Step('suspend', node, None)
            try:
                answer = self._bounded(step, lambda: self._proxy(node + '/suspend', Suspend)(
                    renew=True, lease=self.lease, owner=self._owner), self.service_timeout)
                answers[node] = '' if answer.success else answer.message
            except Exception:   # not reachable: its resume says so (a dead site, say)
                self._forget_proxies(node)
                answers[node] = None
        threads = [threading.Thread(target=check, args=(node,)) for node in held if node not in lost]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        lost.update({node: why for node, why in answers.items() if why})
        if not lost:
            return ''
        return 'the pause was broken: %s' % '; '.join('%s is no longer suspended by this adaptation (%s)' % item
                                                       for item in sorted(lost.items()))

    def _connect(self, steps):
        """Open persistent connections to the services the pause will call, by no-op calls
        (a resume of a running node, a dry-run rebind), so that the pause pays no connection set-up."""
        for step in steps:
            try:   # each bounded (review of the monitor, session 33: a hung node held this for ever)
                self._bounded(_Probe(step.action, step.target), lambda step=step: self._probe(step),
                              2 * self.service_timeout)
            except Exception:   # not reachable yet (paper order: launched in the pause): connect then
                self._proxies.pop(step.target + '/rebind', None)

    def _probe(self, step):
        if step.action in ('suspend', 'resume'):
            # Probes: they answer and change nothing, whoever has the node suspended.
            self._proxy(step.target + '/suspend', Suspend)(probe=True)
            self._proxy(step.target + '/resume', Suspend)(probe=True)
            if step.action == 'suspend':
                self._keeper.connect(step.target)
        elif step.action == 'rebind' and step.target in self._graph_nodes():
            self._rebind(step.detail, dry_run=True)
        elif step.action == 'promote':
            self._proxy(step.target + '/set_promote', SetNodes)

    def _forget_proxies(self, node, cut=False):
        """Close the connections to node's services (``cut``: shut their sockets first, so that a
        thread waiting in a call on one ends)."""
        with self._proxies_lock:   # (the steps of a group run in threads: review of session 35)
            gone = [self._proxies.pop(n) for n in list(self._proxies) if n.startswith(node + '/')]
        for proxy in gone:
            if cut:
                _cut(proxy)
            proxy.close()

    def _close_proxies(self):
        with self._proxies_lock:
            gone, self._proxies = list(self._proxies.values()), {}
        for proxy in gone:
            proxy.close()

    def _proxy(self, name, cls):
        with self._proxies_lock:
            proxy = self._proxies.get(name)
        if proxy is None:
            why = wait_for_service(name, self.service_timeout)
            if why:
                raise StepError('service %s is not available within %.1f s: %s' % (name, self.service_timeout, why))
            with self._proxies_lock:
                proxy = self._proxies.setdefault(name, rospy.ServiceProxy(name, cls, persistent=True))
        return proxy

    @staticmethod
    def _record(step, s0, ok, detail):
        """A step's outcome; ``wall`` is when it started (wall clock), ``ms`` how long it took."""
        return {'action': step.action, 'target': step.target, 'ok': ok, 'detail': detail,
                'ms': (time.monotonic() - s0) * 1e3, 'wall': time.time() - (time.monotonic() - s0)}

    @staticmethod
    def _describe(step, info):
        if step.action == 'rebind':
            b = step.detail
            return ('%s -> %s' % (b.port, b.topic) if b.activate else '%s unbound' % b.port) + \
                (' (was %s)' % info if info else '')
        if step.action == 'launch':
            return 'pid %d' % info.pid
        if step.action == 'kill':
            return 'pid %s' % (info.pid if info is not None else None)
        if step.action == 'resume' and isinstance(info, str):
            return info   # a resume whose answer was lost, its gate found open (_resumed_all_the_same)
        return ''

    def _do(self, step):
        action = step.action
        if action == 'suspend':
            answer = self._proxy(step.target + '/suspend', Suspend)(timeout=self.quiesce_timeout, lease=self.lease,
                                                                    owner=self._owner)
            if not answer.success:
                raise StepError('%s could not be suspended: %s' % (step.target, answer.message))
            self._keeper.hold(step.target)
            return answer.held
        if action == 'resume':
            self._keeper.release(step.target)
            answer = self._proxy(step.target + '/resume', Suspend)(owner=self._owner)
            if not answer.success:
                # Its suspension had ended before this resume (lease, someone else): it ran during
                # the rebinds. Said, never taken for a resume (it was, as "was not suspended").
                raise StepError('%s was not suspended by this adaptation any more: %s' % (step.target, answer.message))
            return answer.held
        if action == 'kill':
            return self._kill(step.target, self._prepared_kills.pop(step.target, None))
        if action == 'launch':
            return self._launch(step.detail)
        if action == 'wait_launched':
            return self._wait_launched()
        if action == 'rebind':
            return self._rebind(step.detail)
        if action == 'promote':
            answer = self._proxy(step.target + '/set_promote', SetNodes)(nodes=list(step.detail.nodes))
            if not answer.success:
                raise StepError('%s refused the nodes %s: %s' % (step.target, list(step.detail.nodes), answer.message))
            return list(answer.previous)
        raise ValueError(action)

    def _launch(self, entry):
        plan = self._launches[entry]
        os.makedirs(self.log_dir, exist_ok=True)
        log = os.path.join(self.log_dir, '%s_%d_%d.log' % (os.path.basename(plan.path)[:-7], int(time.time() * 1e3),
                                                           next(self._launch_count)))
        argv = roslaunch('aft_ftm', 'x.launch', **dict(entry.args))
        argv[argv.index('aft_ftm'):argv.index('aft_ftm') + 2] = [plan.path]
        # Under a guard: the nodes stop when the launcher of the site they join stops; required ones
        # (a replacement of a replica site's Before, Proceed or After) fail-stop the site if they die.
        args = dict(entry.args)
        required = str(args.get('required', '')).lower() == 'true'
        argv = guarded(argv, plan.owners, self.guard_poll, self.guard_grace,
                       fail_site=site_of_launch(args) if required else '')
        env = with_tls(os.environ, plan.tls)   # as the party of their site (checked in validate)
        if plan.owners:
            # On the host of the site the nodes join (an emulated host: its network namespace).
            argv, env = run_where(plan.owners[0].pid, argv, env)
        # Started at a lower priority: the imports and set-up of new nodes (a second of CPU each)
        # must not starve the running replicas. Not much lower: under full load a niceness of 10
        # left a new node unable to finish its set-up in 30 s.
        site = LaunchedSite(Site('adaptation', argv, env=env, log_path=log).start(niceness=self.launch_niceness),
                            plan.nodes)
        self.sites.append(site)
        self._run_sites.append(site)
        return site

    def _wait_launched(self):
        """Wait until every launched node is set up (its ~rebind offered: an FTM node offers it last,
        once set up) and its publishers are connected to every subscriber the master knows, but for
        subscribers that do not answer after a while (see :meth:`_wired`). The set-up of a node under
        load takes tens of seconds, so a node registered without its ~rebind is waited for until
        ``launch_timeout``, and the error then names the service missing; a node whose process ended
        (its roslaunch runs on: the node is not required) never offers it, and ends the wait at once
        (it held the pause, or the turn, for the whole timeout: review of session 48)."""
        started = time.monotonic()
        deadline = started + self.launch_timeout
        pending = [(site, name) for site in self._run_sites for name in site.nodes]
        silent = {}
        while pending:
            stop = stop_reason(self._interrupted, self._lost())
            if stop:   # seconds of waiting: an interrupt or a lost suspension does not wait for its end
                raise StepError(stop)
            for site, _ in pending:
                if not site.alive():
                    raise StepError('the roslaunch of %s exited (a node failed to start%s): see %s'
                                    % (', '.join(site.nodes), self._why_launch_ended(site), site.log_path))
            nodes, services = self._graph()
            lenient = time.monotonic() - started > self.SILENT_AFTER
            pending = [(s, n) for s, n in pending if not (n + '/rebind' in services and
                                                          self._wired(n, silent if lenient else None))]
            for site in collections.OrderedDict((s, None) for s, _ in pending):
                ended = site.ended()   # (what the master still lists of them is a dead process's)
                gone = [n for s, n in pending if s is site and n in ended]
                if gone:
                    said = last_errors(site.output())
                    raise StepError('%s: not set up%s (see %s)' % (', '.join(
                        '%s %s before %s' % (n, ended[n], 'its publishers were connected' if n + '/rebind' in services
                                             else 'it offered %s/rebind' % n) for n in gone),
                        '; ' + said if said else '', site.log_path))
            if not pending:
                break
            if time.monotonic() > deadline:
                raise StepError('not set up within %g s: %s (see %s)' % (
                    self.launch_timeout, '; '.join(self._not_set_up(n, nodes, services) for _, n in pending),
                    pending[0][0].log_path))
            time.sleep(0.02)
        refused = []
        for site in self._run_sites:   # set up: back to the priority of the nodes they join
            refused += site.set_niceness(0)
        if refused:
            self.log('warning: the new nodes keep niceness %d (no privilege to lower it back): pids %s'
                     % (self.launch_niceness, refused))
        return len(self._launched_names)

    @staticmethod
    def _not_set_up(node, nodes, services):
        """What a launched node lacks, past the launch timeout."""
        if node not in nodes:
            return '%s is not registered with the master' % node
        if node + '/rebind' not in services:
            return ('%s is registered with the master but offers no %s/rebind (still in its set-up, or '
                    'no FTM node)' % (node, node))
        return '%s: its publishers are not connected to every subscriber' % node

    def _wired(self, node, silent=None):
        """wired(node); with ``silent`` (a dict kept over one wait), the subscribers node is not
        connected to and that do not answer their XML-RPC API are not waited for. A site powered
        off leaves its nodes registered until someone cleans the master: a new publisher never
        connects to them. Nothing is unregistered here (a node slow to answer may be alive)."""
        lacking = unwired(node, rospy.get_name())   # one look at the master and the node
        if lacking == {}:
            return True
        if silent is None or lacking is None:
            return False
        missing = set().union(*lacking.values())
        master = self.master
        for sub in missing - set(silent):
            try:
                node_api(master.lookupNode(sub), 0.5).getPid(rospy.get_name())
            except Exception:   # no answer: a registration left behind
                silent[sub] = True
                self.log('warning: %s does not answer: %s is not kept waiting for it' % (sub, node))
        return not (missing - set(silent))

    @staticmethod
    def _why_launch_ended(site):
        try:
            with open(site.log_path) as f:
                why = launch_failure(f.read())
        except (OSError, TypeError):   # no log kept
            return ''
        return ': ' + why if why else ''

    def _kill_record(self, node):
        """(psutil.Process, Killed) of node: the pid its API gives, checked to be that node's process,
        and how to start it again (for a rollback). Raises StepError if it cannot be recorded."""
        try:
            uri = self.master.lookupNode(node)   # checked again: it may have been registered anew since
            pid = visible_pid(uri, rospy.get_name(), node)
            if pid is None:
                raise NotTheNode('it is registered at %s, on another machine' % uri)
            proc = psutil.Process(pid)
            # Started again, it stops with its site too (its owners).
            return proc, Killed(pid, proc.cmdline(), proc.cwd(), proc.environ(), owners_of_process(pid))
        except Exception as e:   # cannot record: killing it could not be undone
            raise StepError('cannot find the process of %s (%s): not killed' % (node, e))

    def _kill(self, node, prepared=None):
        """Stop the node's process with SIGINT (as roslaunch stops its nodes; SIGKILL 5 s later), after
        checking that the pid its API gives is that node's process, and recording how to start it again
        (for a rollback; ``prepared``: (process, record) made before any node of its group was signalled,
        or the StepError that made). Not over XML-RPC (rosnode kill): a node under TLS refuses every
        shutdown asked that way, since anyone on the network can ask. Nothing raises once the signal is
        sent: the node is killed, and its record is what the rollback needs (a failure after it lost
        the record, and the rollback did not start the node again: review of session 35)."""
        self._keeper.release(node)   # retired: nothing of it to renew or to find still suspended
        if isinstance(prepared, Exception):
            raise prepared
        proc, record = prepared if prepared is not None else self._kill_record(node)
        pid = record.pid
        try:   # where it is registered now: what its death leaves with the master, if it never unregisters
            uri = self.master.lookupNode(node)
        except Exception:   # not registered, or the master not answering: nothing of it to remove later
            uri = None
        # A node an adaptation started: its guard, disarmed, lets it go. A node of the site's own launch:
        # marked, its crash detector lets it die (aft_ftm.site_watch).
        if disarm_guard_of(pid) is None:
            try:
                mark_retired(pid)
            except OSError as e:
                raise StepError('cannot mark %s (pid %d) retired (%s): not killed, its site would fail over'
                                % (node, pid, e))
        try:
            proc.send_signal(signal.SIGINT)
        except psutil.NoSuchProcess:
            pass   # gone by itself meanwhile: killed all the same
        try:
            alive = wait_dead([proc], 5.0)
            if alive:
                proc.kill()
                alive = wait_dead([proc], 2.0)
            if not alive:
                self._forget_dead(node, uri, pid)
            wait_until(lambda: node not in self._graph()[0], 5.0, 0.02)
        except Exception as e:   # (the master unreachable, the process gone): killed all the same
            self.log('kill %s: after its signal: %s: %s' % (node, type(e).__name__, e))
        return record

    def _forget_dead(self, node, uri, pid):
        """The registrations a dead node left with the master removed at once. A node that ends on its
        SIGINT unregisters itself; one SIGKILLed (by the engine, 5 s later, or by a fault before the
        kill) never does, and the wait for it to leave the master held the pause for its whole 5 s.
        Removed only while the name is still registered at the URI the node had before its signal,
        and nothing listens there any more (connection refused): a name registered anew, or an answer
        that is only slow, keeps it."""
        if uri is None:
            return
        try:
            if self.master.lookupNode(node) != uri:
                return
        except Exception:   # unregistered meanwhile: nothing left
            return
        try:
            visible_pid(uri, rospy.get_name(), node)
            return   # a process answers there as the node: registered anew, it keeps the name
        except ConnectionRefusedError:   # nothing listens there: the registration is the dead one's
            pass
        except Exception:   # a slow answer, another program on the port: not known to be stale, kept
            return
        answered = unregister(self.master, [node], {node: uri})
        self.log('kill %s: its process ended without unregistering: its registrations removed from the master '
                 '(%d removal(s) answered)' % (node, answered))

    # -- rollback -------------------------------------------------------------------------------
    def _undo(self, step):
        return self._bounded(step, lambda: self._undo_step(step), self._call_limit(
            {'restore_binding': 'rebind', 'restore_promote': 'promote'}.get(step.action, step.action)))

    def _undo_step(self, step):
        if step.action == 'resume':
            self._keeper.release(step.target)
            answer = self._proxy(step.target + '/resume', Suspend)(owner=self._owner)
            # Not suspended (any more), or suspended by another owner: nothing of this run's to resume.
            return '%s, %d held messages delivered' % (answer.message, answer.held)
        if step.action == 'stop_launch':
            site = step.detail
            # Site.stop signals the tree only while the launch is not reaped: once reaped (its
            # failure seen by _wait_launched), its pid may be another process's (review of stop 39).
            site.stop(grace=5.0)
            if site in self.sites:
                self.sites.remove(site)
            return 'stopped %s' % ', '.join(site.nodes)
        if step.action == 'respawn':
            record = step.detail
            # A stage of a replica site, started again: its death is the site's failure, as it was.
            argv = guarded(record.cmdline, record.owners, self.guard_poll, self.guard_grace,
                           fail_site=step.target.strip('/').split('/')[0] if record.owners else '')
            env = record.env
            if record.owners:   # on its site's host, as it was (its party in its recorded environment)
                argv, env = run_where(record.owners[0].pid, argv, env)
            os.makedirs(self.log_dir, exist_ok=True)
            # The node's own working directory, given to its process (never this one's: it has threads).
            site = Site('respawn', argv, env=env, cwd=record.cwd,
                        log_path=os.path.join(self.log_dir, 'respawn_%d.log' % record.pid)).start()
            self.respawned.append(site)
            deadline = time.monotonic() + RESPAWN_TIMEOUT
            while True:
                if not site.alive():   # it will never be set up: said at once, not after the whole wait
                    said = last_errors(site.output())
                    raise StepError('%s started again (pid %d) but its process exited before it was set up%s '
                                    '(see %s)' % (step.target, site.pid, '; ' + said if said else '', site.log_path))
                lacks = self._respawn_lacks(step.target, record, site.pid)
                if not lacks:
                    return 'started again, pid %d' % site.pid
                if time.monotonic() > deadline:
                    raise StepError('%s started again (pid %d) but not set up within %g s: %s'
                                    % (step.target, site.pid, RESPAWN_TIMEOUT, lacks))
                time.sleep(0.05)
        if step.action in ('restore_binding', 'restore_promote') and (
                step.detail is UNKNOWN or isinstance(step.detail, tuple) and step.detail[1] is UNKNOWN):
            raise StepError('its %s got no answer in time and may have been carried out later: what it replaced '
                            'is not known, so it is not undone; check %s by hand' % (
                                'rebind' if step.action == 'restore_binding' else 'promotion', step.target))
        if step.action == 'restore_binding':
            bind, previous = step.detail
            restore = adaptation.Bind(bind.node, bind.port, previous, bind.direction, bool(previous))
            self._rebind(restore)
            return 'port %s %s' % (bind.port, 'bound to %s again' % previous if previous else 'unbound again')
        if step.action == 'restore_promote':
            answer = self._proxy(step.target + '/set_promote', SetNodes)(nodes=list(step.detail))
            if not answer.success:
                raise StepError(answer.message)
            return 'promotes %s again' % list(step.detail)
        raise ValueError(step.action)

    @staticmethod
    def _offers_rebind(record):
        return any('aft_ftm' in part for part in record.cmdline)

    def _respawn_lacks(self, node, record, root):
        """'' once node, started again by a rollback as process ``root`` (or a process under it: its
        guard's child), is set up: it offers its ~rebind (an FTM node offers it last, once set up), or,
        another node, is registered; and that registration is the new process's. Else what it lacks.

        A node killed with SIGKILL never unregisters: its name, its services and its URI stay with the
        master until a process registers under that name anew (the master then drops them all). Taken
        for the new node, they had the rollback say the node was started again while the new process
        was still starting, or had failed, and the next undo call a dead URI. So the registered URI is
        asked for its pid: a dead process's answers nothing, and the pid must be the new process's."""
        nodes, services = self._graph()
        if node not in nodes:
            return '%s is not registered with the master' % node
        if self._offers_rebind(record) and node + '/rebind' not in services:
            return '%s is registered but offers no %s/rebind (still in its set-up)' % (node, node)
        try:
            uri = self.master.lookupNode(node)
        except Exception as e:   # unregistered meanwhile
            return '%s cannot be looked up: %s' % (node, e)
        try:
            pid = visible_pid(uri, rospy.get_name(), node)
        except Exception as e:   # nothing answers there (NotTheNode: another process does)
            return ('%s is registered at %s, which is not the new process (the registration its killed '
                    'predecessor, pid %d, left?): %s' % (node, uri, record.pid, e))
        if pid is None or (pid != root and pid not in [p.pid for p in process_tree(root)]):
            return '%s is registered at %s by pid %s, not by the process started again' % (node, uri, pid)
        return ''

    def stop_all(self):
        """Stop every process this engine started, those of runs done too (tests and benchmarks, which
        tear the whole deployment down). Never raises."""
        for site in self.sites + self.respawned:
            site.stop(grace=5.0)
        self.sites, self.committed, self.respawned = [], [], []

    def shutdown(self, wait=5.0):
        """The engine's process stops (the monitor's shutdown): a run in progress is interrupted and
        given ``wait`` seconds to roll back, then what an unfinished run launched is stopped. What runs
        done launched, and nodes a rollback started again, are the sites' now and go on running: the
        monitor's shutdown killed them, and the sites heartbeat on while every request hung (review of
        session 35). Never raises."""
        tx = self.transaction
        if tx is not None and tx.state not in TERMINAL:
            self.interrupt('the engine stops')
            wait_until(lambda: tx.state in TERMINAL, wait, 0.05)
        for site in [site for site in self.sites if site not in self.committed]:
            try:
                site.stop(grace=5.0)
            except Exception:   # shutdown paths never raise
                pass
        self.sites = list(self.committed)
