"""Rebindable ports: the dynamic binding service every FTM node offers (paper Fig. 7)."""
import threading
import warnings

import rosgraph
import rospy
from aft_msgs.srv import Rebind, RebindResponse
import roslib.message

from .. import ports as rules
from ..errors import RebindError


class Ports(object):
    """The publishers and subscribers of a node, each bound to a topic or unbound.

    Publishers and subscribers use tcp_nodelay. ``listeners`` maps publish ports to a
    rospy.SubscribeListener. A rebind is validated fully before anything changes.

    By default (``queue_size=None``) nothing is ever dropped by a queue: publishers write
    synchronously to their connections (a rospy publisher queue drops its oldest message when
    full) and subscriber queues are unbounded. It also saves a thread hand-off per hop.
    """

    def __init__(self, specs, callbacks, queue_size=None, listeners=None):
        self.specs = {s.name: s for s in specs}
        self._callbacks = callbacks
        self._listeners = listeners or {}
        self._default_queue = queue_size
        self._handles = {}
        self._topics = {}
        self._lock = threading.RLock()
        self.unbound_publishes = 0

    def bind(self, name, topic=None, queue_size=0):
        """Bind port name to topic (default: the port's own name, so it can be remapped)."""
        spec = self.specs[name]
        resolved = rospy.resolve_name(topic if topic else name)
        cls = roslib.message.get_message_class(spec.msg_type)
        qs = queue_size or self._default_queue
        with self._lock:
            if self._topics.get(name) == resolved:
                return 'port %s already bound to %s' % (name, resolved)
            self._unbind_locked(name)
            if spec.direction == rules.PUBLISH:
                with warnings.catch_warnings():   # rospy warns about queue_size=None: it is chosen
                    warnings.simplefilter('ignore')
                    handle = rospy.Publisher(resolved, cls, queue_size=qs, tcp_nodelay=True,
                                             subscriber_listener=self._listeners.get(name))
            else:
                handle = rospy.Subscriber(resolved, cls, self._callbacks[name], queue_size=qs,
                                          tcp_nodelay=True)
            self._handles[name] = handle
            self._topics[name] = resolved
        return 'port %s bound to %s' % (name, resolved)

    def unbind(self, name):
        with self._lock:
            return self._unbind_locked(name)

    def _unbind_locked(self, name):
        handle = self._handles.pop(name, None)
        topic = self._topics.pop(name, None)
        if handle is not None:
            handle.unregister()
            return 'port %s unbound from %s' % (name, topic)
        return 'port %s was not bound' % name

    def topic(self, name):
        return self._topics.get(name)

    def publisher(self, name):
        return self._handles.get(name)

    def publish(self, name, msg):
        """Publish on a port; returns False (and counts it) if the port is unbound."""
        handle = self._handles.get(name)
        if handle is None:
            self.unbound_publishes += 1
            rospy.logerr('cannot publish on port %s: it is not bound to any topic', name)
            return False
        handle.publish(msg)
        return True

    def connections(self, name):
        handle = self._handles.get(name)
        return handle.get_num_connections() if handle is not None else 0

    def rebind(self, port, topic, direction, activate, queue_size=0):
        """Validate then apply a rebind; raises RebindError with nothing changed."""
        resolved = rospy.resolve_name(topic) if topic else ''
        try:
            types = dict(rosgraph.Master(rospy.get_name()).getTopicTypes())
        except Exception as e:   # the master cannot be asked: refuse rather than guess
            raise RebindError('cannot check topic types with the ROS master: %s' % e)
        rules.check_rebind(self.specs, port, direction, resolved, types, activate)
        if activate:
            return self.bind(port, resolved, queue_size)
        return self.unbind(port)

    def advertise_service(self):
        """Offer ~rebind (aft_msgs/Rebind)."""
        return rospy.Service('~rebind', Rebind, self._handle_rebind)

    def _handle_rebind(self, req):
        try:
            message = self.rebind(req.port, req.topic, req.direction, req.activate, req.queue_size)
        except RebindError as e:
            rospy.logerr('rebind refused: %s', e)
            return RebindResponse(success=False, message=str(e))
        rospy.loginfo('rebind: %s', message)
        return RebindResponse(success=True, message=message)

    def shutdown(self):
        with self._lock:
            for name in list(self._handles):
                self._unbind_locked(name)


def wait_for_connections(ports, names, timeout):
    """Wait until every named port has at least one connection. Returns the names still missing."""
    deadline = rospy.get_time() + timeout
    missing = list(names)
    rate = 0.01
    while not rospy.is_shutdown():
        missing = [n for n in names if ports.connections(n) < 1]
        if not missing or rospy.get_time() >= deadline:
            return missing
        rospy.sleep(rate)
    return missing
