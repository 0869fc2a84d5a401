"""What a supervised service uses: its heartbeat, with its own status (third paper: the heartbeat
signal is combined with the status update), sent every cycle to the service manager."""
import os

import rospy
from aft_msgs.msg import ServiceHeartbeat

TOPIC = '/aft/service_heartbeat'


class Heartbeat(object):
    """``beat()`` each cycle; ``beat('error', detail)`` reports an internal error (the manager then
    applies the service's failure action). The name is the one the manager gave (AFT_SERVICE)."""

    def __init__(self, name=None, topic=None):
        self.name = name or os.environ.get('AFT_SERVICE') or rospy.get_name().lstrip('/')
        self.seq = 0
        self.pid = os.getpid()
        self.publisher = rospy.Publisher(topic or os.environ.get('AFT_HEARTBEAT_TOPIC', TOPIC), ServiceHeartbeat,
                                         queue_size=10, tcp_nodelay=True)

    def beat(self, status='ok', detail=''):
        self.seq += 1
        self.publisher.publish(ServiceHeartbeat(name=self.name, pid=self.pid, status=status, detail=detail,
                                                seq=self.seq, stamp=rospy.Time.now()))
