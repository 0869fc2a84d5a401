"""Fail-stop of a replica: the site falls silent so that its peer fences it and takes over.

A replica that can no longer serve correctly (its server hangs or died, its state cannot be
captured, the witness deposed it) must neither answer nor go on heartbeating: a site that
heartbeats is alive for its peer, which then never takes over. Any node of the site publishes an
aft_msgs/Failure naming its own site on ``fail_stop`` (the site's crash detector subscribes and
stops its heartbeats for good), raises an alarm, and answers nothing more for the request at hand.
"""
import rospy
from aft_msgs.msg import Failure

from .alarms import alarm


def fail_stop(ports, site, reason, mechanism='pbr'):
    """Publish the fail-stop on the ``fail_stop`` port and an alarm on ``alarms`` (both must exist)."""
    rospy.logerr('%s: FAIL-STOP of site %s: %s', rospy.get_name(), site, reason)
    ports.publish('fail_stop', Failure(site=site, reason=reason, detected=rospy.Time.now()))
    alarm(ports, mechanism, 'fail_stop', 'site %s stops serving: %s' % (site, reason))
