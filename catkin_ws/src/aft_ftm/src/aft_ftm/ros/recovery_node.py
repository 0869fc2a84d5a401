"""Recovery: fail-silence of the failed site, then failover or going on alone."""
import json
import signal
import threading
import time

import psutil
import rospy
from aft_msgs.srv import Rebind, RebindRequest, SetNodes, SetNodesResponse, SetRole
from aft_msgs.msg import Alarm, Failure
from std_msgs.msg import String

from .. import config, health
from ..power_switch import FenceState, Fencing, SwitchError, parse_spec
from ..power_switch_exec import call_switch
from ..master_watch import Decision, MasterWatch
from ..protocol import Role
from ..realtime import RealtimeBurst
from ..detector import DEFAULT_REALTIME_PRIORITY
from ..recovery import (GATES, Step, failed_steps, incomplete, plan, promoted_unasked, role_after, role_in,
                        start_plan, unfenceable)
from ..sites import silence_trees, this_host
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..witness import Op
from .alarms import alarm
from .diagnostics import Diagnostics
from .fencing import NamespaceFence, named_launcher
from .graph import master_answers
from .params import param
from . import tls_transport
from .deadline import CallTimeout, Deadline
from .persistent_service import PersistentService, open_service
from .ports import Ports
from .protocol_node import ROLES
from .witness_client import WitnessClient, WitnessUnreachable, site_launcher_pid


_RECEIVED_LOCK = threading.Lock()


class RecoveryNode(object):
    """Acts on the crash detector's verdicts about the peer replica.

    Backup whose primary failed: kill what is left of the primary's site and fence and promote
    this replica's After, both at once; then promote the Protocol once it stored every checkpointed
    reply (see aft_ftm.recovery for why this order is safe). Primary whose
    backup failed: kill what is left of the backup's site and tell After to stop
    checkpointing.

    A failover needs no ROS master: at set-up a backup binds its entry (the Protocol, or a SEC gate)
    to the clients' request and reply topics through the entry's rebind service (the Protocol queues
    requests as a backup, executing nothing), and opens a persistent connection to every service
    the failover calls (the nodes' set_role, the witness), which remembers the service's address to
    reconnect without the master. The master is probed every ``~master_check_period``: while it
    does not answer, the alarm ``master_unreachable`` is raised (again every ``~master_alarm_repeat``)
    and the diagnostics say WARN, since nothing can start, re-join or be adapted without it.

    With a witness (``~witness``) every step waits for its vote: a backup is promoted only if the
    witness grants it the next epoch, a primary goes on alone only once the witness excluded the
    backup; a refused or unreachable witness changes nothing (an alarm says so, and an unreachable
    one is asked again every ``~witness_retry``). At start the site registers: if the witness names
    it the first primary it promotes its own nodes (they all start as backups), otherwise its After
    joins the primary. Its role then follows the witness's configuration: re-armed whenever the
    site is primary or backup of a pair again (after a re-join), so a deployment survives any
    number of failures, one at a time.

    Parameters:
        ~role (primary | backup): this replica's role at start.
        ~protocol (str, required): node name of this replica's Protocol.
        ~entry (str, default: the Protocol), ~entry_requests_port (default requests),
            ~entry_replies_port (default replies): the node and ports bound to the clients' topics
            (a SEC gate in front of the Protocol: sec_gate, requests_in, replies_out).
        ~promote (list of node names, default [after]): the nodes fenced and promoted, in order, before
            the Protocol (each one's SetRole last_seq is passed to the next): [before, after] for PBR and
            [before, after] for LFR.
        ~client_requests, ~client_replies (str, required for a backup): the Proxies' topics.
        ~peer_namespace (str, required): namespace of the peer site's nodes.
        ~service_timeout (float, 2 s): limit on each service call of a recovery.
        ~learn_period (float, 2 s): how often the pids of the peer's nodes are learned (for fail-silence).
        ~witness (str, default ''): the witness's aft_msgs/Witness service ('' : none).
        ~site (str, required with a witness): this site's name.
        ~site_pid (int, default: the parent process, the site's roslaunch): the site's incarnation.
        ~witness_retry (float, 0.5 s): how soon an unreachable witness is asked again.
        ~power_switch (str, default '': none): the power switch of the peer's host, called in
            FAIL_SILENCE before any promotion: ``unix:PATH`` (an agent's socket, e.g. the emulated
            hosts' switch) or ``command:ARGV...`` (a fence agent such as fence_ipmilan, exit 0 = off;
            ``{host}`` is replaced by ~peer_host). If it does not confirm the host is off, the
            Protocol is NOT promoted: alarm ``fence_failed``, and the switch is asked again every
            ~fence_retry until it confirms (then the promotion completes).
        ~peer_host (str, required with a power switch): the peer's host as the switch names it.
        ~fence_timeout (float, 10 s): the longest one call of the switch may take.
        ~fence_retry (float, 1 s): how soon a switch that did not confirm is asked again.
        ~master_check_period (float, 1 s): how often the ROS master is probed (each probe limited to it).
        ~master_alarm_repeat (float, 60 s): how often the alarm master_unreachable is repeated while it lasts.
        ~realtime_priority (int 0-99, aft_ftm.detector.DEFAULT_REALTIME_PRIORITY; 0 = off): a failover's
            steps run under SCHED_FIFO at this priority (aft_ftm.realtime), and at the usual priority the
            rest of the time. Without the privilege it warns, raises the alarm ``recovery_priority``, and
            fails over at the usual priority.
    Subscribes:
        failures (aft_msgs/Failure), port ``failures``: from this site's crash detector.
        <witness>'s configuration (aft_msgs/Configuration; its node's ~configuration): this site's role.
        /aft/alarms (aft_msgs/Alarm): the alarms of this site's nodes, recorded on ~events too.
        fail_stop (aft_msgs/Failure): this site's own fail-stop (its nodes publish it to the crash
            detector). A site that fail-stopped takes nothing over: a verdict about the peer that reaches
            Recovery afterwards (reported before the detector heard the fail-stop) is refused with the
            alarm ``promotion_refused``.
    Publishes:
        ~events (std_msgs/String, latched): one JSON record per recovery (steps, durations), per start,
            per configuration change, and per alarm of this site's nodes (``"event": "alarm"``).
        alarms (aft_msgs/Alarm), port ``alarms`` (/aft/alarms): a promotion refused, the witness
            unreachable, this site excluded or deposed, the ROS master unreachable (master_unreachable).
        /diagnostics (diagnostic_msgs/DiagnosticArray): role, epoch, last failover, the master (WARN when
            it does not answer).
    Services:
        ~rebind (aft_msgs/Rebind)
        ~set_promote (aft_msgs/SetNodes): replace the list of nodes to promote (an adaptation
            replaced Before or After); refused, changing nothing, unless each new node answers a
            SetRole for this replica's current role.
    """

    def __init__(self):
        self.role = ROLES[param('role', config.choice('primary', 'backup'), 'backup')]
        self.protocol = rospy.resolve_name(param('protocol', config.non_empty_str, required=True))
        self.entry = rospy.resolve_name(param('entry', config.non_empty_str, self.protocol))
        self.entry_requests = param('entry_requests_port', config.non_empty_str, 'requests')
        self.entry_replies = param('entry_replies_port', config.non_empty_str, 'replies')
        promote = param('promote', config.some_names, ['after'])
        self.promote = [rospy.resolve_name(n) for n in promote]
        self.peer_ns = rospy.resolve_name(param('peer_namespace', config.non_empty_str, required=True))
        witness = param('witness', config.witness_service, '')
        required = self.role == Role.BACKUP or bool(witness)
        self.client_requests = param('client_requests', config.non_empty_str, required=required)
        self.client_replies = param('client_replies', config.non_empty_str, required=required)
        self.timeout = param('service_timeout', config.positive_float, 2.0)
        self.learn_period = param('learn_period', config.positive_float, 2.0)
        self.site = param('site', config.non_empty_str, required=bool(witness)) or ''
        self.retry = param('witness_retry', config.positive_float, 0.5)
        self.master_period = param('master_check_period', config.positive_float, 1.0)
        self.master = MasterWatch(param('master_alarm_repeat', config.positive_float, 60.0))
        self.witness = WitnessClient(witness, self.site, param('site_pid', config.non_negative_int,
                                                               site_launcher_pid())) if witness else None
        switch_text = param('power_switch', config.optional_name, '')
        try:
            switch = parse_spec(switch_text)
            self.fencing = Fencing(switch, param('peer_host', config.optional_name, ''),
                                   param('fence_retry', config.positive_float, 1.0))
        except SwitchError as e:
            raise config.ConfigError('%s: %s' % (rospy.resolve_name('~power_switch'), e))
        self.fence_timeout = param('fence_timeout', config.positive_float, 10.0)
        priority = param('realtime_priority', config.non_negative_int, DEFAULT_REALTIME_PRIORITY)
        try:
            self.burst = RealtimeBurst(priority)
        except ValueError as e:
            raise config.ConfigError('%s: %s' % (rospy.resolve_name('~realtime_priority'), e))
        self.priority_told = self.burst.check() is None
        if not self.priority_told:
            rospy.logwarn('%s: %s: failovers run at the usual priority', rospy.get_name(), self.burst.error)
        self.promotion_waits = False   # PROMOTE_PROTOCOL held back until the switch confirms
        self.claim = self.role != Role.BACKUP   # launched as the first primary
        if self.witness is not None:
            self.role = Role.BACKUP   # every node of the site starts as a backup; the witness decides
        self.lock = threading.Lock()
        self.started = time.monotonic()
        self.fence_refused_told = set()   # names told by a fence_refused alarm
        self.stale_told = set()           # stale registrations of the peer logged
        self.unfenceable_told = False     # fence_incomplete raised (while it holds)
        self.recovered = False
        self.deferred = None        # a verdict of a configuration not seen yet (Failure.epoch): run once it is
        self.stopped = None         # why this site fail-stopped, if it did: it then takes nothing over
        self.last_recovery = None   # the last failover record (~events)
        self.epoch = 0         # the witness's epoch last seen
        self.granted = 0       # the epoch the witness granted to the recovery under way
        self.primary_seen = ''  # the primary of the last configuration seen
        self.unasked = None     # the epoch that made this site primary without its asking, not taken over yet
        self.retrying = None    # the failure report whose recovery waits for the witness (its retry is due)
        self.last_seq = None   # set by PROMOTE_AFTER: the last checkpoint the promoted After holds

    def setup(self, timeout):
        names = [n + '/set_role' for n in self.promote] + (
            [self.protocol + '/set_role', self.entry + '/rebind'] if self.role == Role.BACKUP else [])
        for name in names:
            try:
                rospy.wait_for_service(name, timeout)
            except rospy.ROSException:
                rospy.logerr('%s: service %s not available within %.1f s', rospy.get_name(), name, timeout)
                return False
        # Persistent connections, opened now by no-op calls, so that a failover pays no connection set-up
        # and needs no master (each remembers its service's address).
        self.set_role_nodes = [PersistentService(n + '/set_role', SetRole) for n in self.promote]
        self.set_role_protocol = PersistentService(self.protocol + '/set_role', SetRole)
        self.rebind_entry = PersistentService(self.entry + '/rebind', Rebind)
        try:
            for set_role in self.set_role_nodes:
                set_role(role=self.role.value)
            if self.role == Role.BACKUP:
                self.set_role_protocol(role=self.role.value, last_seq=0)
                # The entry hears the clients from now on (a backup queues their requests, executes none)
                # and its replies reach them: a failover binds nothing (a new subscription needs the master).
                for port, topic, direction in ((self.entry_replies, self.client_replies, RebindRequest.PUBLISH),
                                               (self.entry_requests, self.client_requests, RebindRequest.SUBSCRIBE)):
                    bound = self.rebind_entry(port=port, topic=topic, direction=direction, activate=True)
                    if not bound.success:
                        rospy.logerr('%s: cannot bind port %s of %s to %s: %s', rospy.get_name(), port, self.entry,
                                     topic, bound.message)
                        return False
        except (rospy.ServiceException, rospy.ROSException) as e:
            rospy.logerr('%s: cannot reach this replica\'s nodes: %s', rospy.get_name(), e)
            return False
        # The peer's pids are learned once this replica's own nodes answer. Learning from the first
        # moment was tried (session 35) and undone: with both sites in one roslaunch, the first pass
        # found some of the peer's nodes not registered yet, took what it saw for complete, and waited
        # a whole ~learn_period; a peer frozen meanwhile kept two nodes alive (replication.test, CI).
        # A peer failing before it is learned is silenced through its launcher's children
        # (fencing.launcher_roots).
        self.fence = NamespaceFence(self.peer_ns, rospy.get_name())
        threading.Thread(target=self._learn_peer, name='learn-peer', daemon=True).start()
        self.events = rospy.Publisher('~events', String, queue_size=10, latch=True)
        self.ports = Ports([PortSpec('failures', SUBSCRIBE, 'aft_msgs/Failure'),
                            PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')], {'failures': self._on_failure})
        self.ports.bind('alarms', '/aft/alarms')
        if self.witness is not None and not (self.witness.setup(timeout) and self._register(timeout)):
            return False
        self.ports.bind('failures')
        self.ports.advertise_service()
        rospy.Service('~set_promote', SetNodes, self._on_set_promote)
        if self.witness is not None:
            self.configuration = self.witness.subscribe(self._on_configuration, report=lambda detail: alarm(self.ports, 'witness', 'forged_configuration', detail))
        self.alarm_log = rospy.Subscriber('/aft/alarms', Alarm, self._on_alarm, tcp_nodelay=True)
        self.own_fail_stop = rospy.Subscriber('fail_stop', Failure, self._on_own_fail_stop, tcp_nodelay=True)
        self.diagnostics = Diagnostics(self._health, self.site)
        threading.Thread(target=self._watch_master, name='watch-master', daemon=True).start()
        return True

    def _health(self):
        with self.lock:
            role, epoch, last = self.role, self.epoch, self.last_recovery
        return health.recovery(self.site or rospy.get_namespace().strip('/'), role, epoch, last,
                               self.master.unreachable_for(time.monotonic()))

    def _watch_master(self):
        """Probe the ROS master every ~master_check_period: its loss is a degraded state (alarmed)."""
        while not rospy.is_shutdown():
            t0 = time.monotonic()
            answered, why = master_answers(self.master_period)
            decision = self.master.probe(answered, time.monotonic(), why)
            if decision == Decision.ALARM:
                alarm(self.ports, 'ros', 'master_unreachable', 'the ROS master has not answered for %.0f s (%s): '
                      'failovers still work over the connections open, but no node can start, re-join or be '
                      'adapted until it is back' % (self.master.unreachable_for(time.monotonic()), why))
            elif decision == Decision.BACK:
                rospy.loginfo('%s: the ROS master answers again', rospy.get_name())
            self._tell_priority_refused()
            time.sleep(max(0.0, self.master_period - (time.monotonic() - t0)))

    def _tell_priority_refused(self):
        """The alarm that failovers run without real-time priority: once, when a subscriber of the alarms
        is connected (published at once, it would reach nobody), or 10 s after the start in any case."""
        if self.priority_told:
            return
        publisher = self.ports.publisher('alarms')
        if (publisher is not None and publisher.get_num_connections() > 0) or time.monotonic() - self.started > 10.0:
            self.priority_told = True
            alarm(self.ports, 'pbr', 'recovery_priority', 'the Recovery of site %s runs failovers without '
                  'real-time priority (%s): under load they take longer' % (self.site or rospy.get_name(),
                                                                          self.burst.error))

    def _on_alarm(self, msg):
        """Every alarm of this site's nodes (a degraded state) is also an event of this site."""
        if msg.source.startswith(rospy.get_namespace()) and msg.source != rospy.get_name():
            self._event({'event': 'alarm', 'kind': msg.kind, 'source': msg.source, 'detail': msg.detail,
                         'stamp': msg.stamp.to_sec()})

    def _event(self, record):
        """Publish one record on ~events. The topic is latched (a late subscriber gets the last record
        only), so every other record carries the last recovery as ``last_recovery``."""
        if 'failed_site' in record:
            self.last_recovery = record
        else:
            record = dict(record, last_recovery=self.last_recovery)
        self.events.publish(String(data=json.dumps(record)))

    def _register(self, timeout):
        """Ask the witness whether this site serves; if it is the first primary, promote its nodes."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                grant = self.witness.request(Op.REGISTER, claim=self.claim)
            except WitnessUnreachable as e:
                # Asked again within the set-up time: the witness may have granted it, its answer lost
                # (a slow disk past the call limit). Given up at once, the site stopped, and its next
                # incarnation was refused the first primary's role for good (review of the witness,
                # session 33); the same incarnation is granted again.
                if time.monotonic() > deadline or rospy.is_shutdown():
                    rospy.logerr('%s: %s', rospy.get_name(), e)
                    return False
                rospy.logwarn('%s: %s: asked again', rospy.get_name(), e)
                time.sleep(0.2)
                continue
            if grant.granted or grant.primary or time.monotonic() > deadline:
                break
            time.sleep(0.05)   # no primary yet: the first primary's site registers first
        self.epoch = grant.epoch
        record = {'event': 'start', 'site': self.site, 'epoch': grant.epoch, 'primary': grant.primary,
                  'backup': grant.backup, 'witness': grant.message, 'steps': [], 'ok': True}
        if grant.granted and grant.primary == self.site:
            self.granted = grant.epoch
            self._start = time.monotonic()
            self._run_plan(start_plan(), None, record)
            if not record['ok']:
                rospy.logerr('%s: could not take the first primary role: %s', rospy.get_name(), record['steps'])
                return False
            self.role = Role.ALONE
        record['role_after'] = self.role.name
        rospy.loginfo('%s: registered with the witness at epoch %d: %s', rospy.get_name(), grant.epoch, grant.message)
        self._event(record)
        return True

    def _on_configuration(self, conf):
        """Follow the witness: this site's role in each new configuration; re-armed in a pair."""
        with self.lock:
            if conf.epoch <= self.epoch:
                return
            self.epoch = conf.epoch
            before, deposed = self.role, self.primary_seen
            self.role = role_in(conf.primary, conf.backup, self.site)
            self.primary_seen = conf.primary
            waiting = deferred = None
            if self.role in (Role.PRIMARY, Role.BACKUP):
                self.recovered = False
                self.fencing.rearm()
                # A promotion held for the power switch when the peer re-joined as this site's backup
                # (its new incarnation took this site's state): forgotten here, it left the Protocol a
                # backup for good while the witness named this site the primary (review of stop 39).
                waiting = self.promotion_waits and self.role == Role.PRIMARY
                self.promotion_waits = False
                # A verdict on the re-joined peer that came before this configuration did (the
                # callbacks are not ordered): dropped, the backup never took over (review of stop 39).
                if self.deferred is not None and self.deferred.epoch == conf.epoch:
                    deferred, self.deferred = self.deferred, None
            if self.deferred is not None and self.deferred.epoch < conf.epoch:
                # Its own configuration was skipped (the latched topic gives only the latest): the
                # incarnation it judged may be gone; the re-armed detector judges the one there now.
                self.deferred = None
            unasked = self.witness is not None and promoted_unasked(before, self.role, self.site, conf.primary,
                                                                    self.granted, conf.epoch)
            # Until it is carried out, any failure handling here takes over as the backup it was (the
            # old primary, deposed, fail-stops at once: its detector's verdict may come first).
            self.unasked = conf.epoch if unasked else None
            retrying, self.retrying = self.retrying, None   # a new configuration: its retry is dropped
        record = {'event': 'configuration', 'epoch': conf.epoch, 'primary': conf.primary, 'backup': conf.backup,
                  'reason': conf.reason, 'role_before': before.name if before else None,
                  'role_after': self.role.name if self.role else None}
        self._event(record)
        if unasked:
            # Taken over as if the peer had failed (a recovery under way already makes this a no-op).
            why = ('the witness made %s the primary of epoch %d (%s) without this Recovery asking: a late '
                   'PROMOTE; %s is deposed and this site takes over' % (self.site, conf.epoch, conf.reason, deposed))
            alarm(self.ports, 'pbr', 'late_promotion', why)
            failure = Failure(site=deposed or '', host='', pid=0, reason=why, silence=0.0, detected=rospy.Time.now())
            if retrying is not None and deposed in ('', retrying.site):
                # The grant of the recovery whose witness call timed out (the witness answered late): its
                # report names the failed launcher, which fail-silence kills with the rest. Without it,
                # only the nodes learned by pid were, and the launcher could start them again (review of
                # session 36). Its silence and reception time stand (_received_at).
                failure = Failure(site=retrying.site, host=retrying.host, pid=retrying.pid, reason=why,
                                  silence=retrying.silence, detected=retrying.detected, epoch=retrying.epoch)
            threading.Thread(target=self._on_failure, args=(failure, Role.BACKUP), daemon=True).start()
        if waiting:
            threading.Thread(target=self._complete_promotion, args=(conf,), daemon=True).start()
        if deferred is not None:
            threading.Thread(target=self._on_failure, args=(deferred,), daemon=True).start()
        if self.role is None and before is not None:
            alarm(self.ports, 'pbr', 'out_of_configuration', '%s is in no configuration of epoch %d (primary %r, '
                  'backup %r: %s): it neither serves nor takes over until it re-joins'
                  % (self.site, conf.epoch, conf.primary, conf.backup, conf.reason))

    def _on_set_promote(self, req):
        names = [rospy.resolve_name(n) for n in req.nodes]
        if not names or not all(req.nodes):
            return SetNodesResponse(success=False, message='give a non-empty list of node names',
                                    previous=self.promote)
        # The new nodes are told the site's role outside the lock, each call bounded: a replacement node
        # frozen or hung held the lock for ever, and a failure of the peer meanwhile was never recovered
        # from, with no alarm (review of session 36). The role is checked unchanged once they answered.
        with self.lock:
            role = self.role
        proxies = []
        deadline = Deadline('set-promote')
        try:
            for name in names:
                try:
                    proxy = open_service(name + '/set_role', SetRole, self.timeout)
                    answer = deadline.call(proxy, self.timeout, role=role.value)
                except (rospy.ServiceException, rospy.ROSException, CallTimeout) as e:
                    return SetNodesResponse(success=False, previous=self.promote,
                                            message='%s/set_role cannot be called: %s' % (name, e))
                if not answer.success:
                    return SetNodesResponse(success=False, previous=self.promote,
                                            message='%s refused role %s: %s' % (name, role.name, answer.message))
                proxies.append(proxy)
        finally:
            deadline.close()   # its worker thread ends (one per request otherwise)
        with self.lock:   # no recovery runs while the list changes
            if self.role != role:
                return SetNodesResponse(success=False, previous=self.promote,
                                        message='the site\'s role changed from %s to %s while the nodes were told '
                                        'it: ask again' % (role.name, self.role.name if self.role else None))
            previous, self.promote, self.set_role_nodes = self.promote, names, proxies
        rospy.loginfo('%s: nodes to promote are now %s (were %s)', rospy.get_name(), names, previous)
        return SetNodesResponse(success=True, message='promote %s' % ', '.join(names), previous=previous)

    def _set_role(self, index, **request):
        """Call set_role of promote node index; reconnect once if the persistent connection broke (to the
        address known, if the master cannot be asked)."""
        try:
            return self.set_role_nodes[index](**request)
        except (rospy.ServiceException, rospy.ROSException):   # the broken connection is closed: retried
            return self.set_role_nodes[index](**request)

    def _on_own_fail_stop(self, failure):
        with self.lock:
            first = self.stopped is None
            self.stopped = self.stopped or failure.reason or 'fail-stop'
        if first:
            self._event({'event': 'fail_stop', 'reason': self.stopped})

    def _complete_promotion(self, conf):
        """The peer re-joined as this site's backup while this site's promotion waited for the power
        switch: the witness names this site the primary, so its Protocol is promoted now. The failed
        site was never confirmed off: said (``promotion_unfenced``)."""
        with self.lock:
            self._start = time.monotonic()
            record = {'failed_site': self.peer_ns.strip('/'), 'reason': 'the peer re-joined before the power switch '
                      'confirmed it off', 'steps': [], 'ok': True, 'late_promotion': True,
                      'role_before': self.role.name if self.role else None}
            self._run_step(Step.PROMOTE_PROTOCOL, None, record)
            record['seconds'] = time.monotonic() - self._start
            record['done_wall'] = time.time()
            record['role_after'] = self.role.name if self.role else None
        alarm(self.ports, 'pbr', 'promotion_unfenced', '%s re-joined as the backup of %s (epoch %d) before the power '
              'switch confirmed its old incarnation off: the promotion that waited for it %s' % (
                  conf.backup, self.site, conf.epoch,
                  'is completed now' if record['ok'] else 'could not be completed (%s): nobody serves until it is'
                  % failed_steps(record)))
        self._event(record)

    def _received_at(self, failure):
        """When this Recovery first had the failure report (monotonic). The time since the failed site was
        last heard is the report's silence plus the time since: on clocks that do not step. It was the
        wall clock less the report's stamp, which is the simulated time under /use_sim_time, and a clock
        step during a witness retry took the launcher for a reused pid and spared its tree (review of
        session 36)."""
        k = (failure.site, failure.detected.secs, failure.detected.nsecs, failure.pid)
        with _RECEIVED_LOCK:
            received = self.__dict__.setdefault('_received', {})   # failure report -> when first had
            at = received.get(k)
            if at is None:
                at = received[k] = time.monotonic()
                while len(received) > 64:
                    received.pop(next(iter(received)))
        return at

    def _on_failure(self, failure, retried_role=None):
        self._received_at(failure)
        retry = False
        with self.lock:
            if self.recovered:
                if failure.epoch > self.epoch:
                    # The detector watched the peer afresh for a configuration this Recovery has not
                    # seen yet: kept until it has (then run), never dropped.
                    self.deferred = failure
                    rospy.logwarn('%s: %s failed (watched since epoch %d, not seen here yet): kept until that '
                                  'configuration comes', rospy.get_name(), failure.site, failure.epoch)
                return
            self.recovered = True
            stopped = self.stopped
        if stopped is not None:
            # A verdict its crash detector reported before it heard this site's own fail-stop (the stall
            # of campaign seed 15, segment 20): a fail-stopped site never becomes the primary, nor the lone one.
            alarm(self.ports, 'pbr', 'promotion_refused', '%s failed, but site %s fail-stopped itself (%s): it '
                  'takes nothing over; nobody serves until a replica holding the state returns'
                  % (failure.site, self.site or rospy.get_namespace().strip('/'), stopped))
            self._event({'failed_site': failure.site, 'reason': failure.reason, 'steps': [], 'ok': False,
                         'refused': 'this site fail-stopped: %s' % stopped, 'detected_wall': failure.detected.to_sec()})
            return
        with self.lock:
            # A retry keeps the role of its first attempt: the witness may have granted that attempt late,
            # and the configuration it published since names this site alone, with nothing promoted yet.
            role = retried_role or (Role.BACKUP if self.unasked is not None else self.role)
            self.unasked = None
            record = {'failed_site': failure.site, 'reason': failure.reason, 'silence': failure.silence,
                      'role_before': role.name if role else None, 'steps': [], 'ok': True,
                      'detected_wall': failure.detected.to_sec()}
            self._start = time.monotonic()
            self._run_plan(plan(role, self.witness is not None), failure, record)
            record['seconds'] = time.monotonic() - self._start
            record['done_wall'] = time.time()
            witness_steps = [st for st in record['steps'] if st['step'] in {g.name for g in GATES}]
            if witness_steps and not witness_steps[0]['ok']:
                retry = 'unreachable' in witness_steps[0]['detail']
                self.recovered = not retry
                self.retrying = failure if retry else None
            else:
                self.role = role_after(role) if role else None
            record['role_after'] = self.role.name if self.role else None
        rospy.logwarn('%s: recovery from the failure of %s in %.1f ms: %s', rospy.get_name(), failure.site,
                      record['seconds'] * 1e3, ', '.join('%s %.1f ms%s' % (s['step'], s['seconds'] * 1e3,
                                                                          '' if s['ok'] else ' FAILED')
                                                          for s in record['steps']) or 'nothing to do')
        for st in record['steps']:
            rospy.loginfo('%s: %s: %s', rospy.get_name(), st['step'], st['detail'])
        self._event(record)
        if record['role_before'] is None and self.witness is not None:
            # Excluded or deposed: the peer's failure leaves nobody with the state. Never silent.
            alarm(self.ports, 'pbr', 'promotion_refused', '%s failed and %s cannot take over: it is in no '
                  'configuration of the witness (epoch %d); nobody serves until a replica holding the state returns'
                  % (failure.site, self.site, self.epoch))
        failed = failed_steps(record)
        if failed and not retry and not self.promotion_waits:   # a fence retry completes it otherwise
            kind, consequence = incomplete(role, record)
            alarm(self.ports, 'pbr', kind, '%s failed and %s did not complete its recovery: %s; %s'
                  % (failure.site, self.site or rospy.get_name(), failed, consequence))
        if retry:
            threading.Timer(self.retry, self._retry_failure, [failure, role, self.epoch]).start()
        elif record['ok'] and record['steps']:
            threading.Thread(target=self._clean_master, daemon=True).start()

    def _retry_failure(self, failure, role, epoch):
        """A recovery retried after the witness was unreachable; dropped if a newer configuration came
        meanwhile: the failed site may have re-registered or re-joined since, and the retry would
        exclude and fence its new, healthy incarnation (review of stop 39). The failure it was about
        was decided by whoever made that configuration; the detector, re-armed when the site is back,
        judges the new incarnation afresh."""
        with self.lock:
            moved = self.epoch != epoch
            if moved and self.role in (Role.PRIMARY, Role.BACKUP):
                self.recovered = False
        if moved:
            rospy.logwarn('%s: the retried recovery from the failure of %s is dropped: the witness is at epoch %d '
                          '(was %d when it was tried)', rospy.get_name(), failure.site, self.epoch, epoch)
            self._event({'event': 'retry_dropped', 'failed_site': failure.site, 'epoch': self.epoch,
                         'since': epoch})
            return
        self._on_failure(failure, role)

    def _run_plan(self, waves, failure, record):
        """Run the waves of a plan; a failed gate (the witness's vote) ends it."""
        for wave in waves:
            threads = [threading.Thread(target=self._run_step, args=(step, failure, record)) for step in wave]
            began = time.monotonic()
            for thread in threads:
                thread.start()
            for step, thread in zip(wave, threads):
                self._wait_step(step, thread, failure, began)
            if any(not st['ok'] for st in record['steps'] if Step[st['step']] in GATES):
                return

    def _wait_step(self, step, thread, failure, began):
        """Wait for a step (started at ``began``) as long as it runs: a frozen node of this site only
        delays the promotion (its call is answered once the node runs again; a new call would not be,
        nor would a refusal serve). Never silent: past ~service_timeout (for fencing through a power
        switch, ~fence_timeout more), the alarm recovery_slow names the step."""
        patience = self.timeout + (self.fence_timeout if step == Step.FAIL_SILENCE and self.fencing.switch else 0.0)
        thread.join(max(0.0, began + patience - time.monotonic()))
        if not thread.is_alive():
            return
        why = 'from the failure of %s' % failure.site if failure is not None else 'taking the first primary role'
        alarm(self.ports, 'pbr', 'recovery_slow', 'the recovery of %s %s waits for its step %s, running for %.1f s: '
              'what it calls does not answer (a node of this site, the witness or the power switch: frozen, hung '
              'or overloaded); nobody serves meanwhile'
              % (self.site or rospy.get_name(), why, step.name, time.monotonic() - began))
        thread.join()
        rospy.logwarn('%s: step %s ended after %.1f s', rospy.get_name(), step.name, time.monotonic() - began)

    def _run_step(self, step, failure, record, do=None):
        t0 = time.monotonic()
        try:
            with self.burst():   # this thread only: what it starts runs at the usual priority
                detail = (do or self._do)(step, failure)
            ok = True
        except Exception as e:   # a failed step is reported, and the next ones still run
            detail, ok = str(e), False
            record['ok'] = False
            rospy.logerr('%s: recovery step %s failed: %s', rospy.get_name(), step.name, e)
        record['steps'].append({'step': step.name, 'ok': ok, 'detail': detail,
                                'start': t0 - self._start, 'seconds': time.monotonic() - t0})

    def _do(self, step, failure):
        stopped = self.stopped
        if stopped is not None and step != Step.FAIL_SILENCE:
            # Its own fail-stop heard during the recovery (the two topics are not ordered): nothing more
            # is taken over; fencing the failed peer still is harmless.
            raise RuntimeError('site %s fail-stopped itself (%s): it takes nothing over' % (self.site, stopped))
        if step in (Step.WITNESS_PROMOTE, Step.WITNESS_EXCLUDE):
            op = Op.PROMOTE if step == Step.WITNESS_PROMOTE else Op.EXCLUDE
            try:
                grant = self.witness.request(op)
            except WitnessUnreachable as e:
                alarm(self.ports, 'pbr', 'witness_unreachable', '%s cannot reach the witness (%s): it does not %s; '
                      'asked again in %.1f s' % (self.site, e, 'take over' if op == Op.PROMOTE else 'go on alone',
                                                 self.retry))
                raise RuntimeError('witness unreachable: %s' % e)
            if not grant.granted:
                alarm(self.ports, 'pbr', 'promotion_refused' if op == Op.PROMOTE else 'deposed',
                      '%s: the witness refused %s: %s' % (self.site, op.name, grant.message))
                raise RuntimeError('the witness refused %s: %s' % (op.name, grant.message))
            self.granted = grant.epoch
            return 'epoch %d: %s' % (grant.epoch, grant.message)
        if step == Step.FAIL_SILENCE:
            return self._fail_silence(failure)
        if step == Step.PROMOTE_AFTER:
            last_seq = 0
            for index, name in enumerate(self.promote):
                result = self._set_role(index, role=Role.ALONE.value, last_seq=last_seq, epoch=self.granted,
                                        initial=failure is None)
                if not result.success:
                    raise RuntimeError('%s refused: %s' % (name, result.message))
                last_seq = result.last_seq
            self.last_seq = last_seq
            return 'last checkpoint %d' % last_seq
        if step == Step.PROMOTE_PROTOCOL:
            if self.last_seq is None:
                # Never a Protocol serving clients without its After fenced against the old primary.
                raise RuntimeError('not promoted: the After was not promoted (see PROMOTE_AFTER)')
            if not self.fencing.may_promote():
                # Never a Protocol serving clients while the old primary's host may still answer them.
                self.promotion_waits = True
                raise RuntimeError('not promoted: the power switch did not confirm %s is off (%s); asked again '
                                   'every %.1f s' % (self.fencing.host, self.fencing.last and
                                                     self.fencing.last.detail, self.fencing.retry_period))
            result = self.set_role_protocol(role=Role.ALONE.value, last_seq=self.last_seq, epoch=self.granted)
            if not result.success:
                raise RuntimeError('Protocol refused: %s' % result.message)
            return result.message
        if step == Step.AFTER_ALONE:
            for index, name in enumerate(self.promote):
                result = self._set_role(index, role=Role.ALONE.value, epoch=self.granted)
                if not result.success:
                    raise RuntimeError('%s refused: %s' % (name, result.message))
            return 'going on alone'
        raise ValueError(step)

    def _learn_peer(self):
        while not rospy.is_shutdown():
            complete = True
            try:
                if not self.recovered:   # re-armed after a re-join: the peer's new pids are learned
                    self.fence.learn()
                    complete = not self.fence.unlearned
                    self._tell_fence_refused()
                    self._tell_unfenceable()
                    self._log_stale()
            except Exception as e:   # the master is unreachable for a while: try again later
                rospy.logwarn_throttle(30, '%s: cannot learn the nodes of %s: %s' % (rospy.get_name(), self.peer_ns, e))
            # A node of the peer not learned yet (its site is starting) cannot be killed by pid if it
            # freezes: ask again soon, not a whole period later.
            rospy.sleep(self.learn_period if complete else min(self.learn_period, 0.2))

    def _not_told(self, table, told):
        """[(name, why)] of a fence table (name -> why) not in ``told`` yet, now added to it; a name gone from
        the table is forgotten from ``told``, so that it is told again if it comes back."""
        with self.fence.lock:
            current = dict(table)
        told &= set(current)
        fresh = [(name, why) for name, why in sorted(current.items()) if name not in told]
        told.update(name for name, _ in fresh)
        return fresh

    def _log_stale(self):
        """Log once each registration of the peer left by a dead node whose port another process holds now."""
        for name, why in self._not_told(self.fence.stale, self.stale_told):
            rospy.loginfo('%s: %s is registered still, but its process died and %s: left alone', rospy.get_name(),
                          name, why)

    def _tell_fence_refused(self):
        """The alarm ``fence_refused``, once per name while it stays registered: a node registered under the peer's name
        space whose API named a process that is not it (a forged registration, or a node's name taken
        over). That process is never signalled for the peer; if the real node runs elsewhere under that
        name, fail-silence cannot reach it by pid."""
        if not self._alarms_heard():
            return   # told once someone hears it (or 10 s after the start in any case)
        for name, why in self._not_told(self.fence.refused, self.fence_refused_told):
            alarm(self.ports, 'pbr', 'fence_refused', '%s is registered under %s, but %s: that process is never '
                  'killed for this site\'s fail-silence' % (name, self.peer_ns, why))

    def _tell_unfenceable(self):
        """The alarm ``fence_incomplete``, once while it holds (again if it holds again later): nodes of
        the peer on another machine, and no power switch to silence them (recovery.unfenceable)."""
        with self.fence.lock:
            remote = dict(self.fence.remote)
        why = unfenceable(remote, self.fencing.switch is not None, tls_transport.active())
        if why is None:
            self.unfenceable_told = False
            return
        if self.unfenceable_told or not self._alarms_heard():
            return
        self.unfenceable_told = True
        alarm(self.ports, 'pbr', 'fence_incomplete', '%s cannot make %s silent at a failover: %s' % (
            rospy.get_name(), self.peer_ns, why))

    def _alarms_heard(self):
        """Whether an alarm published now is heard: a subscriber is connected, or 10 s have passed."""
        publisher = self.ports.publisher('alarms') if getattr(self, 'ports', None) is not None else None
        return publisher is not None and (publisher.get_num_connections() > 0 or
                                          time.monotonic() - self.started >= 10.0)

    def _fail_silence(self, failure):
        """Kill what is left of the failed site: its host powered off by the power switch (if one is
        configured: a failure of it fails this step, and no promotion follows), its launcher's whole
        process tree when the heartbeat names one on this host that started a node learned of its name
        space (a forged heartbeat names any pid), and every node of its name space whose pid was learned."""
        done = []
        if self.fencing.begin(time.monotonic()) is FenceState.FENCING:
            outcome = self._ask_switch()
            if not outcome.confirmed:
                raise RuntimeError(outcome.detail)
            done.append(outcome.detail)
        t0 = time.monotonic()
        nodes = self.fence.processes()
        roots = []
        if failure.pid > 0 and failure.host == this_host():
            roots, why = self._launcher(failure)
            done.append(why)
        # Every thread seen stopped, then all killed: none runs another instruction or can be resumed, and
        # the promotion does not wait for their tear-down.
        killed = silence_trees(roots, list(nodes.values()))
        done.append('%d processes of %s stopped and killed (%d nodes learned by pid)' % (
            len(killed), failure.site, len(nodes)))
        return '%s in %.1f ms' % ('; '.join(done), (time.monotonic() - t0) * 1e3)

    def _ask_switch(self):
        """One call of the power switch (state FENCING); settles the Fencing. A switch that does not
        confirm raises the alarm fence_failed and is asked again after ~fence_retry."""
        outcome = call_switch(self.fencing.switch, self.fencing.host, self.fence_timeout)
        self.fencing.settle(outcome, time.monotonic())
        if not outcome.confirmed:
            alarm(self.ports, 'pbr', 'fence_failed', '%s cannot fence %s (attempt %d): %s; no promotion until the '
                  'switch confirms it is off, asked again in %.1f s' % (self.site or rospy.get_name(),
                                                                      self.fencing.host, self.fencing.attempts,
                                                                      outcome.detail, self.fencing.retry_period))
            timer = threading.Timer(self.fencing.retry_period, self._retry_fence)
            timer.daemon = True
            timer.start()
        return outcome

    def _retry_fence(self):
        """Ask the switch again; once it confirms, complete a promotion that waited for it."""
        if rospy.is_shutdown():
            return
        with self.lock:
            now = time.monotonic()
            state = self.fencing.retry(now)
            if state is FenceState.REFUSED:   # woken a little early: not due yet
                timer = threading.Timer(max(0.01, self.fencing.next_try - now), self._retry_fence)
                timer.daemon = True
                timer.start()
                return
            if state is not FenceState.FENCING:
                return   # re-armed meanwhile (the peer re-joined)
            self._start = time.monotonic()
            record = {'failed_site': self.peer_ns.strip('/'), 'reason': 'fencing retried', 'steps': [], 'ok': True,
                      'role_before': self.role.name if self.role else None, 'late_promotion': self.promotion_waits}
            self._run_step(Step.FAIL_SILENCE, None, record, do=self._ask_switch_step)
            if record['ok'] and self.promotion_waits:
                self.promotion_waits = False
                self._run_step(Step.PROMOTE_PROTOCOL, None, record)
            record['seconds'] = time.monotonic() - self._start
            record['done_wall'] = time.time()
            record['role_after'] = self.role.name if self.role else None
        if record['ok']:
            rospy.logwarn('%s: %s confirmed off by the power switch after %d attempts%s', rospy.get_name(),
                          self.fencing.host, self.fencing.attempts,
                          '; the promotion completed' if record['late_promotion'] else '')
            self._event(record)
            threading.Thread(target=self._clean_master, daemon=True).start()

    def _ask_switch_step(self, step, failure):
        outcome = self._ask_switch()
        if not outcome.confirmed:
            raise RuntimeError(outcome.detail)
        return outcome.detail

    def _launcher(self, failure):
        """([psutil.Process] whose trees fail-silence kills for the failed site's launcher on this host,
        what was found): see fencing.launcher_roots."""
        since_heard = failure.silence + max(0.0, time.monotonic() - self._received_at(failure))
        launcher, pids, why, refused, partial = named_launcher(failure.pid, failure.site, self.peer_ns,
                                                               self.fence.prefix, since_heard, self.fence.started)
        if launcher is None:
            return [], why
        if partial:
            # It runs more than the failed site: stopped for good (it starts nothing of the site again, a
            # respawn or a node it had not started yet), then its children read again, now that none
            # can come or go; its other nodes run on. Never silent.
            try:
                launcher.send_signal(signal.SIGSTOP)
            except psutil.Error:
                pass
            _, pids, why, refused, partial = named_launcher(failure.pid, failure.site, self.peer_ns,
                                                            self.fence.prefix, since_heard, self.fence.started)
            alarm(self.ports, 'pbr', 'fence_partial', '%s; it stays stopped (SIGSTOP) so that it starts nothing of '
                  '%s again: its other nodes run on without their launcher until an operator resumes or restarts '
                  'it' % (why, failure.site))
        if refused:   # a forged heartbeat or failure report names any pid it likes
            alarm(self.ports, 'pbr', 'fence_refused', why)
        roots = []
        for pid in pids:
            try:
                proc = launcher if pid == failure.pid else psutil.Process(pid)
                if proc is launcher or proc.ppid() == failure.pid:
                    roots.append(proc)
            except psutil.NoSuchProcess:
                continue
        return roots, why

    def _clean_master(self):
        """Ask the failed site's remaining nodes to shut down, and unregister the dead ones. Best effort,
        after the failover: skipped while the master does not answer (its loss is alarmed by
        _watch_master, not here)."""
        if self.master.unreachable_for(time.monotonic()) is not None:
            rospy.loginfo('%s: the master does not answer: the nodes of %s are not unregistered', rospy.get_name(),
                          self.peer_ns)
            return
        try:
            count = self.fence.shut_down_the_rest()
            rospy.loginfo('%s: master cleaned of %d nodes of %s', rospy.get_name(), count, self.peer_ns)
        except Exception as e:   # best effort: the failover is already done
            rospy.logwarn('%s: could not clean the master of %s: %s', rospy.get_name(), self.peer_ns, e)
