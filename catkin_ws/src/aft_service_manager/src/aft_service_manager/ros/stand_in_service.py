"""A small periodic service standing in for the remote-handling services of the third paper
(TrajectoryGenerator, C4G, ...): it works every period, publishes a counter, sends its heartbeat,
saves its state, and can be made to fail on demand (crash, hang, memory leak, CPU hog, error)."""
import json
import os
import signal
import threading
import time

import rospy
from aft_msgs.srv import InjectFault, InjectFaultResponse
from std_msgs.msg import String, UInt64

from aft_ftm import config
from aft_ftm.state_store import from_environment
from aft_ftm.ros.params import param
from aft_service_manager.ros.service_heartbeat import Heartbeat
from aft_service_manager.trust import default_state_dir

FAULTS = ('crash', 'exit', 'hang', 'leak', 'hog', 'error')


class StandInServiceNode(object):
    """Parameters:
        ~period (float, 0.01 s): the service's cycle (wall clock)
        ~save_every (float, 0.5 s): how often its state (the counter) is saved
        ~counter_limit (int, 10**9): the range check of a restored state
        ~spare_setup (float, 0 s): a warm spare's set-up before it says it is ready (long: hung in it)
    Publishes:
        ~output (std_msgs/UInt64): the counter, each cycle
        ~restored (std_msgs/String, latched): JSON {restored, reason, counter} at start
        /aft/service_heartbeat (aft_msgs/ServiceHeartbeat): each cycle, unless the manager gave it
            its local channel (aft_service_manager.channel)
    A warm spare (AFT_SPARE=1, started by the manager) makes its publishers, says it is ready and
    waits: no output, no state read, until the manager promotes it (SIGUSR1).
    Services:
        ~fault (aft_msgs/InjectFault): mode crash (SIGSEGV), exit (status 3), hang (SIGSTOP of itself),
            leak (magnitude MB more each cycle), hog (a busy thread), error (reported in the heartbeat)
    """

    def __init__(self):
        self.period = param('period', config.positive_float, 0.01)
        self.save_every = param('save_every', config.positive_float, 0.5)
        # a warm spare's set-up time before it says it is ready (long: a spare hung in its set-up)
        self.spare_setup = param('spare_setup', config.non_negative_float, 0.0)
        limit = param('counter_limit', config.non_negative_int, 10 ** 9)
        self.store, self.restore = from_environment(
            os.path.join(default_state_dir(), '%s.json' % rospy.get_name().strip('/').replace('/', '_')),
            lambda state: None if isinstance(state.get('counter'), int) and 0 <= state['counter'] <= limit
            else 'counter %r outside 0 .. %d' % (state.get('counter'), limit))
        self.counter = 0
        self.error = None
        self.leak_mb = 0.0
        self.leaked = []

    def setup(self, timeout):
        # Everything a consumer must have connected to is made first; a warm spare then waits idle
        # (publishing nothing) until the manager promotes it, and only then restores the state.
        self.restored_pub = rospy.Publisher('~restored', String, queue_size=1, latch=True)
        self.output = rospy.Publisher('~output', UInt64, queue_size=10, tcp_nodelay=True)
        self.heartbeat = Heartbeat()
        if self.heartbeat.spare:
            threading.Thread(target=self._promoted, name='spare', daemon=True).start()
        else:
            self._start()
        return True

    def _promoted(self):
        if self.spare_setup:
            rospy.sleep(self.spare_setup)
        while not rospy.is_shutdown() and not self.heartbeat.wait_promoted(0.5):
            pass
        if not rospy.is_shutdown():
            rospy.loginfo('%s: promoted from warm spare', rospy.get_name())
            self._start()

    def _start(self):
        reason = 'restoring not asked for: clean start'
        restored = False
        if self.restore:
            state, why = self.store.load()
            if state is None:
                reason = 'clean start: %s' % why
                rospy.logwarn('%s: %s', rospy.get_name(), reason)
            else:
                self.counter, restored, reason = state['counter'], True, 'restored'
        threading.Thread(target=self._loop, name='cycle', daemon=True).start()
        self.restored_pub.publish(String(data=json.dumps({'restored': restored, 'reason': reason,
                                                          'counter': self.counter})))
        # its service registered once its first cycles are out (the master's XML-RPC takes
        # milliseconds of the interpreter a promoted spare needs for its first output)
        threading.Timer(0.05 if self.heartbeat.spare else 0.0,
                        lambda: rospy.Service('~fault', InjectFault, self._on_fault)).start()

    def _loop(self):
        tick = time.monotonic()
        last_save = 0.0
        while not rospy.is_shutdown():
            self.counter += 1
            if self.leak_mb:
                self.leaked.append(bytearray(int(self.leak_mb * 1e6)))
            try:
                self.output.publish(UInt64(data=self.counter))
            except rospy.ROSException:   # shutting down: its topics are closed
                break
            self.heartbeat.beat('error', self.error) if self.error else self.heartbeat.beat()
            now = time.monotonic()
            if now - last_save >= self.save_every:
                self.store.save({'counter': self.counter})
                last_save = now
            tick = max(tick + self.period, time.monotonic() - self.period)
            time.sleep(max(0.0, tick - time.monotonic()))

    def _on_fault(self, req):
        mode = req.mode
        if mode not in FAULTS:
            return InjectFaultResponse(success=False, message='mode must be one of %s, got %r' % (', '.join(FAULTS), mode))
        rospy.logwarn('%s: fault injected: %s', rospy.get_name(), mode)
        if mode == 'leak':
            self.leak_mb = req.magnitude or 5.0
        elif mode == 'hog':
            threading.Thread(target=self._hog, daemon=True).start()
        elif mode == 'error':
            self.error = 'injected error'
        else:
            # After the answer has gone out.
            threading.Timer(0.05, self._die, args=(mode,)).start()
        return InjectFaultResponse(success=True, message='%s injected' % mode)

    @staticmethod
    def _hog():
        while True:
            pass

    @staticmethod
    def _die(mode):
        if mode == 'crash':
            os.kill(os.getpid(), signal.SIGSEGV)
        elif mode == 'exit':
            os._exit(3)
        else:
            os.kill(os.getpid(), signal.SIGSTOP)
