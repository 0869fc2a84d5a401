"""Fakes shared by the tests that need no ROS master: messages and a clock."""
import types


def request(origin='/proxy', rid=1, oldest_pending=0, client='/client'):
    """A stand-in for aft_msgs/Request in tests that need no ROS."""
    return types.SimpleNamespace(origin=origin, id=rid, oldest_pending=oldest_pending, client=client)


def reply(origin='/proxy', rid=1, value=None, oldest_pending=0):
    """A stand-in for aft_msgs/Reply."""
    return types.SimpleNamespace(origin=origin, id=rid, value=value, oldest_pending=oldest_pending)


class FakeClock(object):
    def __init__(self, now=0.0):
        self.now = now

    def advance(self, dt):
        self.now += dt
        return self.now


class FakePublisher(object):
    """A rospy.Publisher that keeps what it is given."""

    def __init__(self):
        self.published = []

    def publish(self, msg):
        self.published.append(msg)


class FakePorts(object):
    """A node's ports (aft_ftm.ports) without ROS: what it published, in order. Built with a node's
    specs and callbacks (it stands for ``aft_ftm.ros.ports.Ports`` then), ``deliver`` hands an input
    to the node as a subscriber's thread would."""

    def __init__(self, specs=(), callbacks=None):
        self.sent = []
        self.specs = {s.name: s for s in specs}
        self.callbacks = callbacks or {}

    def suspension(self, hold, quiescent=None, before_suspend=None, resumed=None):
        pass

    def deliver(self, port, msg):
        self.callbacks[port](msg)

    def publish(self, port, msg):
        self.sent.append((port, msg))

    def kinds(self):
        """(port, alarm kind or None) of each message published."""
        return [(port, getattr(msg, 'kind', None)) for port, msg in self.sent]

    def alarms(self):
        """The kinds of the alarms published."""
        return [msg.kind for port, msg in self.sent if port == 'alarms']
