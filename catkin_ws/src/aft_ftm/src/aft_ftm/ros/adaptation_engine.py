"""The Adaptation Engine: runs an adaptation script against the live ROS graph.

It checks the whole script against the graph before touching anything (nodes exist and offer
the services the steps need, launch files exist and load with their arguments, the nodes they
start do not clash with running ones, every rebind of an existing node would be accepted: the
node itself answers a dry run, naming both types when a topic has the wrong one). It then runs
the planned steps (:func:`aft_ftm.adaptation.plan`); when one fails, it undoes what was done in
reverse order and resumes everything it suspended, and reports it.

Uses the master API, the nodes' services and XML-RPC, psutil and roslaunch processes; it needs
an initialised rospy node (the ``adapt`` command and the monitor are ones).
"""
import itertools
import os
import threading
import time

import psutil
import rosgraph
import rosnode
import rospkg
import rospy
from aft_msgs.srv import Rebind, RebindRequest, SetNodes, Suspend

from .. import adaptation
from ..adaptation import ScriptError, StepError
from ..sites import Site, launch_failure, terminate_tree, wait_dead, wait_until
from .deployment import roslaunch, wired
from .fencing import is_local, node_api


def resolve_launch_file(spec):
    """``package/file.launch`` (found in the package's launch/ folder or anywhere in it) or a path."""
    if os.path.isfile(spec):
        return os.path.abspath(spec)
    package, _, name = spec.partition('/')
    try:
        root = rospkg.RosPack().get_path(package)
    except rospkg.ResourceNotFound:
        raise ScriptError('launch file %s: no such file, and no ROS package %r' % (spec, package))
    for folder, _, files in os.walk(root):
        if name in files:
            return os.path.join(folder, name)
    raise ScriptError('launch file %s: package %s has no file %s' % (spec, package, name))


def launch_nodes(path, args):
    """The absolute names of the nodes a launch file starts with these arguments (it must load)."""
    import roslaunch.config
    import roslaunch.xmlloader
    config = roslaunch.config.ROSLaunchConfig()
    loader = roslaunch.xmlloader.XmlLoader()
    loader.ignore_unset_args = False
    try:
        loader.load(path, config, argv=['%s:=%s' % a for a in args], verbose=False)
    except Exception as e:   # roslaunch raises several kinds; all mean "this launch cannot start"
        raise ScriptError('launch file %s does not load with %s: %s'
                          % (path, ' '.join('%s:=%s' % a for a in args) or 'no arguments', e))
    return [rosgraph.names.ns_join(n.namespace, n.name) for n in config.nodes], config


class Engine(object):
    """Runs scripts. ``log`` is a function of one string (the ``adapt`` command prints)."""

    def __init__(self, log=None, quiesce_timeout=5.0, launch_timeout=60.0, service_timeout=5.0,
                 connect_timeout=2.0, log_dir=None, launch_niceness=5):
        self.log = log or (lambda text: rospy.loginfo(text))
        self.quiesce_timeout = quiesce_timeout
        self.launch_timeout = launch_timeout
        self.service_timeout = service_timeout
        self.connect_timeout = connect_timeout
        self.launch_niceness = launch_niceness
        self.log_dir = log_dir or os.path.join(rospkg.get_log_dir(), 'aft_adaptations')
        self.sites = []            # roslaunch processes started by this engine and still running
        self._launch_count = itertools.count()
        self.respawned = []        # nodes started again from their command line by a rollback

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

    # -- validation -----------------------------------------------------------------------------
    def validate(self, script, mode):
        """Check script against the live graph; returns the plan. Raises ScriptError naming the
        problem; nothing is changed."""
        steps = adaptation.plan(script, mode)
        self._proxies = {}
        nodes, services = self._graph()
        launched = []
        self._launch_configs = {}
        for entry in script.launch:
            path = resolve_launch_file(entry.file)
            names, _ = launch_nodes(path, entry.args)
            clash = sorted(set(names) & nodes)
            if clash:
                raise ScriptError('launch file %s would start %s, already running (a second node of the same '
                                  'name stops the first): choose other names' % (entry.file, ', '.join(clash)))
            self._launch_configs[entry] = (path, names)
            launched += names

        def need(node, service, why):
            if node in launched:
                return
            if node not in nodes:
                raise ScriptError('unknown node %s (%s): it is not running' % (node, why))
            if node + '/' + service not in services:
                raise ScriptError('node %s offers no %s service (%s): is it an FTM node?' % (node, service, why))
        for node in script.suspend:
            need(node, 'suspend', 'to suspend')
        for node in script.retire:
            if node not in nodes:
                raise ScriptError('unknown node %s (to retire): it is not running' % node)
            try:
                uri = self.master.lookupNode(node)
            except Exception as e:
                raise ScriptError('node %s (to retire) cannot be looked up: %s' % (node, e))
            if not is_local(uri):
                raise ScriptError('node %s (to retire) runs on another host (%s): the engine kills, and '
                                  'restarts on a rollback, only nodes of its own host' % (node, uri))
        for bind in script.bind:
            need(bind.node, 'rebind', 'to rebind its port %s' % bind.port)
            if bind.node not in launched:
                try:
                    self._rebind(bind, dry_run=True)
                except (StepError, rospy.ServiceException, rospy.ROSException) as e:
                    raise ScriptError('%s does not answer its rebind service: %s' % (bind.node, e))
        for promote in script.promote:
            need(promote.recovery, 'set_promote', 'to change the nodes it promotes')
            for node in promote.nodes:
                if node not in launched and node not in nodes:
                    raise ScriptError('unknown node %s (for %s to promote)' % (node, promote.recovery))
        self._launched_names = launched
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

    # -- running --------------------------------------------------------------------------------
    def run(self, script, mode='prepared'):
        """Validate, then run the script. Returns a report (dict). Raises ScriptError (invalid:
        nothing changed); a failed step is rolled back and reported with ok=False.

        Consecutive steps of the same action run in parallel, except suspensions, which follow
        the script's order (a backup's After is suspended after the primary's Protocol is
        quiescent, so the last checkpoint is in when it applies it).
        """
        t0 = time.monotonic()
        steps = self.validate(script, mode)
        report = {'script': script.name, 'kind': script.kind, 'mode': mode, 'ok': True, 'steps': [],
                  'rolled_back': False, 'error': '', 'validated_s': time.monotonic() - t0}
        self.log('adaptation %s (%s, %s order): %d steps' % (script.name, script.kind, mode, len(steps)))
        self._sites_of_run = []
        done = []
        pause_start = pause_end = None
        report['cleanup_errors'] = []
        cleanup = adaptation.cleanup_steps(steps)
        for group in adaptation.groups(steps):
            if group[0] in cleanup:
                # Resumed: the new configuration serves. What is left (killing the old nodes) is
                # cleanup; undoing the adaptation now would rebind a live graph, so failures here
                # are reported, not rolled back.
                for step, s0, error, info in self._run_group(group):
                    report['steps'].append(self._record(step, s0, error is None,
                                                        self._describe(step, info) if error is None else error))
                    if error is not None:
                        report['cleanup_errors'].append('%s %s: %s' % (step.action, step.target, error))
                        self.log('cleanup step %s %s failed: %s (the adaptation stands)' % (
                            step.action, step.target, error))
                continue
            if group[0].action == 'suspend' and pause_start is None:
                self._connect(steps)   # persistent connections, opened before the pause
                pause_start = time.monotonic()
            results = self._run_group(group)
            failed = [r for r in results if r[2] is not None]
            for step, s0, error, info in results:
                if error is None or step.action == 'suspend':
                    # A suspension that failed may still have closed the node's gate (its answer
                    # lost): the rollback resumes it too, which is harmless on a running node.
                    done.append((step, info))
                report['steps'].append(self._record(step, s0, error is None,
                                                    self._describe(step, info) if error is None else error))
            if failed:
                step, _, error, _ = failed[0]
                report.update(ok=False, error='step %s %s failed: %s' % (step.action, step.target, error))
                self.log('FAILED: %s: rolling back' % report['error'])
                report['rollback'] = self._roll_back(done)
                report['rolled_back'] = True
                pause_end = self._resumed_at   # clients wait until the rollback resumed them
                break
            if group[-1].action == 'resume' and not any(s.action == 'resume' for s in steps[steps.index(group[-1]) + 1:]):
                pause_end = time.monotonic()
        if pause_start is not None and pause_end is None:
            pause_end = time.monotonic()
        report['pause_s'] = (pause_end - pause_start) if pause_start is not None else 0.0
        report['duration_s'] = time.monotonic() - t0
        report['nodes_touched'] = script.nodes_touched(self._launched_names)
        report['launched_pids'] = [s.pid for s in self._sites_of_run if s.alive()]
        self.log('adaptation %s %s: pause %.1f ms, %.2f s in all, %d nodes touched' % (
            script.name, 'done' if report['ok'] else 'ROLLED BACK', report['pause_s'] * 1e3,
            report['duration_s'], len(report['nodes_touched'])))
        return report

    def _run_group(self, group):
        """Run steps (in parallel if more than one); returns [(step, start, error or None, info)]."""
        results = [None] * len(group)

        def one(i, step):
            s0 = time.monotonic()
            try:
                results[i] = (step, s0, None, self._do(step))
            except (StepError, ScriptError, rospy.ServiceException, rospy.ROSException) as e:
                self._forget_proxies(step.target)   # rospy keeps a broken persistent connection
                results[i] = (step, s0, str(e), None)
            except Exception as e:   # an unexpected error is still a failed step, rolled back
                results[i] = (step, s0, '%s: %s' % (type(e).__name__, e), None)
        if len(group) == 1:
            one(0, group[0])
        else:
            threads = [threading.Thread(target=one, args=(i, s)) for i, s in enumerate(group)]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
        return results

    def _connect(self, steps):
        """Open persistent connections to the services the pause will call, by no-op calls
        (a resume of a running node, a dry-run rebind), so that the pause pays no connection set-up."""
        for step in steps:
            try:
                if step.action in ('suspend', 'resume'):
                    # Probes: they answer and change nothing, whoever has the node suspended.
                    self._proxy(step.target + '/suspend', Suspend)(probe=True)
                    self._proxy(step.target + '/resume', Suspend)(probe=True)
                elif step.action == 'rebind' and step.target in self._graph_nodes():
                    self._rebind(step.detail, dry_run=True)
                elif step.action == 'promote':
                    self._proxy(step.target + '/set_promote', SetNodes)
            except Exception:   # not reachable yet (paper order: launched in the pause): connect then
                self._proxies.pop(step.target + '/rebind', None)

    def _forget_proxies(self, node):
        for name in [n for n in getattr(self, '_proxies', {}) if n.startswith(node + '/')]:
            self._proxies.pop(name).close()

    def _graph_nodes(self):
        if not hasattr(self, '_nodes_cache') or time.monotonic() - self._nodes_cache[0] > 0.5:
            self._nodes_cache = (time.monotonic(), self._graph()[0])
        return self._nodes_cache[1]

    def _proxy(self, name, cls):
        proxy = getattr(self, '_proxies', {}).get(name)
        if proxy is None:
            try:
                rospy.wait_for_service(name, self.service_timeout)
            except rospy.ROSException:
                raise StepError('service %s is not available' % name)
            proxy = rospy.ServiceProxy(name, cls, persistent=True)
            if hasattr(self, '_proxies'):
                self._proxies[name] = proxy
        return proxy

    def _record(self, step, s0, ok, detail):
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
            return 'pid %s' % (info or {}).get('pid')
        return ''

    def _do(self, step):
        action = step.action
        if action == 'suspend':
            answer = self._proxy(step.target + '/suspend', Suspend)(timeout=self.quiesce_timeout)
            if not answer.success:
                raise StepError('%s could not be suspended: %s' % (step.target, answer.message))
            return answer.held
        if action == 'resume':
            answer = self._proxy(step.target + '/resume', Suspend)()
            return answer.held
        if action == 'kill':
            return self._kill(step.target)
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
        path, names = self._launch_configs[entry]
        os.makedirs(self.log_dir, exist_ok=True)
        log = os.path.join(self.log_dir, '%s_%d_%d.log' % (os.path.basename(path)[:-7], int(time.time() * 1e3),
                                                           next(self._launch_count)))
        argv = roslaunch('aft_ftm', 'x.launch', **dict(entry.args))
        argv[argv.index('aft_ftm'):argv.index('aft_ftm') + 2] = [path]
        # Started at a lower priority: the imports and set-up of new nodes (a second of CPU each)
        # must not starve the running replicas. Not much lower: under full load a niceness of 10
        # left a new node unable to finish its set-up in 30 s.
        site = Site('adaptation', argv, log_path=log).start(niceness=self.launch_niceness)
        site.nodes = names
        self.sites.append(site)
        self._sites_of_run.append(site)
        return site

    def _wait_launched(self):
        """Wait until every launched node is set up (its ~rebind offered, or registered if it has
        none) and its publishers are connected to every subscriber the master knows."""
        deadline = time.monotonic() + self.launch_timeout
        pending = [(site, name) for site in self._sites_of_run for name in site.nodes]
        while pending:
            for site, _ in pending:
                if not site.alive():
                    raise StepError('the roslaunch of %s exited (a node failed to start%s): see %s'
                                    % (', '.join(site.nodes), self._why_launch_ended(site), site.log_path))
            _, services = self._graph()
            pending = [(s, n) for s, n in pending if not (n + '/rebind' in services and wired(n))]
            if not pending:
                break
            if time.monotonic() > deadline:
                raise StepError('not set up within %.0f s: %s (see %s)' % (
                    self.launch_timeout, ', '.join(n for _, n in pending), pending[0][0].log_path))
            time.sleep(0.02)
        refused = []
        for site in self._sites_of_run:   # set up: back to the priority of the nodes they join
            refused += site.set_niceness(0)
        if refused:
            self.log('warning: the new nodes keep niceness %d (no privilege to lower it back): pids %s'
                     % (self.launch_niceness, refused))
        return len(self._launched_names)

    @staticmethod
    def _why_launch_ended(site):
        try:
            with open(site.log_path) as f:
                why = launch_failure(f.read())
        except (OSError, TypeError):   # no log kept
            return ''
        return ': ' + why if why else ''

    def _kill(self, node):
        """rosnode kill, after recording how to start the node again (for a rollback)."""
        record = {}
        try:
            uri = self.master.lookupNode(node)
            code, _, pid = node_api(uri, 1.0).getPid(rospy.get_name())
            proc = psutil.Process(pid)
            record = {'pid': pid, 'cmdline': proc.cmdline(), 'cwd': proc.cwd(), 'env': proc.environ()}
        except Exception as e:   # cannot record: killing it could not be undone
            raise StepError('cannot find the process of %s (%s): not killed' % (node, e))
        _, failed = rosnode.kill_nodes([node])
        if failed:
            raise StepError('rosnode kill %s failed' % node)
        alive = wait_dead([proc], 5.0)
        if alive:
            proc.kill()
            wait_dead([proc], 2.0)
        wait_until(lambda: node not in self._graph()[0], 5.0, 0.02)
        return record

    # -- rollback -------------------------------------------------------------------------------
    def _roll_back(self, done):
        results = []
        self._resumed_at = None
        for step in adaptation.undo_plan(done):
            if step.action == 'stop_launch' and self._resumed_at is None:
                self._resumed_at = time.monotonic()
            try:
                detail = self._undo(step)
                ok = True
            except Exception as e:   # keep undoing the rest: each failure is reported
                detail, ok = str(e), False
            results.append({'action': step.action, 'target': step.target, 'ok': ok, 'detail': detail})
            self.log('  rollback %s %s: %s%s' % (step.action, step.target, 'ok' if ok else 'FAILED ', detail))
        return results

    def _undo(self, step):
        if step.action == 'resume':
            return 'resumed, %d held messages delivered' % self._do(step)
        if step.action == 'stop_launch':
            site = step.detail
            terminate_tree(site.pid, grace=5.0)
            site.stop()
            if site in self.sites:
                self.sites.remove(site)
            return 'stopped %s' % ', '.join(site.nodes)
        if step.action == 'respawn':
            record = step.detail
            site = Site('respawn', record['cmdline'], env=record['env'],
                        log_path=os.path.join(self.log_dir, 'respawn_%d.log' % record['pid']))
            os.makedirs(self.log_dir, exist_ok=True)
            prev = os.getcwd()
            os.chdir(record['cwd'])
            try:
                site.start()
            finally:
                os.chdir(prev)
            self.respawned.append(site)
            if not wait_until(lambda: step.target + '/rebind' in self._graph()[1] or
                              (step.target in self._graph()[0] and not self._offers_rebind(record)), 30.0, 0.05):
                raise StepError('%s started again (pid %d) but not set up within 30 s' % (step.target, site.pid))
            return 'started again, pid %d' % site.pid
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
        return any('aft_ftm' in part for part in record.get('cmdline', []))

    def stop_all(self):
        """Stop every process this engine started (tests and benchmarks). Never raises."""
        for site in self.sites + self.respawned:
            site.stop(grace=5.0)
        self.sites, self.respawned = [], []
