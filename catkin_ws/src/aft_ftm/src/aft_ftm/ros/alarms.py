"""Publishing aft_msgs/Alarm from a node's ``alarms`` port."""
import rospy
from aft_msgs.msg import Alarm


def alarm(ports, mechanism, kind, detail, request=None):
    """Publish an alarm on the node's ``alarms`` port and log it (details never carry keys)."""
    rospy.logwarn('%s: %s %s: %s', rospy.get_name(), mechanism, kind, detail)
    ports.publish('alarms', Alarm(source=rospy.get_name(), mechanism=mechanism, kind=kind, detail=detail,
                                  request_id=request.id if request is not None else 0,
                                  origin=request.origin if request is not None else '',
                                  stamp=rospy.Time.now()))
