"""The watchdog of a replicated pub/sub node (the second paper's Arduino, section III.D): it
watches the primary board's heartbeats and, when they stop, switches to the backup."""
import json
import os
import threading
import time

import rospy
from aft_msgs.srv import SetRole
from std_msgs.msg import String

from .. import config
from ..detector import HeartbeatMonitor
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import Role
from ..sites import power_off, this_host
from .params import param
from .ports import Ports


class WatchdogNode(object):
    """Declares the watched board failed after ``~timeout`` of silence, then:

    1. enforces its fail-silence: a board that only stalled must not come back as a second primary,
       so the process tree of its launcher is killed (if it runs on this host);
    2. promotes the backup: SetRole ALONE on each node of ``~promote``, in order, over connections
       opened at set-up (a failover does not need the ROS master);
    3. publishes the failover, with the detection time (the silence) and the switch time.

    It acts once: after a failover the remaining board runs alone.

    Parameters:
        ~watched (str, required): the watched board's site name (as in its heartbeats)
        ~promote (list of node names, required): the backup's nodes to promote, in order
        ~timeout (float, 0.05 s): the silence that declares the board failed
        ~startup_grace (float, 0 = never): declare a board never heard failed after this long
        ~service_timeout (float, 2 s): limit on each promotion call
        ~niceness (int, -5): a watchdog must not be starved by the load it watches
    Subscribes:
        heartbeat (aft_msgs/Heartbeat), port ``heartbeat``: the watched board's crash detector
    Publishes:
        events (std_msgs/String), port ``events``: one JSON record per failover
    Services:
        ~rebind (aft_msgs/Rebind), ~suspend/~resume (aft_msgs/Suspend)
    """

    def __init__(self):
        self.watched = param('watched', config.non_empty_str, required=True)
        promote = param('promote', lambda n, v: v, required=True)
        if not isinstance(promote, list) or not promote or not all(isinstance(x, str) and x for x in promote):
            raise config.ConfigError('parameter %s must be a non-empty list of node names, got %r'
                                     % (rospy.resolve_name('~promote'), promote))
        self.promote = [rospy.resolve_name(n) for n in promote]
        self.timeout = param('timeout', config.positive_float, 0.05)
        grace = param('startup_grace', lambda n, v: 0.0 if v == 0 else config.positive_float(n, v), 0.0)
        self.service_timeout = param('service_timeout', config.positive_float, 2.0)
        self.niceness = param('niceness', config.niceness, -5)
        self.monitor = HeartbeatMonitor(self.timeout, grace, time.monotonic())
        self.lock = threading.Lock()
        self.done = False
        self.host = this_host()
        self.ports = Ports([PortSpec('heartbeat', SUBSCRIBE, 'aft_msgs/Heartbeat'),
                            PortSpec('events', PUBLISH, 'std_msgs/String')],
                           {'heartbeat': self._on_heartbeat}, queue_size=10)
        self.proxies = {}

    def setup(self, timeout):
        try:
            os.setpriority(os.PRIO_PROCESS, 0, self.niceness)
        except OSError as e:
            rospy.logwarn('%s: cannot set niceness %d (%s)', rospy.get_name(), self.niceness, e)
        for name in ('events', 'heartbeat'):
            self.ports.bind(name)
        for node in self.promote:
            try:
                rospy.wait_for_service(node + '/set_role', timeout)
            except rospy.ROSException:
                rospy.logerr('%s: %s/set_role is not available', rospy.get_name(), node)
                return False
            self.proxies[node] = rospy.ServiceProxy(node + '/set_role', SetRole, persistent=True)
            # Open the connection now, with a call that changes nothing (the backup stays a backup):
            # a failover must not need the ROS master, which may be gone by then.
            try:
                answer = self.proxies[node](role=Role.BACKUP.value, last_seq=0)
            except (rospy.ServiceException, rospy.ROSException) as e:
                rospy.logerr('%s: %s/set_role does not answer: %s', rospy.get_name(), node, e)
                return False
            if not answer.success:
                rospy.logerr('%s: %s is not a backup: %s', rospy.get_name(), node, answer.message)
                return False
        self.ports.advertise_service()
        threading.Thread(target=self._loop, name='watchdog', daemon=True).start()
        return True

    def _on_heartbeat(self, beat):
        if beat.site != self.watched:
            return
        with self.lock:
            self.monitor.beat(time.monotonic(), beat)

    def _loop(self):
        tick = self.timeout / 10.0
        while not rospy.is_shutdown() and not self.done:
            with self.lock:
                verdict = self.monitor.check(time.monotonic())
            if verdict is not None:
                self.done = True
                self._failover(verdict)
                return
            time.sleep(tick)

    @staticmethod
    def _call(proxy, timeout, **request):
        """A service call limited to timeout seconds (rospy's calls have no limit of their own).
        Returns (answer, error)."""
        result = {}

        def call():
            try:
                result['answer'] = proxy(**request)
            except Exception as e:   # any failure of the call is a failed promotion, reported
                result['error'] = str(e) or type(e).__name__
        thread = threading.Thread(target=call, daemon=True)
        thread.start()
        thread.join(timeout)
        if thread.is_alive():
            return None, 'no answer within %.1f s' % timeout
        return result.get('answer'), result.get('error')

    def _failover(self, verdict):
        started = time.monotonic()
        info = verdict.last_info
        rospy.logwarn('%s: board %s failed: %s', rospy.get_name(), self.watched, verdict.reason)
        killed = 0
        if info is not None and info.host == self.host and info.pid > 0:
            killed = power_off(info.pid)
        promoted, problems = [], []
        for node in self.promote:
            answer, error = self._call(self.proxies[node], self.service_timeout, role=Role.ALONE.value, last_seq=0)
            if error:
                problems.append('%s: %s' % (node, error))
                break
            if not answer.success:
                problems.append('%s refused: %s' % (node, answer.message))
                break
            promoted.append(node)
        switch = time.monotonic() - started
        record = {'t': rospy.get_time(), 'kind': 'failover', 'board': self.watched, 'reason': verdict.reason,
                  'silence': verdict.silence, 'switch': switch, 'killed': killed, 'promoted': promoted,
                  'ok': not problems, 'problems': problems}
        if problems:
            rospy.logerr('%s: failover incomplete: %s', rospy.get_name(), '; '.join(problems))
        else:
            rospy.logwarn('%s: switched to the backup in %.1f ms (silence %.1f ms)', rospy.get_name(),
                          switch * 1e3, verdict.silence * 1e3)
        self.ports.publish('events', String(data=json.dumps(record)))
