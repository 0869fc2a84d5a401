"""An FTM node's health (aft_ftm.health) on /diagnostics, each second, where rqt_robot_monitor and
``rostopic echo /diagnostics`` look; and reading it back (``rosrun aft_ftm status``)."""
import rospy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from ..health import Level, Report

PREFIX = 'aft_ftm: '   # DiagnosticStatus.name is PREFIX + the node's name


def status_of(name, report, hardware_id=''):
    return DiagnosticStatus(level=int(report.level), name=PREFIX + name, message=report.message,
                            hardware_id=hardware_id, values=[KeyValue(key=k, value=v) for k, v in report.values])


def report_of(status):
    """(node name, Report) of an AFT-ROS DiagnosticStatus, or None for anyone else's."""
    if not status.name.startswith(PREFIX):
        return None
    level = Level(min(int(status.level), Level.ERROR))   # STALE (3) and beyond read as ERROR
    return status.name[len(PREFIX):], Report(level, status.message, [(v.key, v.value) for v in status.values])


class Diagnostics(object):
    """Publishes report() (an aft_ftm.health.Report) for this node every ``period`` seconds."""

    def __init__(self, report, hardware_id='', period=1.0):
        self.report = report
        self.hardware_id = hardware_id
        self.name = rospy.get_name()
        self.publisher = rospy.Publisher('/diagnostics', DiagnosticArray, queue_size=10)
        self.timer = rospy.Timer(rospy.Duration(period), self._tick)

    def _tick(self, _event=None):
        try:
            report = self.report()
        except Exception as e:   # a report that cannot be made is itself a fault to show
            report = Report(Level.ERROR, 'cannot report its health: %s' % e, [])
        array = DiagnosticArray()
        array.header.stamp = rospy.Time.now()
        array.status.append(status_of(self.name, report, self.hardware_id))
        try:
            self.publisher.publish(array)
        except rospy.ROSException:
            pass   # shutting down
