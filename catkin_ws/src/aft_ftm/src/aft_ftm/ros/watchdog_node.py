"""The watchdog of a replicated pub/sub node (the second paper's Arduino, section III.D): it watches
every board by role and, when the primary board's heartbeats stop, switches to the backup; a board
brought back re-joins and becomes the backup again. The logic is aft_ftm.board_watch (no rospy)."""
import json
import os
import threading
import time
import uuid

import psutil
import rospy
from aft_msgs.msg import Alarm, PrimaryBoard
from aft_msgs.srv import SetRole
from std_msgs.msg import String

from .. import config, health
from ..board_watch import BoardWatch, Connect, Failover, Report, boards_param
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import Role
from ..sites import power_off_trees, this_host
from .fencing import named_launcher
from .diagnostics import Diagnostics
from .params import param
from .ports import Ports


class WatchdogNode(object):
    """Watches each board's heartbeats and its After's acknowledgments (aft_ftm.board_watch). When
    the primary is silent for ``~timeout`` and a backup can take over:

    1. its fail-silence is enforced: a board that only stalled must not come back as a second
       primary, so the process tree of its launcher is stopped, then killed (if it runs on this host);
    2. as soon as it is stopped and sent SIGKILL, the backup is promoted: SetRole ALONE on each of its
       nodes, in order, over connections opened
       before the failure (a failover does not need the ROS master). Only a board that acknowledged
       a checkpoint of the primary is ever promoted. A node that does not answer within
       ``~service_timeout`` is waited for on the same call, ``PROMOTE_TRIES`` periods in all (each node);
    3. the failover is published, with the detection time (the silence) and the switch time.

    Which board is the primary is said on ``primary`` (latched), at the start and at each take-over
    once the backup's nodes all took their role (a failed promotion says nothing: a board that only
    stalled drives on), with a term one more each time: a consumer of the replicated output (the car's
    commandManager) takes it from those nodes only, and the boards' Afters of another board step down
    (aft_ftm.primary_word). Where this watchdog cannot power a failed board off (another host's, with no
    switch), that board resumed still publishes, until it hears the word.

    A silent primary with no backup, or a silent backup, is reported and left running (it is not
    promoted while silent). A board heard from a new launcher (it was started again) holds no state:
    it is not promoted until its After acknowledged a checkpoint of the primary; the watchdog then
    opens its connections to that board's nodes, and it is the backup. Every such step raises an alarm.

    Parameters:
        ~boards (dict, required): {board: [node to promote, ...]} for each board (two or more), by
            the board's site name (as in its heartbeats)
        ~primary (str, required): the board that starts as the primary; the others start as backups
        ~timeout (float, 0.05 s): the silence that declares a board failed
        ~stall_after (float, ~timeout / 5): a check of the heartbeats later than this after the previous
            one was the watchdog's own stall, not held against the boards (aft_ftm.detector)
        ~startup_grace (float, 0 = never): declare a board never heard failed after this long
        ~service_timeout (float, 2 s): limit on each promotion call and on opening a re-joined board's
            connections
        ~niceness (int, -5): a watchdog must not be starved by the load it watches
        ~suspend_lease (float, 10 s), ~suspend_buffer_bytes (int, 64 MiB): the lease of a suspension
            and the bound of what it holds (every FTM node: see aft_ftm.ros.ports.Ports).
    Subscribes:
        heartbeat/<board> (aft_msgs/Heartbeat), port ``heartbeat/<board>``: each board's crash detector
        acks/<board> (aft_msgs/CheckpointAck), port ``acks/<board>``: each board's After's acknowledgments
    Publishes:
        primary (aft_msgs/PrimaryBoard, latched), port ``primary``: the primary board and its nodes
            (those promoted), the term (1 at the start, one more at each take-over) and this run's
            incarnation
        events (std_msgs/String), port ``events``: one JSON record per failover (kind ``failover``),
            board brought back (``board_back``) and re-join (``rejoin``)
        alarms (aft_msgs/Alarm), port ``alarms``: mechanism ``pbr``, kinds ``board_failed`` (a failover),
            ``failover_failed``, ``primary_silent``, ``board_silent``, ``board_back``, ``board_rejoined``,
            ``backup_unreachable``, ``backup_restarted``, ``stale_announcement`` (a fail-stop announced by
            another incarnation than the board's: late, or forged; ignored)
    Services:
        ~rebind (aft_msgs/Rebind), ~suspend/~resume (aft_msgs/Suspend)
    """

    def __init__(self):
        self.boards = {board: [rospy.resolve_name(n) for n in nodes]
                       for board, nodes in param('boards', boards_param, required=True).items()}
        self.first = param('primary', lambda n, v: config.one_of(n, v, self.boards), required=True)
        self.timeout = param('timeout', config.positive_float, 0.05)
        self.stall_after = param('stall_after', config.positive_float, self.timeout / 5.0)
        self.grace = param('startup_grace', config.non_negative_float, 0.0)
        self.service_timeout = param('service_timeout', config.positive_float, 2.0)
        self.niceness = param('niceness', config.niceness, -5)
        self.lock = threading.Lock()
        self.host = this_host()
        self.watch = None            # BoardWatch, from set-up on
        self.proxies = {}            # board -> {node: persistent SetRole proxy}
        self.diagnostics = None
        self.term = 0
        self.announce_lock = threading.Lock()
        # START:PID:ID: consumers follow a later run, never an earlier one (aft_ftm.primary_word)
        self.incarnation = '%.6f:%d:%s' % (time.time(), os.getpid(), uuid.uuid4().hex[:12])
        specs = [PortSpec('events', PUBLISH, 'std_msgs/String'), PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm'),
                 PortSpec('primary', PUBLISH, 'aft_msgs/PrimaryBoard')]
        callbacks = {}
        for board in self.boards:
            specs += [PortSpec('heartbeat/' + board, SUBSCRIBE, 'aft_msgs/Heartbeat'),
                      PortSpec('acks/' + board, SUBSCRIBE, 'aft_msgs/CheckpointAck')]
            callbacks['heartbeat/' + board] = lambda beat, board=board: self._on_heartbeat(board, beat)
            callbacks['acks/' + board] = lambda ack, board=board: self._on_ack(board, ack)
        self.ports = Ports(specs, callbacks, queue_size=10)

    def setup(self, timeout):
        try:
            os.setpriority(os.PRIO_PROCESS, 0, self.niceness)
        except OSError as e:
            rospy.logwarn('%s: cannot set niceness %d (%s)', rospy.get_name(), self.niceness, e)
        for board in self.boards:
            if board != self.first:
                proxies, error = self._open(self.boards[board], timeout)
                if error:
                    rospy.logerr('%s: board %s: %s', rospy.get_name(), board, error)
                    return False
                self.proxies[board] = proxies
        with self.lock:
            self.watch = BoardWatch(self.boards, self.first, self.timeout, time.monotonic(), self.grace,
                                    connected=set(self.proxies), stall_after=self.stall_after)
        for name in sorted(self.ports.specs):
            self.ports.bind(name, latch=name == 'primary')
        self._announce(self.first)
        self.ports.advertise_service()
        self.diagnostics = Diagnostics(self._health)
        threading.Thread(target=self._loop, name='watchdog', daemon=True).start()
        return True

    def _health(self):
        with self.lock:
            watch = self.watch
            report = health.watchdog(watch.primary, watch.backup, sum(b.failures for b in watch.boards.values()),
                                     watch.describe())
        return health.with_suspension(report, self.ports.gate.state.name, self.ports.gate.held)

    def _open(self, nodes, timeout):
        """Persistent SetRole connections to nodes, each opened with a call that changes nothing (a
        backup stays a backup): a failover must not need the ROS master, which may be gone by then.
        Returns (proxies, error)."""
        proxies = {}
        for node in nodes:
            try:
                rospy.wait_for_service(node + '/set_role', timeout)
            except rospy.ROSException:
                self._close(proxies)
                return {}, '%s/set_role is not available' % node
            proxies[node] = rospy.ServiceProxy(node + '/set_role', SetRole, persistent=True)
            answer, error = self._call(proxies[node], timeout, role=Role.BACKUP.value, last_seq=0)
            if error or not answer.success:
                self._close(proxies)
                return {}, ('%s/set_role does not answer: %s' % (node, error) if error else
                            '%s is not a backup: %s' % (node, answer.message))
        return proxies, ''

    @staticmethod
    def _close(proxies):
        for proxy in proxies.values():
            try:
                proxy.close()
            except Exception:   # a dead board's connection: closing it must never fail the caller
                pass

    # -- inputs ----------------------------------------------------------------------------------
    def _on_heartbeat(self, board, beat):
        if beat.site != board:
            rospy.logwarn_throttle(10.0, '%s: a heartbeat of site %s on the topic of board %s: ignored'
                                   % (rospy.get_name(), beat.site, board))
            return
        with self.lock:
            actions = self.watch.beat(board, time.monotonic(), beat.host, beat.pid, beat)
        self._carry_out(actions)

    def _on_ack(self, board, ack):
        with self.lock:
            actions = self.watch.ack(board, ack.ok, ack.to, time.monotonic())
        self._carry_out(actions)

    def _loop(self):
        tick = self.timeout / 10.0
        while not rospy.is_shutdown():
            with self.lock:
                actions = self.watch.check(time.monotonic())
            self._carry_out(actions)
            time.sleep(tick)

    # -- actions ---------------------------------------------------------------------------------
    def _carry_out(self, actions):
        for action in actions:
            if isinstance(action, Failover):
                self._failover(action)
            elif isinstance(action, Connect):
                threading.Thread(target=self._connect, args=(action,), daemon=True).start()
            elif isinstance(action, Report):
                self._report(action)

    def _report(self, report):
        if report.alarm:
            rospy.logwarn('%s: pbr %s: %s', rospy.get_name(), report.kind, report.detail)
            self.ports.publish('alarms', Alarm(source=rospy.get_name(), mechanism='pbr', kind=report.kind,
                                               detail=report.detail, stamp=rospy.Time.now()))
        else:
            rospy.loginfo('%s: %s', rospy.get_name(), report.detail)
        if report.record is not None:
            self._publish(dict(report.record))

    def _announce(self, board):
        """Say that board is the primary, in a new term."""
        with self.announce_lock:   # the terms go out in their order
            self.term += 1
            self.ports.publish('primary', PrimaryBoard(stamp=rospy.Time.now(), board=board, nodes=self.boards[board],
                                                       term=self.term, incarnation=self.incarnation))

    def _publish(self, record):
        record['t'] = rospy.get_time()
        self.ports.publish('events', String(data=json.dumps(record)))

    def _power_off(self, board, verdict, on_stopped):
        """Enforce the fail-silence of a failed board: on_stopped() runs once every process of it is
        stopped (it can send nothing more) and sent SIGKILL (nobody's SIGCONT can start it again), before
        their tear-down is waited for. Returns the number of processes."""
        self._close(self.proxies.pop(board, {}))
        info = verdict.last_info
        if info is not None and info.host == self.host and info.pid > 0:
            # The pid a heartbeat named is checked as Recovery checks it (fencing.named_launcher): alive
            # since the board was last heard, no ancestor of this watchdog, a launcher of the board's
            # nodes. Its tree was killed whatever it was: a forged beat naming pid 1 made the watchdog
            # kill itself, and a reused pid an unrelated tree (review of session 36).
            _, pids, why, refused, _ = named_launcher(info.pid, board, '/' + board, '/%s/' % board, verdict.silence)
            if pids:
                return power_off_trees(pids, on_stopped=on_stopped)
            on_stopped()   # the take-over first: the alarm below may take a while (a master gone)
            if psutil.pid_exists(info.pid):   # (gone: the board is down, nothing to say)
                self._report(Report('fence_refused' if refused else 'fail_silence_unenforced',
                                    'board %s failed: %s; the take-over goes on, relying on the board being really '
                                    'down' % (board, why), True, None))
            return 0
        on_stopped()   # the take-over first: the alarm below may take a while (a master gone)
        # Another host's board (or one never heard): this watchdog cannot stop it. Said, not silent:
        # if it still runs, its beats say so later (fail_silence_broken).
        self._report(Report('fail_silence_unenforced', 'board %s failed on %s: this watchdog (on %s) cannot power it '
                            'off; the take-over goes on, relying on the board being really down'
                            % (board, info.host if info is not None else 'an unknown host', self.host), True, None))
        return 0

    def _connect(self, action):
        proxies, error = self._open(action.nodes, self.service_timeout)
        with self.lock:
            if not error:
                self._close(self.proxies.get(action.board, {}))
                self.proxies[action.board] = proxies
            actions = self.watch.connected(action.board, error, time.monotonic())
        self._carry_out(actions)

    PROMOTE_TRIES = 3   # periods of ~service_timeout a backup's node is waited for on its SetRole ALONE

    @staticmethod
    def _call(proxy, timeout, periods=None, **request):
        """A service call limited to timeout seconds (rospy's calls have no limit of their own).
        Returns (answer, error); with ``periods``, waits up to that many timeouts for the same call and
        returns (answer, error, the periods waited past the first)."""
        result = {}

        def call():
            try:
                result['answer'] = proxy(**request)
            except Exception as e:   # any failure of the call is a failed promotion, reported
                result['error'] = str(e) or type(e).__name__
        thread = threading.Thread(target=call, daemon=True)
        thread.start()
        waited = 0
        thread.join(timeout)
        while thread.is_alive() and periods is not None and waited < periods - 1:
            waited += 1
            thread.join(timeout)
        if thread.is_alive():
            answer, error = None, 'no answer within %.1f s' % (timeout * (waited + 1))
        else:
            answer, error = result.get('answer'), result.get('error')
        return (answer, error) if periods is None else (answer, error, waited)

    def _failover(self, failover):
        started = time.monotonic()   # nothing is logged before the switch: with the master gone, logging is slow
        verdict = failover.verdict
        promoted, problems, switched, retried = [], [], [], [0]

        def promote():
            # The failed board is stopped and sent SIGKILL (it can publish nothing more, whoever resumes
            # it): the backup may take over now, while the kernel tears the processes down.
            proxies = self.proxies.get(failover.to, {})
            for node in failover.nodes:
                if node not in proxies:
                    problems.append('%s: no connection open to it' % node)
                    break
                # A node that does not answer within service_timeout (stalled: a load peak, a pause) is
                # waited for longer, on the same call (PROMOTE_TRIES periods in all): ALONE taken late is
                # still taken. A second call through the master failed at once with the master gone, the
                # case the persistent connections are for (review of session 52). Given up, the word is
                # never said and a node that took its role later drives nobody.
                answer, error, waited = self._call(proxies[node], self.service_timeout, periods=self.PROMOTE_TRIES,
                                                   role=Role.ALONE.value, last_seq=0)
                retried[0] += waited
                if error:
                    problems.append('%s: %s' % (node, error))
                    break
                if not answer.success:
                    problems.append('%s refused: %s' % (node, answer.message))
                    break
                promoted.append(node)
            if not problems:
                # Said once every node took its role, never before: a promotion that failed must not depose
                # a board that was only stalled and that nobody could power off (it drives on). The new
                # primary's first output may come before the word: its consumers hold it a moment.
                self._announce(failover.to)
            switched.append(time.monotonic() - started)
        killed = self._power_off(failover.board, verdict, promote)
        switch = switched[0]
        with self.lock:
            self.watch.promoted(failover.to, problems, time.monotonic())
        self._publish({'kind': 'failover', 'board': failover.board, 'to': failover.to, 'reason': verdict.reason,
                       'silence': verdict.silence, 'switch': switch, 'killed': killed, 'promoted': promoted,
                       'term': self.term, 'retried': retried[0],
                       'ok': not problems, 'problems': problems})
        if problems:
            self._report(Report('failover_failed', 'board %s failed (%s) and nobody took over: %s'
                                % (failover.board, verdict.reason, '; '.join(problems)), True, None))
        else:
            rospy.logwarn('%s: switched to board %s in %.1f ms (silence %.1f ms)', rospy.get_name(), failover.to,
                          switch * 1e3, verdict.silence * 1e3)
            self._report(Report('board_failed', 'board %s failed (%s): powered off, board %s took over in %.1f ms%s and '
                                'goes on without a backup until a board re-joins'
                                % (failover.board, verdict.reason, failover.to, switch * 1e3,
                                   ' (waited %d more periods: it did not answer within %.1f s)'
                                   % (retried[0], self.service_timeout) if retried[0] else ''), True, None))
