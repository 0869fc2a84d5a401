"""Running one scenario of the car case study, start to finish, on a ROS master of its own.

The run's processes, each a site (aft_ftm.sites) so that a fault can kill exactly one of them:
the master, the recorder (rosbag), the car (car.launch: simulator, TJP, Emergency Braking,
mechanisms) and one or two boards (board.launch: controllerPid, and with PBR its After and crash
detector). The runner is itself a ROS node on simulated time: it injects the faults that kill
processes (a board's power loss, the simulator's or the master's crash), starts a board again (it
re-joins as the backup) and runs adaptations, at their scenario times. Afterwards it reads the bag
back, and writes the summary (JSON) and the plot.

A scenario's own master makes every run independent, and lets a scenario kill the master.
"""
import contextlib
import functools
import glob
import json
import os
import re
import signal
import socket
import subprocess
import threading
import time
import uuid
import warnings

import psutil
import rosbag
import rosgraph
import rospy
from aft_msgs.msg import Alarm, CarCommand, CarState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from aft_ftm.ros.graph import unwired
from aft_ftm.sites import Site, process_tree, wait_dead, wait_until

from .. import resources
from .. import scenario as scenarios
from .. import summary as summaries

TOPICS = ['/car/state', '/car/command', '/tjp/pid_command', '/tjp/events', '/aft/alarms', '/tjp/gap',
          '/tjp/safety_distance', '/tjp/speed', '/sensors/imu', '/sensors/laser_0', '/sensors/laser_1',
          '/sensors/laser_2', '/sensors/ultrasonic', '/tjp/emergency', '/tjp/safe_stop', '/tjp/service_manager/events']
CAR_NODES = ['/car_sim', '/tjp/measure_manager', '/tjp/distance_security_calculator', '/tjp/command_manager',
             '/tjp/emergency_braking']
MECHANISM_NODES = {'tr_imu': ['/ftm/imu_tr'], 'triplication_vote': ['/ftm/laser_vote'],
                   'alarm_and_stop': ['/ftm/alarm_manager'], 'pbr': ['/ftm/watchdog'], 'tr_ultrasonic': []}
RECORDER = '/tjp_record'
HAZARD_MARGIN_S = 1.0   # road time a control experiment runs on after its hazard has shown
RUNNER = '/tjp_scenario_runner'
ADAPT_GRACE = 8.0   # s of wall time an adaptation is given to report before the run ends
AFTER_TIMEOUT = 0.5   # road time (s) a board's After may give no sign of life before its board fail-stops


class RunError(Exception):
    pass


def free_port():
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def board_nodes(board, pbr):
    return ['/%s/controller_pid' % board] + (['/%s/cycle_after' % board, '/%s/crash_detector' % board] if pbr else [])


class ScenarioRun(object):
    """One run of a scenario (a dict from tjp_sim.scenario) into directory out."""

    def __init__(self, scenario, path, out, gui=False, log=print, setup_timeout=90.0, until_hazard=None,
                 tls_policy=None):
        self.scenario, self.path, self.out, self.gui, self.log = scenario, path, out, gui, log
        self.until_hazard = until_hazard   # end the run once this hazard has shown (a control experiment)
        self.live = None
        self.setup_timeout = setup_timeout
        self.pbr = 'pbr' in scenario['mechanisms']
        self.sites = {}
        self.port = free_port()
        self.env = dict(os.environ, ROS_MASTER_URI='http://127.0.0.1:%d' % self.port,
                        ROS_LOG_DIR=os.path.join(out, 'logs'))
        self.bag = os.path.join(out, 'run.bag')
        self.done = set()
        self.simulator_killed = False   # the clock is then expected to stop: the run ends sooner
        self.threads = []
        self.finished = threading.Event()   # the run's loop ended: threads waiting on simulated time stop
        self.adaptations = []
        self.engines = []    # adaptation engines: what they launched is stopped with the run
        self.intrusions = []  # what each intruder reported (aft_ftm.ros.intruder.sweep)
        # Mutual TLS (issue 16): the car, each board and the operator (this runner, the adaptation
        # engine in it and what the engine starts) are parties with certificates of their own.
        self.tls_policy = tls_policy
        self.tls_dir = os.path.join(out, 'tls') if tls_policy else None

    # -- processes -------------------------------------------------------------------------------
    TLS_PARTIES = ('car', 'board_a', 'board_b', 'operator', 'recorder', 'intruder')

    def _make_tls(self):
        from aft_ftm import tls
        authority = os.path.join(self.tls_dir, 'authority')   # the CA's key stays here
        tls.make_authority(authority)
        for party in self.TLS_PARTIES:
            tls.issue(authority, party)
            tls.export_party(authority, party, os.path.join(self.tls_dir, party))

    def tls_env(self, party, base=None):
        """The environment of a process of party under this run's TLS (base, default the run's)."""
        env = dict(self.env if base is None else base)
        if self.tls_policy and party:
            env.update(AFT_TLS_DIR=os.path.join(self.tls_dir, party), AFT_TLS_PARTY=party,
                       AFT_TLS_POLICY=self.tls_policy)
        return env

    def _site(self, name, argv):
        party = name if name in self.TLS_PARTIES else None   # the master: no TLS
        env = self.tls_env(party)
        if self.scenario.get('boards_remote') and name in scenarios.BOARD_HOSTS:
            # A host of its own: its nodes bound to its address, its heartbeats naming it (not this host).
            env.update(ROS_IP=scenarios.BOARD_HOSTS[name])
            env.pop('ROS_HOSTNAME', None)
        site = Site(name, argv, env=env, log_path=os.path.join(self.out, 'logs', name + '.log'))
        self.sites[name] = site.start()
        return site

    def _launch_args(self):
        args = ['scenario:=%s' % os.path.abspath(self.path), 'gui:=%s' % str(self.gui).lower()]
        args += ['%s:=%s' % (m, str(m in self.scenario['mechanisms']).lower()) for m in scenarios.MECHANISMS]
        return args + ['managed_tjp:=%s' % str(self.scenario['managed_tjp']).lower()]

    def _forget_last_run_of_the_manager(self):
        """Each run is a new car: the record the service manager of the last run left (powered off at its
        end, as a car is) must not hold its safe state or its services down in this one."""
        from aft_service_manager import trust
        record = os.path.join(trust.default_state_dir(self.env), 'manager_tjp_service_manager.record')
        try:
            os.unlink(record)
        except OSError:   # none left
            pass

    def expected_nodes(self):
        nodes = CAR_NODES + board_nodes('board_a', self.pbr) + (board_nodes('board_b', True) if self.pbr else [])
        for mechanism in self.scenario['mechanisms']:
            nodes += MECHANISM_NODES[mechanism]
        if self.scenario['managed_tjp']:
            nodes.append('/tjp/service_manager')
        return nodes

    def start(self):
        os.makedirs(os.path.join(self.out, 'logs'), exist_ok=True)
        if self.tls_policy:
            self._make_tls()
        self._site('master', ['rosmaster', '--core', '-p', str(self.port)])
        master = rosgraph.Master(RUNNER, master_uri=self.env['ROS_MASTER_URI'])
        if not wait_until(lambda: self._answers(master), 20.0):
            raise RunError('the ROS master on port %d did not start' % self.port)
        master.setParam('/use_sim_time', True)
        master.setParam('/run_id', str(uuid.uuid4()))   # the launches started at once must share one
        if self.tls_policy:   # rosbag record has no TLS: a rospy recorder that has
            self._site('recorder', ['rosrun', 'tjp_sim', 'recorder', '-O', self.bag, '__name:=' + RECORDER[1:]] + TOPICS)
        else:
            self._site('recorder', ['/usr/lib/rosbag/record', '-O', self.bag, '--tcpnodelay',
                                    '__name:=' + RECORDER[1:]] + TOPICS)
        if self.scenario['managed_tjp']:
            self._forget_last_run_of_the_manager()
        self._site('car', ['roslaunch', 'tjp_sim', 'car.launch'] + self._launch_args())
        self._site('board_a', self._board_argv('board_a', 'primary'))
        if self.pbr:
            self._site('board_b', self._board_argv('board_b', 'backup'))
        # The runner's own node, on simulated time, on this run's master.
        os.environ.update(ROS_MASTER_URI=self.env['ROS_MASTER_URI'])
        if self.tls_policy:
            from aft_ftm.ros.params import secure_from_environment
            os.environ.update(self.tls_env('operator', {}))
            secure_from_environment()
        # A publisher rospy gave up on (a duplicate connection closed in its TLS handshake: the alarms of
        # distanceSecurityCalculator once, and the demo's adaptation never came) is connected again.
        from aft_ftm.ros.subscription_keeper import keep_subscriptions
        keep_subscriptions()
        rospy.init_node(RUNNER[1:], disable_signals=True)
        with warnings.catch_warnings():   # queue_size=None is chosen: publish synchronously, drop nothing
            warnings.simplefilter('ignore')
            self.events = rospy.Publisher('/tjp/events', String, queue_size=None, tcp_nodelay=True)
        self.alarm_kinds = set()
        self.tls_alarms = []   # what the TLS layer of any node raised (a refused connection, a cut one)
        rospy.Subscriber('/aft/alarms', Alarm, self._on_alarm, tcp_nodelay=True)
        if self.until_hazard:
            self.live = LiveHazards(self.scenario)
        t0 = time.monotonic()
        missing = self._wait_ready(master)
        if missing:
            raise RunError('the car did not come up within %.0f s: %s (logs in %s)%s'
                           % (self.setup_timeout, ', '.join(missing[:6]), os.path.join(self.out, 'logs'),
                              self._warnings_of(missing[:6])))
        self.log('scenario %s: %d nodes up and connected in %.1f s' % (self.scenario['name'],
                                                                       len(self.expected_nodes()), time.monotonic() - t0))

    def _warnings_of(self, missing, lines=6):
        """The last warnings and errors the nodes named in ``missing`` logged, and the TLS alarms heard:
        the logs directory is gone with the machine a CI run was on, the error message is not."""
        named = sorted(set(re.findall(r'(/[A-Za-z_][\w/]*)', ' '.join(missing))))
        told = []
        for node in named:
            pattern = os.path.join(self.out, 'logs', '*', node.strip('/').replace('/', '-') + '-[0-9]*.log')
            for path in sorted({os.path.realpath(p) for p in glob.glob(pattern) if not p.endswith('-stdout.log')}):
                try:
                    with open(path, errors='replace') as f:
                        found = [line.rstrip()[:300] for line in f if re.match(r'\[[\w.]+\]\[(WARN|ERROR|FATAL)', line)]
                except OSError:
                    continue
                if found:
                    told.append('%s:\n  %s' % (os.path.basename(path), '\n  '.join(found[-lines:])))
        if self.tls_alarms:
            told.append('TLS alarms:\n  %s' % '\n  '.join(self.tls_alarms[-lines:]))
        return ''.join('\n' + t for t in told)

    def _on_alarm(self, msg):
        self.alarm_kinds.add(msg.kind)
        if msg.mechanism == 'tls':
            self.tls_alarms.append('%s %s: %s' % (msg.source, msg.kind, msg.detail))

    def _board_argv(self, board, role):
        """The command that starts a board: with PBR in ``role``, paired with the other board."""
        if not self.pbr:
            return ['roslaunch', 'tjp_sim', 'board.launch', 'board:=%s' % board, 'pbr:=false']
        peer = 'board_b' if board == 'board_a' else 'board_a'
        # The After's signs of life are judged on the wall clock: 0.5 s of road time, as cycle_timeout, but
        # never under five of its ticks (0.05 s of wall clock each, whatever the rate).
        return ['roslaunch', 'tjp_sim', 'board.launch', 'board:=%s' % board, 'peer:=%s' % peer, 'role:=%s' % role,
                'after_timeout:=%g' % max(AFTER_TIMEOUT / self.scenario['rate'], 0.25)]

    @staticmethod
    def _answers(master):
        try:
            master.getPid()
            return True
        except Exception:   # not up yet
            return False

    def _wait_ready(self, master):
        nodes = self.expected_nodes()
        services = ['%s/rebind' % n for n in nodes if n not in ('/car_sim', '/tjp/service_manager')] + ['/car_sim/start']

        def missing():
            try:
                _, subs, srvs = master.getSystemState()
            except Exception as e:
                return ['master: %s' % e]
            have = {name for name, _ in srvs}
            gone = [s for s in services if s not in have]
            recording = {t for t, nodes in subs if RECORDER in nodes}
            gone += ['recorder on %s' % t for t in ('/car/state', '/tjp/events') if t not in recording]
            if not gone:
                for n in nodes + [RECORDER]:
                    links = unwired(n, RUNNER)
                    if links is None:
                        gone.append('%s not connected (it does not answer)' % n)
                    elif links:
                        gone.append('%s not connected (%s)' % (n, '; '.join(
                            '%s to %s' % (topic, ', '.join(sorted(subs))) for topic, subs in sorted(links.items()))))
            if not gone and self.events.get_num_connections() < 1:
                gone = ['recorder not connected to the runner']
            return gone
        deadline = time.monotonic() + self.setup_timeout
        while time.monotonic() < deadline:
            dead = [why for why in (site.failure() for site in self.sites.values()) if why]
            if dead:
                return dead
            gone = missing()
            if not gone:
                return []
            time.sleep(0.1)
        return missing()

    # -- the run ---------------------------------------------------------------------------------
    def event(self, kind, **fields):
        fields.update(t=round(rospy.get_time(), 4), kind=kind)
        self.events.publish(String(data=json.dumps(fields)))
        self.log('  t=%6.2f s  %s %s' % (fields['t'], kind, ' '.join('%s=%s' % kv for kv in sorted(fields.items())
                                                                         if kv[0] not in ('t', 'kind'))))

    def run(self):
        """Start the simulation and act on the scenario's process faults and adaptations until the end."""
        try:
            rospy.ServiceProxy('/car_sim/start', Trigger)()
        except (rospy.ServiceException, rospy.ROSException) as e:
            raise RunError('the simulator did not start: %s' % e)
        duration, rate = self.scenario['duration'], self.scenario['rate']
        wall_limit = time.monotonic() + duration / rate * 4 + 60
        last_t, last_change = -1.0, time.monotonic()
        actions = [('fault', i, f) for i, f in enumerate(self.scenario['faults']) if f['kind'] in scenarios.PROCESS_FAULTS]
        actions += [('event', i, e) for i, e in enumerate(self.scenario['events']) if e['kind'] == 'adapt' and e['at'] is not None]
        triggers = [('event', i, e) for i, e in enumerate(self.scenario['events']) if e['kind'] == 'adapt' and e['on_alarm']]
        ended = 'the scenario ended'
        shown_at, next_look = None, time.monotonic()
        while True:
            t = rospy.get_time()
            wall = time.monotonic()
            if self.live is not None and shown_at is None and wall >= next_look:
                next_look = wall + 0.5
                if self.until_hazard in self.live.shown():
                    shown_at = t
                    self.log('    %s shown by t=%.2f s: the control experiment ends %.1f s later'
                             % (self.until_hazard, t, HAZARD_MARGIN_S))
            if shown_at is not None and t >= shown_at + HAZARD_MARGIN_S:
                ended = 'the control experiment showed %s by t=%.2f s and ended at t=%.2f s' % (
                    self.until_hazard, shown_at, t)
                break
            if t != last_t:
                last_t, last_change = t, wall
            for key, i, item in actions:
                if item['at'] <= t and (key, i) not in self.done:
                    self.done.add((key, i))
                    self._act(item)
            for key, i, item in triggers:
                if item['on_alarm'] in self.alarm_kinds and (key, i) not in self.done:
                    self.done.add((key, i))
                    self.log('    alarm %s: adaptation %s' % (item['on_alarm'], item['script']))
                    self._act(item)
            if t >= duration - 0.021:
                break
            stalled = wall - last_change
            if stalled > (3.0 if self.simulator_killed else 10.0):
                ended = 'the clock stopped at t=%.2f s' % t
                break
            if wall > wall_limit:
                ended = 'the wall-clock limit was reached at t=%.2f s' % t
                break
            time.sleep(0.005)
        self.finished.set()
        for thread in self.threads:
            thread.join(60.0)
        time.sleep(0.3)   # the last messages on their way to the recorder (wall clock: sim time may have stopped)
        self.log('scenario %s: %s' % (self.scenario['name'], ended))
        return ended

    def _act(self, item):
        kind = item['kind']
        if kind in ('power_loss', 'board_back', 'board_hang') and item['board'] not in self.sites:
            self.event('fault', fault=kind, target=item['board'], skipped='the board does not run without pbr')
        elif kind == 'power_loss':
            board = item['board']
            self.event('fault', fault='power_loss', target=board)
            killed, _ = self.sites[board].power_off_fault()
            self.log('    board %s powered off (%d processes)' % (board, killed))
        elif kind == 'board_back':
            # Powered on again: the board's launch starts afresh, as a backup (it holds no state and
            # re-joins the primary); without PBR it drives alone again.
            board = item['board']
            self.event('fault', fault='board_back', target=board)
            old = self.sites[board]
            if old.alive():
                self.log('    board %s is still running: not started again' % board)
                return
            old.stop()
            self._site(board, self._board_argv(board, 'backup'))
            self.log('    board %s started again (as a backup)' % board)
        elif kind == 'board_hang':
            # controllerPid (or the board's After) stops without exiting: the rest of its board lives on.
            board, node = item['board'], item.get('node', 'controller_pid')
            procs = self._board_nodes(board, node)
            self.event('fault', fault='board_hang', target=board, node=node, processes=len(procs),
                       until=item.get('until'))
            for proc in procs:
                try:
                    proc.send_signal(signal.SIGSTOP)
                except psutil.Error:   # ended since it was listed (its resume skips it)
                    pass
            if item.get('until') is not None:
                thread = threading.Thread(target=self._resume, args=(procs, item['until'], node), daemon=True)
                self.threads.append(thread)
                thread.start()
        elif kind == 'simulator_crash':
            self.event('fault', fault='simulator_crash', target='car_sim')
            self.simulator_killed = True
            procs = []
            for proc in process_tree(self.sites['car'].pid):
                try:
                    if any('car_sim' in a for a in proc.cmdline()[:3]):
                        procs.append(proc)
                except psutil.Error:   # gone meanwhile
                    pass
            for proc in procs:
                proc.kill()
            wait_dead(procs, 5.0)
        elif kind in ('node_crash', 'node_hang'):
            self.event('fault', fault=kind, target=item['node'])
            for proc in process_tree(self.sites['car'].pid):
                try:
                    if '__name:=%s' % item['node'] in proc.cmdline():
                        proc.send_signal(signal.SIGKILL if kind == 'node_crash' else signal.SIGSTOP)
                except psutil.Error:   # gone meanwhile
                    pass
        elif kind == 'master_crash':
            self.event('fault', fault='master_crash', target='rosmaster')
            self.sites['master'].power_off()
        elif kind == 'intrusion':
            self.event('fault', fault='intrusion', target='graph')
            thread = threading.Thread(target=self._intrude, daemon=True)
            self.threads.append(thread)
            thread.start()
        elif kind == 'adapt':
            thread = threading.Thread(target=self._adapt, args=(item,), daemon=True)
            self.threads.append(thread)
            thread.start()

    def _board_nodes(self, board, node):
        """The processes of ``node`` in ``board``'s launch, or all of them for ``board`` (none once it is
        powered off)."""
        found = []
        for proc in process_tree(self.sites[board].pid):
            try:
                if node == 'board' or '__name:=%s' % node in proc.cmdline():
                    found.append(proc)
            except psutil.Error:   # gone meanwhile
                pass
        return found

    def _resume(self, procs, until, node):
        """SIGCONT to ``procs`` once the simulated time reaches ``until``, or the run ended first (its clock
        stopped short of it, the simulator crashed): a node is never left stopped."""
        while rospy.get_time() < until and not self.finished.wait(0.005) and not rospy.is_shutdown():
            pass
        alive = []
        for proc in procs:
            try:
                # A process fenced meanwhile is killed: gone, or a zombie while its frozen launch has not
                # reaped it (a whole board frozen). Only a live one is resumed, and counted.
                if proc.status() != psutil.STATUS_ZOMBIE:
                    proc.send_signal(signal.SIGCONT)
                    alive.append(proc.pid)
            except psutil.Error:   # fenced meanwhile: killed and reaped
                pass
        self.event('fault', fault='board_resumed', target=node, resumed=len(alive))

    def _intrude(self):
        """The intruder (aft_ftm's ``intruder``) in clear, and under TLS with the certificate of
        party intruder, which the policy trusts with nothing; what got through goes to the summary."""
        parties = [None] + (['intruder'] if self.tls_policy else [])
        for party in parties:
            env = {k: v for k, v in self.tls_env(party).items() if party or not k.startswith('AFT_TLS_')}
            argv = ['rosrun', 'aft_ftm', 'intruder', '--hold', '1.0'] + (['--policy', self.tls_policy]
                                                                       if self.tls_policy else [])
            try:
                done = subprocess.run(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, timeout=28,
                                      universal_newlines=True)
                got = json.loads(done.stdout.strip().splitlines()[-1])
                if not isinstance(got, dict) or not {'connected', 'served', 'refused', 'topics'} <= set(got):
                    raise ValueError('not a report: %r' % (got,))
            except Exception as e:   # timed out, died, said something else: the verdict says so
                got = {'error': 'the intruder did not report: %s' % e}
            got['party'] = party or 'none (in clear)'
            self.intrusions.append(got)
            self.event('intrusion', party=got['party'], connected=len(got.get('connected', [])),
                       served=len(got.get('served', [])), refused=got.get('refused', 0), error=got.get('error', ''))

    def _adapt(self, item):
        from aft_ftm.adaptation import ScriptError
        from aft_ftm.ros.adaptation_engine import Engine
        try:
            script = load_script(item['script'], item['args'])
            # Its steps go to logs/adaptation.log (a run whose adaptation did not end says where it was).
            engine = Engine(log=functools.partial(_append, os.path.join(self.out, 'logs', 'adaptation.log')))
            self.engines.append(engine)
            report = engine.run(script, 'prepared')
            self.event('adaptation', script=item['script'], ok=bool(report['ok']), pause=round(report['pause_s'], 5),
                       duration=round(report['duration_s'], 3), error=report.get('error', ''))
            self.adaptations.append(report)
        except ScriptError as e:
            self.event('adaptation', script=item['script'], ok=False, pause=0.0, duration=0.0, error=str(e))
        except Exception as e:   # never a thread that dies unsaid
            self.event('adaptation', script=item['script'], ok=False, pause=0.0, duration=0.0,
                       error='%s: %s' % (type(e).__name__, e))

    # -- the end ---------------------------------------------------------------------------------
    def stop(self):
        """Stop every process of the run; never raises. The recorder is stopped with SIGINT (it
        closes the bag) after the others, the master last."""
        for engine in self.engines:
            engine.stop_all()
        if self.live is not None:
            self.live.close()
        # The car and the boards are powered off: the run is over and recorded, and a roslaunch
        # takes 1.5 s to stop its nodes gently, a quarter of a short scenario's road time.
        for name, site in self.sites.items():
            if name not in ('recorder', 'master'):
                site.power_off()
                site.stop()
        for name in ('recorder', 'master'):
            site = self.sites.get(name)
            if site is None:
                continue
            if name == 'recorder' and site.alive():
                try:
                    os.kill(site.pid, signal.SIGINT)
                    site.proc.wait(timeout=10)
                except Exception:   # shutdown paths never raise
                    pass
            site.stop(grace=5.0)
        try:
            rospy.signal_shutdown('scenario done')
        except Exception:
            pass

    def leftovers(self):
        """Processes of the run still alive (there should be none after stop())."""
        launched = [site for engine in self.engines for site in engine.sites + engine.respawned]
        return [s.name for s in list(self.sites.values()) + launched if s.alive()]


def _append(path, line):
    with open(path, 'a') as f:
        f.write('%.3f %s\n' % (time.time(), line))


def load_script(name, args):
    """An adaptation script: a path, or the name of one shipped in tjp_sim/adaptations or aft_ftm's."""
    from aft_ftm.ros import adapt_command
    shipped = resources.path('adaptations', name + '.yaml')
    spec = shipped if os.path.isfile(shipped) else name
    return adapt_command.load_script(spec, ['%s:=%s' % kv for kv in sorted(args.items())])


# What the summary reads (tjp_sim.summary's input), from the bag or live.
RECORDED = {'/car/state': CarState, '/car/command': CarCommand, '/tjp/pid_command': CarCommand,
            '/aft/alarms': Alarm, '/tjp/events': String, '/tjp/service_manager/events': String}


def new_record():
    return {'states': [], 'commands': [], 'pid_commands': [], 'alarms': [], 'events': [], 'service_events': []}


def add_message(run, topic, msg):
    """Add one message of a RECORDED topic to the run's records."""
    if topic == '/car/state':
        run['states'].append((msg.stamp.to_sec(), msg.gap, msg.follower_speed, msg.leader_speed, msg.accel,
                              msg.obstacle, msg.collided))
    elif topic == '/car/command':
        run['commands'].append((msg.stamp.to_sec(), msg.accel, msg.mode, msg.source))
    elif topic == '/tjp/pid_command':
        run['pid_commands'].append((msg.stamp.to_sec(), msg.source))
    elif topic == '/aft/alarms':
        run['alarms'].append((msg.stamp.to_sec(), msg.source, msg.mechanism, msg.kind, msg.detail))
    elif topic == '/tjp/events':
        run['events'].append(json.loads(msg.data))
    else:
        run['service_events'].append(json.loads(msg.data))


def sorted_record(run):
    """The records in time order (messages of different topics arrive in any order)."""
    return {key: sorted(rows, key=lambda r: r['wall'] if key == 'service_events' else r['t'] if key == 'events'
                        else r[0]) for key, rows in run.items()}


def read_bag(path):
    """The run's records (tjp_sim.summary's input) from the bag."""
    if not os.path.exists(path) and os.path.exists(path + '.active'):
        raise RunError('the recorder did not close %s (a .active file remains)' % path)
    run = new_record()
    try:
        bag = rosbag.Bag(path)
    except (OSError, rosbag.ROSBagException) as e:
        raise RunError('cannot read the record %s: %s' % (path, e))
    with bag:
        for topic, msg, _ in bag.read_messages(topics=list(RECORDED)):
            add_message(run, topic, msg)
    return sorted_record(run)


class LiveHazards(object):
    """The hazards the run shows for good so far (tjp_sim.summary.shown_so_far), from the same records
    as the bag's, received live: the control experiment can end once its hazard has shown. The
    verdict is still read from the bag."""

    def __init__(self, scenario):
        self.scenario = scenario
        self.lock = threading.Lock()
        self.run = new_record()
        self.subscribers = [rospy.Subscriber(topic, kind, self._on_message, callback_args=topic, tcp_nodelay=True)
                            for topic, kind in RECORDED.items()]

    def _on_message(self, msg, topic):
        with self.lock:
            add_message(self.run, topic, msg)

    def shown(self):
        with self.lock:
            run = {key: list(rows) for key, rows in self.run.items()}
        return summaries.shown_so_far(sorted_record(run), self.scenario['expect'], stop_expected(self.scenario))

    def close(self):
        for subscriber in self.subscribers:
            subscriber.unregister()


def stop_expected(scenario):
    """Whether the scenario's faults call for a controlled stop (the FMECA's alarm-and-stop rows)."""
    control = scenario['control'] or {}
    return scenario['expect']['stop_within'] is not None or control.get('hazard') == 'no_stop'


def run_scenario(name, out, disable=None, gui=False, plot=True, log=print, until_hazard=False, tls_policy=None,
                 stopping=contextlib.nullcontext):
    """Run scenario name (a file or shipped name), with mechanism disable removed if given (the
    control experiment). With until_hazard (a control experiment only), the run ends HAZARD_MARGIN_S
    of road time after the scenario's control hazard has shown, not at its duration. Returns the
    summary (with its verdict and hazards); writes summary.json, run.bag and plot.png into out.
    With tls_policy, every connection between the car's nodes is mutual TLS under that policy.
    stopping(): a context the run's stop runs in (the scenario command defers its SIGTERM there)."""
    path = scenarios.path_of(name)
    scenario = scenarios.load(name)
    if disable:
        scenario = scenarios.without(scenario, disable)
    os.makedirs(out, exist_ok=True)
    if until_hazard and not (disable and scenario['control']):
        raise RunError('ending at the hazard is for a control experiment: a scenario with a control hazard, '
                       'run without its mechanism')
    runner = ScenarioRun(scenario, path, out, gui=gui, log=log,
                         until_hazard=scenario['control']['hazard'] if until_hazard else None, tls_policy=tls_policy)
    try:
        runner.start()
        ended = runner.run()
    finally:
        with stopping():   # a signal's exception waits for the stop: raised in it, it left processes behind
            runner.stop()
    left = runner.leftovers()
    if left:
        raise RunError('processes of the run still alive after stopping: %s' % ', '.join(left))
    record = read_bag(runner.bag)
    managed = record.pop('service_events')
    try:
        summary = summaries.summarize(record, scenario['expect'])
    except ValueError as e:   # no car state recorded, malformed rows
        raise RunError('%s (logs in %s)' % (e, os.path.join(out, 'logs')))
    summary['service_manager'] = {
        'faults': [{'service': e['service'], 'kind': e['kind'], 'detail': e['detail']} for e in managed
                   if e['event'] == 'fault'],
        'restarted': [e['service'] for e in managed if e['event'] == 'spawned' and e.get('starts', 1) > 1]}
    summary.update(scenario=scenario['name'], mechanisms=scenario['mechanisms'], ended=ended,
                   ended_at_hazard=runner.until_hazard is not None and ended.startswith('the control experiment'),
                   hazards=summaries.hazards(summary, scenario['expect']['min_gap_fraction'], stop_expected(scenario)),
                   bag=runner.bag, seed=scenario['seed'], rate=scenario['rate'])
    expected = sum(1 for f in scenario['faults'] if f['kind'] == 'intrusion') * (2 if tls_policy else 1)
    if expected and len(runner.intrusions) < expected:   # an intruder thread that never reported
        runner.intrusions += [{'party': '?', 'error': 'no report'}] * (expected - len(runner.intrusions))
    if runner.intrusions:
        summary['intrusions'] = runner.intrusions
        through = ['%s: %s' % (i['party'], i.get('error') or 'heard on %s, served %s' % (i['connected'], i['served']))
                   for i in runner.intrusions if i.get('error') or i['connected'] or i['served']]
        if through:
            summary['verdict']['ok'] = False
            summary['verdict']['problems'].append('the intruder got through: %s' % '; '.join(through))
    # An adaptation the scenario asks for whose moment came (its time, or its alarm raised on the
    # graph, as recorded) at least ADAPT_GRACE s of wall time before the end, but that never reported:
    # said, not left to show as a collision.
    ran = {a.get('script') for a in summary['adaptations']}
    first = summary['alarm_first_at']
    for event in scenario['events']:
        if event['kind'] != 'adapt' or event['script'] in ran:
            continue
        at = first.get(event['on_alarm']) if event['on_alarm'] else event['at']
        due = at is not None and at <= summary['duration'] - ADAPT_GRACE * scenario['rate']
        if due:
            summary['verdict']['ok'] = False
            summary['verdict']['problems'].append('the adaptation %s never reported (%s)' % (
                event['script'], 'its alarm %s was raised' % event['on_alarm'] if event['on_alarm'] else
                'due at t=%.1f s' % event['at']))
    if tls_policy:
        # A connection between two of the car's own parties that the policy refuses is one the car
        # needed and lost: the run fails. Refusals of the intruders, and handshakes that rospy
        # retried, are counted and shown.
        own = tuple('party %s may not' % p for p in ScenarioRun.TLS_PARTIES if p != 'intruder')
        gaps = [a for a in runner.tls_alarms if any(o in a for o in own)]
        summary['tls'] = {'policy': tls_policy, 'alarms': len(runner.tls_alarms), 'policy_gaps': gaps}
        if gaps:
            summary['verdict']['ok'] = False
            summary['verdict']['problems'].append('the TLS policy refused the car\'s own nodes: %s' % '; '.join(gaps[:3]))
    if plot:
        from ..plot import plot as draw
        summary['plot'] = draw(record, os.path.join(out, 'plot.png'), title='%s (seed %d)' % (scenario['name'],
                                                                                              scenario['seed']),
                               min_gap_fraction=scenario['expect']['min_gap_fraction'])
    with open(os.path.join(out, 'summary.json'), 'w') as f:
        json.dump(summary, f, indent=1, default=str)
    return summary
