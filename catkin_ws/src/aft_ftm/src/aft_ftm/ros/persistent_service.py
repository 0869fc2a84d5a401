"""Service calls that need no ROS master once set up.

A rospy ServiceProxy asks the master for the service's address (``lookupService``) every time it
opens a connection, and a persistent one opens its connection at its first call. A failover makes
first calls (a backup's Proceed calls its server for the first time, a promoted After its state
manager): with the master dead those calls fail. :class:`PersistentService` opens its connection
at set-up (:meth:`PersistentService.connect`) and remembers the address the master gave, so that a
reconnection (the connection broke) also works while the master cannot be reached, as long as the
service still runs where it did.
"""
import socket

import rosgraph
import rospy
from rospy.exceptions import TransportInitError
from rospy.impl.tcpros_base import TCPROSTransport


class PersistentService(rospy.ServiceProxy):
    """A persistent rospy.ServiceProxy that can connect without the master.

    ``connect()`` opens the connection now (the master is asked, once). Later connections ask the
    master too, and use the last address it gave when it cannot be reached (``master_misses`` counts
    them). Calls raise what rospy.ServiceProxy raises.
    """

    def __init__(self, name, service_class):
        super(PersistentService, self).__init__(name, service_class, persistent=True)
        self.master_misses = 0

    @property
    def connected(self):
        return self.transport is not None

    def call(self, *args, **kwds):
        """rospy.ServiceProxy.call; a connection that failed (anything but the service's own error
        answer) is closed, so that the next call opens a new one."""
        try:
            return super(PersistentService, self).call(*args, **kwds)
        except (rospy.ServiceException, rospy.ROSException) as e:
            if 'responded with an error' not in str(e):
                self.reset()
            raise

    def reset(self):
        """Close the connection (if open); the next call opens a new one."""
        transport, self.transport = self.transport, None
        if transport is not None:
            transport.close()

    def fresh(self):
        """A new PersistentService to the same service that knows its last address (to leave this one
        to a call that may never return)."""
        other = PersistentService(self.resolved_name, self.service_class)
        other.uri = self.uri
        return other

    def connect(self):
        """Open the persistent connection if it is not open; raises rospy.ServiceException."""
        if self.transport is not None:
            return
        uri = self._get_service_uri(None)
        host, port = rospy.core.parse_rosrpc_uri(uri)
        transport = TCPROSTransport(self.protocol, self.resolved_name)
        transport.buff_size = self.buff_size
        try:
            transport.connect(host, port, uri)
        except TransportInitError as e:
            raise rospy.ServiceException('unable to connect to service %s: %s' % (self.resolved_name, e))
        self.transport = transport

    def _get_service_uri(self, request):
        """The service's address from the master; the last one it gave if it cannot be reached."""
        try:
            uri = rosgraph.Master(rospy.get_name()).lookupService(self.resolved_name)
        except (socket.error, OSError) as e:   # the master is unreachable
            if self.uri is None:
                raise rospy.ServiceException('service %s: the master cannot be reached to find it (%s)'
                                             % (self.resolved_name, e))
            self.master_misses += 1
            return self.uri
        except rosgraph.MasterError as e:
            raise rospy.ServiceException('service %s unavailable: %s' % (self.resolved_name, e))
        self.uri = uri
        return uri


def open_service(name, service_class, timeout):
    """Wait for the service (asks the master), then open a PersistentService to it. Raises
    rospy.ROSException (not available within timeout) or rospy.ServiceException."""
    rospy.wait_for_service(name, timeout)
    proxy = PersistentService(name, service_class)
    proxy.connect()
    return proxy
