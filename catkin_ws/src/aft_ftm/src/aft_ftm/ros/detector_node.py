"""Crash detector: heartbeats to the peer site, and failure verdicts about it."""
import os
import threading
import time

import psutil
import rospy
from aft_msgs.msg import Configuration, Failure, Heartbeat
from aft_msgs.srv import PeerStatus, PeerStatusResponse

from .. import config, health
from ..detector import (ANNOUNCED, DEFAULT_PHI, DEFAULT_REALTIME_PRIORITY, DEFAULT_RULE, DEFAULT_TIMEOUT,
                        HeartbeatMonitor, PeerState, PhiAccrualMonitor, incarnation, why_heard_again)
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..site_watch import SiteWatch, WatchError, children_nodes
from ..sites import this_host
from .alarms import alarm
from .diagnostics import Diagnostics
from .launch_files import replaceable_by_launch, required_by_launch
from .params import param
from .ports import Ports
from .qos import Marker
from .witness_client import configuration_topic, from_witness_only


def _sent(beat):
    """(seq, sent time) of a heartbeat message, or None."""
    return None if beat is None else (beat.seq, beat.stamp.to_sec())


class CrashDetectorNode(object):
    """Sends this site's heartbeat every period and declares the peer failed after timeout.

    Parameters:
        ~site (str, required): this site's name.  ~peer (str, required): the watched site's name.
        ~period (float, 0.01 s), ~timeout (float, 0.03 s)
        ~detector (str, aft_ftm.detector.DEFAULT_RULE): the rule that judges a silence a failure (aft_ftm.detector):
            ``timeout``, a fixed ~timeout; ``phi``, phi accrual, ~timeout deciding only while the first
            ~phi_min_samples intervals are learnt.
        ~phi_threshold (float, 8), ~phi_window (int, 100 intervals), ~phi_min_std (float, 0.005 s),
        ~phi_pause (float, 0 s: the acceptable pause added to the mean), ~phi_min_samples (int, 10):
            the phi rule's settings (read, and checked, only with ~detector phi).
        ~startup_grace (float, 0 = never): declare a never-heard peer failed after this long.
        ~site_pid (int, default: this node's parent, i.e. the site's roslaunch): sent in heartbeats
            so that the peer's Recovery can enforce fail-silence on the same host.
        ~niceness (int, default -5): the detector's own process priority. A failure detector must not
            be starved by the load it watches (its peer would declare this site failed); lowering
            it needs privileges: without them it warns and runs at the default.
        ~realtime_priority (int 0-99, aft_ftm.detector.DEFAULT_REALTIME_PRIORITY; 0 = off): every thread
            of the detector under SCHED_FIFO at this priority (threads rospy starts later included,
            checked every second). Under load a late heartbeat was a starved sender far more often than
            a slow link (scripts/bench_detection): at real-time priority the heartbeats stay on time on
            a loaded 2-core machine. The detector sleeps between beats, so it takes little CPU from
            anybody. Without the privilege it warns, raises an alarm (``detector_priority``) and runs
            at its niceness.
        ~follow_witness (bool, default false): watch the peer again when the witness's configuration
            names it once more (it re-joined after a failure).
        ~witness (str, default '' : none; the launch files give the replica's, one for all its nodes): the service of that witness; its configurations
            are its node's ~configuration beside it (one witness per replicated service).
        ~watch_required (bool, default true): watch the required nodes of this site's roslaunch (the
            process ~site_pid; read from its launch file) through pidfds, and fail-stop the moment one
            dies, rather than heartbeat until roslaunch's shutdown reaches this node (about 200 ms:
            aft_ftm.site_watch). Nothing is watched with ~site_pid 0, or when the launcher is not a
            roslaunch whose file loads (said in the log).
        ~watch_replaceable (bool, default false; replica.launch sets it for an adaptable site): watch
            too the stage nodes the launch starts without required="true" (aft_ftm's protocol, before,
            proceed, after: an adaptation may replace them), and fail-stop the moment one dies, unless
            an adaptation marked it retired first (aft_ftm.site_watch.mark_retired); only those of this
            node's name space, and only with ~watch_required. Without it, a crashed stage of an
            adaptable site left requests waiting for the Protocol's timeouts.
        ~alive_timeout (float, default 0 = off): once a sign of life was heard on ``alive`` (the
            pub/sub After's, aft_ftm.ros.cycle_nodes), none for this long (s, wall clock; this
            detector's own stalls excused, as in its peer's verdict; keep it several of the After's
            ticks) means the node that gives them hangs (stopped, deadlocked; a death is seen by
            ~watch_required). If its last sign said a backup could take over, and the peer is heard
            (within ten periods, 0.1 s at least; judged again at every check while the hang lasts),
            this site fail-stops (its peer is promoted); otherwise (a backup, or a primary alone) the hang is alarmed
            (``node_hung``), the site beats on, and the node serves again if it resumes.
        ~alive_from (str, default '' = any): the node whose signs of life count (its caller id);
            another publisher's are ignored (counted in the diagnostics' log), as a forged one would
            hide a hang.
    Publishes:
        heartbeat (aft_msgs/Heartbeat), port ``heartbeat``; when this site fail-stops, one last one
            whose ``stopping`` says why, so that the peer declares it failed at once
        failures (aft_msgs/Failure), port ``failures``: to this site's Recovery
        alarms (aft_msgs/Alarm), port ``alarms`` (/aft/alarms): this site fail-stopped; a peer declared
            failed is heard again (it came back); it is watched again.
        /diagnostics (diagnostic_msgs/DiagnosticArray): the peer alive, failed or never heard (aft_ftm.health).
    Subscribes:
        peer_heartbeat (aft_msgs/Heartbeat), port ``peer_heartbeat``: a beat with ``stopping`` declares the
            peer failed at the next check (it announced its fail-stop)
        fail_stop (aft_msgs/Failure), port ``fail_stop``: a node of this site cannot serve correctly any
            more: the heartbeats stop for good, so that the peer fences this site and takes over.
        alive (std_msgs/Bool), port ``alive``, with ~alive_timeout: a node of this site still works
            (``data``: a backup could take over from it now).
    Services:
        ~rebind (aft_msgs/Rebind)
        ~peer_status (aft_msgs/PeerStatus): may the peer take over now (heard within ~timeout, not
            declared failed)? Asked by a node of this site whose server hangs, before it fail-stops the
            site (aft_ftm.recovery.SiteRole). And does the peer's site run (``heard``: its beats heard
            within ~timeout, even after it was declared failed)? Asked by this site's After before it
            admits a joiner of the peer's site.
    """

    def __init__(self):
        self.site = param('site', config.non_empty_str, required=True)
        self.peer = param('peer', config.non_empty_str, required=True)
        self.period = param('period', config.positive_float, 0.01)
        timeout = param('timeout', config.positive_float, DEFAULT_TIMEOUT)
        if timeout <= self.period:
            raise config.ConfigError('parameter %s (%r) must be longer than ~period (%r)'
                                     % (rospy.resolve_name('~timeout'), timeout, self.period))
        grace = param('startup_grace', config.non_negative_float, 0.0)
        self.site_pid = param('site_pid', config.non_negative_int, os.getppid())
        self.niceness = param('niceness', config.niceness, -5)
        self.follow_witness = param('follow_witness', config.flag, False)
        self.witness = param('witness', config.witness_service, '')
        self.watch_required = param('watch_required', config.flag, True)
        self.watch_replaceable = param('watch_replaceable', config.flag, False)
        self.realtime_priority = param('realtime_priority', config.non_negative_int, DEFAULT_REALTIME_PRIORITY)
        if self.realtime_priority > 99:
            raise config.ConfigError('parameter %s must be from 0 (off) to 99, got %r'
                                     % (rospy.resolve_name('~realtime_priority'), self.realtime_priority))
        self.realtime_threads = set()   # thread ids already under SCHED_FIFO
        self.realtime_lock = threading.Lock()   # _realtime and _leave_realtime, one at a time
        self.realtime_error = None
        self.realtime_told = False
        self.started = time.monotonic()
        self.timeout, self.grace = timeout, grace
        self.detector = param('detector', config.choice('timeout', 'phi'), DEFAULT_RULE)
        self.phi = None
        if self.detector == 'phi':
            self.phi = {'threshold': param('phi_threshold', config.positive_float, DEFAULT_PHI['threshold']),
                        'window': param('phi_window', config.positive_int, DEFAULT_PHI['window']),
                        'min_std': param('phi_min_std', config.positive_float, DEFAULT_PHI['min_std']),
                        'acceptable_pause': param('phi_pause', config.non_negative_float,
                                                  DEFAULT_PHI['acceptable_pause']),
                        'min_samples': param('phi_min_samples', config.positive_int, DEFAULT_PHI['min_samples'])}
            if not 2 <= self.phi['min_samples'] <= self.phi['window']:
                raise config.ConfigError('parameters %s (%r) and %s (%r): need 2 <= min_samples <= window' % (
                    rospy.resolve_name('~phi_min_samples'), self.phi['min_samples'],
                    rospy.resolve_name('~phi_window'), self.phi['window']))
        self.monitor = self._new_monitor(time.monotonic())
        self.alive_timeout = param('alive_timeout', config.non_negative_float, 0.0)
        self.alive_from = param('alive_from', config.optional_name, '')
        # (a fixed timeout: the signs of life come from this site's own host, never over a slow link)
        self.alive = self._alive_monitor() if self.alive_timeout else None
        self.alive_replaceable = False   # the last sign of life said a backup could take over
        self.alive_hang = None           # the verdict of a hang that lasts (no sign of life since)
        # A peer that beats every period is heard within this (a beat late by ten periods is not now).
        self.peer_heard_within = max(10 * self.period, 0.1)
        self.alive_strangers = 0         # signs of life from another node than ~alive_from: ignored
        self.watched_since = 0   # the witness's epoch that made this detector watch its peer afresh (0: at start)
        self.lock = threading.Lock()
        self.beat_lock = threading.Lock()   # one heartbeat at a time: none after the last (stopping) one
        self.host = this_host()
        self.ports = Ports([PortSpec('heartbeat', PUBLISH, 'aft_msgs/Heartbeat'),
                            PortSpec('failures', PUBLISH, 'aft_msgs/Failure'),
                            PortSpec('peer_heartbeat', SUBSCRIBE, 'aft_msgs/Heartbeat'),
                            PortSpec('fail_stop', SUBSCRIBE, 'aft_msgs/Failure'),
                            PortSpec('alive', SUBSCRIBE, 'std_msgs/Bool'),
                            PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
                           {'peer_heartbeat': self._on_heartbeat, 'fail_stop': self._on_fail_stop,
                            'alive': self._on_alive}, queue_size=10)
        self.seq = 0
        self.stopped = None        # why this site fail-stopped: no heartbeat is sent any more
        self.peer_back_told = False
        self.stale_told = set()   # incarnations whose stale fail-stop announcement was told (once each)
        self.wrong_sites = set()  # sites other than the peer heard on the peer's topic (told once each)
        # A failure report published while Recovery was not connected (rospy handles a publisher's
        # inbound connections one at a time: one stalled handshake holds the others back for up to
        # 60 s): (the monitor that declared it, the message), published once Recovery connects.
        self.undelivered = None
        self.qos = Marker()   # the heartbeat connections, low delay on the network (aft_ftm.ros.qos)

    def _new_monitor(self, now):
        """A monitor of the peer by the chosen rule. A check later than one period after the
        previous one means this detector itself was stalled (stall_after)."""
        if self.phi is not None:
            return PhiAccrualMonitor(bootstrap_timeout=self.timeout, startup_grace=self.grace, started_at=now,
                                     stall_after=self.period, **self.phi)
        return HeartbeatMonitor(self.timeout, self.grace, now, stall_after=self.period)

    def setup(self, timeout):
        try:
            os.setpriority(os.PRIO_PROCESS, 0, self.niceness)
        except OSError as e:
            rospy.logwarn('%s: cannot set niceness %d (%s): heartbeats may be late under load',
                          rospy.get_name(), self.niceness, e)
        for name in ('heartbeat', 'failures', 'peer_heartbeat', 'fail_stop') + (('alive',) if self.alive else ()):
            self.ports.bind(name)
        self.ports.bind('alarms', '/aft/alarms')
        self.ports.advertise_service()
        rospy.Service('~peer_status', PeerStatus, self._on_peer_status)
        rospy.on_shutdown(self._leave_realtime)   # the first thing done when the node stops
        self._realtime()
        if self.follow_witness and self.witness:
            self.configuration = rospy.Subscriber(configuration_topic(self.witness), Configuration, from_witness_only(
                self.witness, self._on_configuration, report=lambda detail: alarm(self.ports, 'witness', 'forged_configuration', detail)), tcp_nodelay=True)
        self.thread = threading.Thread(target=self._loop, name='heartbeat', daemon=True)
        self.thread.start()
        if self.watch_required and self.site_pid:
            threading.Thread(target=self._watch_site, name='site-watch', daemon=True).start()
        self.diagnostics = Diagnostics(self._health, self.site)
        return True

    def _watch_site(self, scan_period=0.2, patient_for=120.0, slow_scan=2.0):
        """Fail-stop this site the moment a required node of its roslaunch dies, or (~watch_replaceable)
        a stage node that no adaptation retired (aft_ftm.site_watch)."""
        try:
            launcher = psutil.Process(self.site_pid)
            argv, namespace = launcher.cmdline(), launcher.environ().get('ROS_NAMESPACE', '/')
        except psutil.Error as e:
            rospy.logwarn('%s: the site launcher (pid %d) cannot be read: its nodes are not watched (%s)',
                          rospy.get_name(), self.site_pid, e)
            return
        required = required_by_launch(argv, namespace) - {rospy.get_name()}
        # Only this site's (this node's name space): roslaunch does not stop a launch running both
        # replicas when the other's dies.
        replaceable = {n for n in replaceable_by_launch(argv, namespace) - required
                       if n.startswith(rospy.get_namespace())} if self.watch_replaceable else set()
        if replaceable:
            rospy.loginfo('%s: the stage nodes %s are watched too (adaptable site): their death fails the site '
                          'unless an adaptation retires them', rospy.get_name(), ', '.join(sorted(replaceable)))
        watched = required | replaceable
        if not watched:
            rospy.loginfo('%s: no required node known for the launcher %s: none watched', rospy.get_name(),
                          ' '.join(argv[:6]))
            return
        try:
            watch = SiteWatch(watched)
        except WatchError as e:
            rospy.logwarn('%s: %s: the required nodes of the site are not watched', rospy.get_name(), e)
            return
        started = time.monotonic()
        while not rospy.is_shutdown() and self.stopped is None:
            if watch.missing():
                try:
                    adopted = watch.adopt(children_nodes(self.site_pid))
                except WatchError as e:
                    rospy.logwarn('%s: %s: the site watch stops', rospy.get_name(), e)
                    return
                if adopted:
                    rospy.loginfo('%s: watching the required nodes %s (still to find: %s)', rospy.get_name(),
                                  ', '.join(sorted(adopted)), ', '.join(sorted(watch.missing())) or 'none')
            waiting = watch.missing()
            patience = scan_period if time.monotonic() - started < patient_for else slow_scan
            failed = None
            for pid, name in watch.wait(patience if waiting else 1.0):
                if name in replaceable and watch.retired(pid):
                    rospy.loginfo('%s: %s (pid %d) retired by an adaptation: no failure', rospy.get_name(), name, pid)
                elif failed is not None:
                    continue   # the first death names the failure
                elif name in replaceable:
                    failed = ('the stage node %s (pid %d) died, and no adaptation retired it: the site cannot '
                              'serve without it' % (name, pid))
                else:
                    failed = 'the required node %s (pid %d) died: its roslaunch stops the site' % (name, pid)
            if failed:
                self._on_fail_stop(Failure(site=self.site, reason=failed, detected=rospy.Time.now()))
                break
        watch.close()

    def _realtime(self):
        """Put every thread of this process not yet under SCHED_FIFO there (threads started by those
        already there inherit it; others, started by rospy's own threads, are caught at the next call)."""
        with self.realtime_lock:
            self._realtime_locked()

    def _realtime_locked(self):
        if not self.realtime_priority or self.realtime_error:
            return
        try:
            tids = set(int(t) for t in os.listdir('/proc/self/task'))
        except OSError as e:
            self.realtime_error = str(e)
            return
        for tid in tids - self.realtime_threads:
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(self.realtime_priority))
            except ProcessLookupError:
                continue                  # the thread ended meanwhile
            except OSError as e:
                self.realtime_error = 'SCHED_FIFO %d refused: %s' % (self.realtime_priority, e)
                rospy.logwarn('%s: %s', rospy.get_name(), self.realtime_error)
                return
        self.realtime_threads = tids

    def _leave_realtime(self):
        """Every thread back to the usual policy, for good: a node shutting down has no deadline to
        meet, and whatever it does then (rospy joins threads for seconds; see also
        aft_ftm.ros.xmlrpc_shutdown) must not take a core from the machine's other processes."""
        with self.realtime_lock:
            self.realtime_priority = 0   # _realtime() does nothing from now on
            try:
                tids = [int(t) for t in os.listdir('/proc/self/task')]
            except OSError:
                return
        for tid in tids:
            try:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            except OSError:   # ended meanwhile
                pass

    def _tell_realtime_error(self, now):
        """The alarm that this detector runs without real-time priority: once, when a subscriber of the
        alarms is connected (published at once, it would reach nobody), or after 10 s in any case."""
        if self.realtime_error is None or self.realtime_told:
            return
        if self._connected('alarms') or now - self.started > 10.0:
            self.realtime_told = True
            alarm(self.ports, 'pbr', 'detector_priority', 'the crash detector of site %s runs without real-time '
                  'priority (%s): its heartbeats may be late under load' % (self.site, self.realtime_error))

    def _health(self):
        with self.lock:
            heard = self.monitor.last_heard
            return health.detector(self.site, self.peer, self.monitor.state.name,
                                   time.monotonic() - heard if heard is not None else None, self.stopped)

    def _on_peer_status(self, _req):
        with self.lock:
            now = time.monotonic()
            alive, why = self.monitor.can_take_over(now, self.timeout)
            heard, state = self.monitor.last_heard, self.monitor.state.name
            runs = self.monitor.heard_within(now, self.timeout)
        return PeerStatusResponse(alive=alive, state=state, silence=-1.0 if heard is None else now - heard,
                                  why='site %s: %s' % (self.peer, why), heard=runs, peer=self.peer)

    def _on_heartbeat(self, beat):
        if beat.site != self.peer:
            # Another site's beats (a topic remapped wrong, two pairs on one topic, or forged) say nothing of
            # the peer: counted as its, they kept a dead peer alive (review of session 36). Told once per site.
            with self.lock:
                first = beat.site not in self.wrong_sites and len(self.wrong_sites) < 16
                if first:   # (bounded: a forger naming ever new sites grows nothing)
                    self.wrong_sites.add(beat.site)
            if first:
                alarm(self.ports, 'pbr', 'wrong_site', 'a heartbeat of site %r (pid %d on %s) on the topic of peer %s '
                      '(%s): ignored; it says nothing of %s' % (beat.site, beat.pid, beat.host, self.peer,
                                                               self.ports.topic('peer_heartbeat'), self.peer))
            return
        if beat.stopping:
            with self.lock:
                heard = self.monitor.last_info
                stale = self.monitor.stale_announcements
                self.monitor.announced(time.monotonic(), beat.stopping, beat)   # the loop reports it
                stale = self.monitor.stale_announcements > stale
                first = stale and incarnation(beat) not in self.stale_told and len(self.stale_told) < 64
                if first:   # (bounded: a forger naming ever new pids gets 64 alarms, then the log's count)
                    self.stale_told.add(incarnation(beat))
            if first:   # once per incarnation named: a forger may repeat it at any rate
                alarm(self.ports, 'pbr', 'stale_announcement', 'site %s announced a fail-stop (%s) from pid %d on %s, '
                      'not the incarnation heard last (pid %d on %s): ignored; a late last word of an old '
                      'incarnation, or forged' % (beat.site, beat.stopping, beat.pid, beat.host, heard.pid, heard.host))
            return
        with self.lock:
            before = self.monitor.last_info
            back = self.monitor.beat(time.monotonic(), beat) and not self.peer_back_told
            self.peer_back_told = self.peer_back_told or back
        if back:
            why = why_heard_again(_sent(before), _sent(beat), self.period, self.timeout)
            alarm(self.ports, 'pbr', 'peer_back', 'site %s, declared failed, is heard again (pid %d on %s): it must '
                  're-join before it may serve or be promoted%s' % (beat.site, beat.pid, beat.host,
                                                                     '; ' + why if why else ''))

    def _on_fail_stop(self, failure):
        with self.beat_lock:
            with self.lock:
                first = self.stopped is None
                self.stopped = self.stopped or failure.reason
            if first:
                # The last heartbeat says why: the peer need not wait out its timeout to take over.
                self.seq += 1
                try:
                    self.ports.publish('heartbeat', Heartbeat(site=self.site, host=self.host, pid=self.site_pid,
                                                              seq=self.seq, stamp=rospy.Time.now(),
                                                              stopping=failure.reason or 'fail-stop'))
                except rospy.ROSException as e:   # going down: the peer's timeout detects it as before
                    rospy.logwarn('%s: the last heartbeat (this site fail-stops) was not sent: %s', rospy.get_name(),
                                  e)
            alarm(self.ports, 'pbr', 'fail_stop', 'site %s stops heartbeating: %s' % (self.site, failure.reason))

    def _alive_monitor(self):
        return HeartbeatMonitor(self.alive_timeout, 0.0, time.monotonic(), stall_after=self.period)

    def _on_alive(self, msg):
        sender = getattr(msg, '_connection_header', {}).get('callerid', '')
        with self.lock:
            if self.alive_from and sender != self.alive_from:
                self.alive_strangers += 1
                first = self.alive_strangers == 1
            else:
                first = None
                self.alive_replaceable, self.alive_hang = msg.data, None
                if self.alive.beat(time.monotonic()):   # it resumes after a hang alarmed: watched afresh
                    self.alive = self._alive_monitor()
                    self.alive.beat(time.monotonic())
                    resumed = True
                else:
                    resumed = False
        if first:
            rospy.logwarn('%s: a sign of life on %s from %s, not %s: ignored (it would hide a hang)',
                          rospy.get_name(), self.ports.topic('alive'), sender or 'an unnamed node', self.alive_from)
        elif first is None and resumed:
            alarm(self.ports, 'pbr', 'node_resumed', 'site %s: signs of life on %s again' % (
                self.site, self.ports.topic('alive')))

    def _check_alive(self, now):
        """Fail-stop this site if the node giving signs of life on ``alive`` stopped giving them, its
        last one said a backup could take over, and the peer is heard; else say the hang, and judge
        it again at every check while it lasts (the peer may be heard again: a board that failed and
        re-joined is heard, though its verdict stands; review of session 38)."""
        with self.lock:
            verdict = self.alive.check(now)
            if verdict is not None:
                self.alive_hang = verdict   # until a sign of life comes (_on_alive)
            hang, replaceable = self.alive_hang, self.alive_replaceable
            peer_heard = self.monitor.heard_within(now, self.peer_heard_within)
        if hang is None or self.stopped is not None:
            return
        what = 'no sign of life on %s: %s; the node that gives them hangs (stopped or deadlocked)' % (
            self.ports.topic('alive'), hang.reason.replace('heartbeat', 'sign of life'))
        if replaceable and peer_heard:
            reason = '%s; this site fail-stops so that the backup takes over' % what
            rospy.logerr('%s: %s', rospy.get_name(), reason)
            self._on_fail_stop(Failure(site=self.site, host=self.host, pid=self.site_pid, reason=reason,
                                       silence=hang.silence, detected=rospy.Time.now()))
        elif verdict is not None:   # said once per hang
            why = ('its last sign said no backup could take over' if not replaceable else
                   'its peer %s is not heard now' % self.peer)
            alarm(self.ports, 'pbr', 'node_hung', 'site %s: %s; %s: this site beats on (it fail-stops if its peer '
                  'is heard while the hang lasts), and it serves again if it resumes' % (self.site, what, why))

    def _on_configuration(self, conf):
        """The peer is in the witness's configuration again (it re-joined): watch it afresh."""
        if self.peer not in (conf.primary, conf.backup):
            return
        with self.lock:
            if self.monitor.state != PeerState.FAILED:
                return
            self._watch_again()
            self.watched_since = conf.epoch
        alarm(self.ports, 'pbr', 'peer_watched', 'site %s re-joined (epoch %d): watched again' % (self.peer, conf.epoch))

    def _watch_again(self):
        """A fresh monitor of the peer, heard now (under self.lock): silent from now on, it is declared
        failed. The incarnation heard last (a new one, beating since it started again) is kept: a late
        last word of an older one is then stale, also before the next beat."""
        now = time.monotonic()
        last = self.monitor.last_info
        self.monitor = self._new_monitor(now)
        self.monitor.beat(now, last)
        self.peer_back_told = False

    def _loop(self):
        """Send a heartbeat every period; check the peer five times as often, so that a
        failure is declared within period/5 of the timeout expiring."""
        tick = self.period / 5.0
        next_beat = next_tick = next_realtime = time.monotonic()
        while not rospy.is_shutdown():
            now = time.monotonic()
            if now >= next_realtime:
                self._realtime()
                next_realtime = now + 1.0
                self._tell_realtime_error(now)
            if now >= next_beat and self.stopped is None:
                with self.beat_lock:
                    if self.stopped is None:
                        self.seq += 1
                        try:
                            self.ports.publish('heartbeat', Heartbeat(site=self.site, host=self.host,
                                                                      pid=self.site_pid, seq=self.seq,
                                                                      stamp=rospy.Time.now()))
                        except rospy.ROSException:
                            if rospy.is_shutdown():
                                return   # the node is going down: its topics are closed
                            raise
                next_beat = max(next_beat + self.period, now)   # late: do not burst to catch up
                try:
                    self.qos.mark(self.ports.publisher('heartbeat'), self.ports.publisher('peer_heartbeat'))
                except Exception as e:   # never the heartbeats' end: the mark is an optimisation
                    rospy.logwarn_throttle(60.0, '%s: cannot mark the heartbeat connections low delay: %s: %s',
                                           rospy.get_name(), type(e).__name__, e)
            if self.alive is not None:
                self._check_alive(now)
            with self.lock:
                verdict = self.monitor.check(now)
            if verdict is not None and self.stopped is None:   # a fail-stopped site takes nothing over
                self._report(verdict)
            elif self.undelivered is not None:
                self._deliver_late()
            next_tick = max(next_tick + tick, time.monotonic())
            time.sleep(max(0.0, next_tick - time.monotonic()))

    def _report(self, verdict):
        info = verdict.last_info
        rospy.logwarn('%s: site %s failed: %s', rospy.get_name(), self.peer, verdict.reason)
        failure = Failure(site=self.peer, host=info.host if info else '', pid=info.pid if info else 0,
                          reason=verdict.reason, silence=verdict.silence, detected=rospy.Time.now(),
                          epoch=self.watched_since)
        if not self._connected('failures'):
            # Published now, it would reach nobody: kept until Recovery is connected. Never silent.
            self.undelivered = (self.monitor, failure, verdict.reason.startswith(ANNOUNCED))
            alarm(self.ports, 'pbr', 'failure_undelivered', 'site %s failed, but no Recovery is connected to %s: '
                  'the report is sent as soon as one is' % (self.peer, self.ports.topic('failures')))
            return
        self.ports.publish('failures', failure)

    def _connected(self, port):
        publisher = self.ports.publisher(port)
        return publisher is not None and publisher.get_num_connections() > 0

    def _deliver_late(self):
        """The kept failure report, once Recovery is connected, if the peer is still the failed one
        (not heard again, not re-joined since): otherwise it is moot and dropped, saying so.

        A peer heard again, as the incarnation declared failed (or first heard now, if it was never
        heard within the start-up grace), after a silence (not its own fail-stop) is watched again: the
        verdict reached nobody, so nothing was fenced, promoted or excluded, and the FAILED it left was final with no witness to re-arm it (a site re-joins only through one).
        A later real failure of that peer was then never reported: a pair without a witness whose
        detectors suspected each other while they started stayed so, and once its primary was powered
        off nobody took over (session 48's clean-clone CI; session 50)."""
        monitor, failure, announced = self.undelivered
        with self.lock:
            current = self.monitor is monitor and monitor.beats_after_failure == 0
            # (last_beat None: its fail-stop announced since, also after the verdict: not watched again)
            same = (self.monitor is monitor and not announced and monitor.last_beat is not None
                    and (failure.pid == 0 or incarnation(monitor.last_info) == (failure.host, failure.pid)))
            if self.stopped is None and not current and same:
                self._watch_again()
        if self.stopped is not None:   # a fail-stopped site takes nothing over
            self.undelivered = None
            rospy.logwarn('%s: the failure report of %s is dropped: this site fail-stopped', rospy.get_name(),
                          failure.site)
        elif not current:
            self.undelivered = None
            rospy.logwarn('%s: the failure report of %s is dropped: %s was heard again before a Recovery '
                          'connected', rospy.get_name(), failure.site, failure.site)
            if same:
                alarm(self.ports, 'pbr', 'peer_watched', 'site %s, declared failed (%s) before any Recovery '
                      'connected, is heard again: nothing was fenced or promoted; watched again'
                      % (failure.site, failure.reason))
        elif self._connected('failures'):
            self.undelivered = None
            self.ports.publish('failures', failure)
            rospy.logwarn('%s: the failure report of %s sent late, once Recovery connected', rospy.get_name(),
                          failure.site)
