"""Publishing aft_msgs/Alarm from a node's ``alarms`` port.

An alarm's detail can carry what a request or a reply held (an assertion's message names the
values it refused, a vote the results that differ). Under mutual TLS it goes on ``/aft/alarms``
(TLS: only the parties the policy lets read it) and into the node's own log file, but not on
``/rosout``, which stays in clear (its node is ROS's own, without TLS): there the alarm is logged
by its mechanism and kind only."""
import logging

import rospy
from aft_msgs.msg import Alarm

# rospy's 'rospy.*' loggers write the node's log file (ROS_HOME/log), never /rosout
LOCAL = logging.getLogger('rospy.aft.alarms')


def alarm(ports, mechanism, kind, detail, request=None):
    """Publish an alarm on the node's ``alarms`` port and log it (details never carry keys)."""
    log_alarm(mechanism, kind, detail)
    ports.publish('alarms', Alarm(source=rospy.get_name(), mechanism=mechanism, kind=kind, detail=detail,
                                  request_id=request.id if request is not None else 0,
                                  origin=request.origin if request is not None else '',
                                  stamp=rospy.Time.now()))


def log_alarm(mechanism, kind, detail, tls=None):
    """Log an alarm: on /rosout with its detail in clear, or, under TLS (``tls`` None: whether this
    process installed it), on /rosout by kind only and with its detail in the node's own log file."""
    if tls is None:
        from .tls_transport import installed
        tls = installed()
    if not tls:
        rospy.logwarn('%s: %s %s: %s', rospy.get_name(), mechanism, kind, detail)
        return
    rospy.logwarn('%s: %s %s (its detail on /aft/alarms and in this node\'s log file: /rosout is in clear)',
                  rospy.get_name(), mechanism, kind)
    LOCAL.warning('%s: %s %s: %s', rospy.get_name(), mechanism, kind, detail)
