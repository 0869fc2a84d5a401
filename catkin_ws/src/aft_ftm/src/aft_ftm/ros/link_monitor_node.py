"""The link monitor: measures the bandwidth to the peer site and hands it to the monitor (R)."""
import os
import threading

import rosgraph.network
import rospy
from std_msgs.msg import Float64

from .. import config, health
from ..link_probe import Estimator, ProbeError, Sink, check_endpoint, probe, rate
from .diagnostics import Diagnostics
from .params import param


class LinkMonitorNode(object):
    """Answers its peer's probes (a sink), and probes the peer every ``~period``: a short TCP stream
    whose rate the peer's sink measures (see aft_ftm.link_probe). Publishes the median of the last
    ``~window`` probes on ``bandwidth``, which the launch file remaps to the monitor's
    ``/aft/monitor/bandwidth``: a real drop of the link's capacity (a rate limit, a congested
    network) changes the monitor's R by itself.

    Parameters:
        ~peer (str, required): the peer's link monitor node, e.g. /slave/link_monitor; its sink's
            address is read from its ``~endpoint`` parameter.
        ~site (str, default: this node's name space): this site, for /diagnostics.
        ~period (float, 2 s): time between two probes.
        ~probe_seconds (float, 0.2 s), ~probe_bytes (int, 4 MiB): how long a probe streams, at most.
        ~window (int, 3): probes in the median.
        ~port (int, 0 = any free): the sink's TCP port; it listens on this host's ROS address.
    Publishes:
        bandwidth (std_msgs/Float64, bytes/s).
        ~endpoint (parameter, host:port): where the sink listens, for the peer.
        /diagnostics: the figure reported, and probes that fail (WARN).
    """

    def __init__(self):
        self.peer = rospy.resolve_name(param('peer', config.non_empty_str, required=True))
        self.site = param('site', config.non_empty_str, rospy.get_namespace().strip('/') or 'root')
        self.period = param('period', config.positive_float, 2.0)
        self.seconds = param('probe_seconds', config.positive_float, 0.2)
        self.max_bytes = param('probe_bytes', config.positive_int, 4 << 20)
        self.estimator = Estimator(param('window', config.positive_int, 3))
        self.port = param('port', config.non_negative_int, 0)
        self.lock = threading.Lock()
        self.last = None
        self.why = None

    def setup(self, timeout):
        address = rosgraph.network.get_host_name()
        self.sink = Sink('0.0.0.0', self.port).start()
        rospy.set_param('~endpoint', '%s:%d' % (address, self.sink.endpoint[1]))
        rospy.on_shutdown(self.sink.close)
        self.publisher = rospy.Publisher('bandwidth', Float64, queue_size=1)
        self.diagnostics = Diagnostics(self._health, self.site)
        threading.Thread(target=self._probe_loop, name='probe', daemon=True).start()
        return True

    def _health(self):
        with self.lock:
            return health.link_monitor(self.site, self.peer, self.estimator.estimate(), self.last,
                                       self.estimator.failures, self.why)

    def _peer_endpoint(self):
        name = self.peer + '/endpoint'
        if not rospy.has_param(name):
            raise ProbeError('%s has not said where its sink listens (no parameter %s)' % (self.peer, name))
        return check_endpoint(name, rospy.get_param(name))

    def _probe_loop(self):
        endpoint = None
        source = os.environ.get('ROS_IP') or None
        while not rospy.is_shutdown():
            try:
                if endpoint is None:
                    endpoint = self._peer_endpoint()
                measured = rate(*probe(endpoint, self.seconds, self.max_bytes, source=source))
                why = None if measured else 'the probe was too short to measure'
            except Exception as e:   # the peer down, partitioned, not started: reported, tried again
                measured, why, endpoint = None, str(e), None
            with self.lock:
                self.estimator.add(measured)
                self.last, self.why = measured, why
                estimate = self.estimator.estimate() if measured else None
            if estimate is not None:
                self.publisher.publish(Float64(data=estimate))
            elif why:
                rospy.logwarn_throttle(10, '%s: no bandwidth measured: %s' % (rospy.get_name(), why))
            rospy.sleep(self.period)
