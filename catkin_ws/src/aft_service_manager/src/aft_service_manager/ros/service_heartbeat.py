"""What a supervised service uses: its heartbeat, with its own status (third paper: the heartbeat
signal is combined with the status update), sent every cycle to the service manager.

A service the manager spawned on its host beats through the local channel the manager gave it
(aft_service_manager.channel: a memory write per beat, no message); any other (started by hand, or
on another host) publishes its beats on the ROS topic."""
import os

import rospy
from aft_msgs.msg import ServiceHeartbeat

from aft_service_manager.channel import ServiceEnd

TOPIC = '/aft/service_heartbeat'


class Heartbeat(object):
    """``beat()`` each cycle; ``beat('error', detail)`` reports an internal error (the manager then
    applies the service's failure action). The name is the one the manager gave (AFT_SERVICE).
    ``local`` is the channel's end (None: the ROS topic); ``wait_promoted()`` holds a warm spare
    until the manager promotes it (at once otherwise). Make it in the main thread."""

    def __init__(self, name=None, topic=None):
        self.name = name or os.environ.get('AFT_SERVICE') or rospy.get_name().lstrip('/')
        self.seq = 0
        self.pid = os.getpid()
        self.local = ServiceEnd.from_environment(self.name)
        self.publisher = None if self.local else rospy.Publisher(
            topic or os.environ.get('AFT_HEARTBEAT_TOPIC', TOPIC), ServiceHeartbeat, queue_size=10, tcp_nodelay=True)

    @property
    def spare(self):
        return self.local is not None and self.local.spare

    def wait_promoted(self, timeout=None):
        return True if self.local is None else self.local.wait_promoted(timeout)

    def beat(self, status='ok', detail=''):
        self.seq += 1
        if self.local is not None:
            self.local.beat(status, detail)
            return
        self.publisher.publish(ServiceHeartbeat(name=self.name, pid=self.pid, status=status, detail=detail,
                                                seq=self.seq, stamp=rospy.Time.now()))
