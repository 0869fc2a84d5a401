"""Fail-stop of a site from outside it: ``python -m aft_ftm.ros.fail_site --site S --reason TEXT``.

What a site's own node does when it cannot serve correctly (:mod:`aft_ftm.ros.fail_stop`), for a
process that is no node of the site: the guard of an adaptation's replacement nodes
(:mod:`aft_ftm.ros.guarded_launch`), when a required replacement died. It publishes an
aft_msgs/Failure naming the site on ``/S/fail_stop``, which the site's crash detector hears: its
heartbeats stop for good, its peer fences it and takes over within a detection time. A site that
loses its After this way must not go on heartbeating with requests going nowhere.

The message is not latched, so a site that comes back later (a new crash detector) never hears
it: it is sent only once a subscriber is connected, within ``--timeout`` seconds. Either way an
alarm says what happened on /aft/alarms. Exit status 0 if a subscriber was there to hear it, 1 if
none was (the site is down already, or it has no crash detector: the alarm says so).
"""
import argparse
import os
import sys
import time

ALARM_KIND = 'fail_stop'


def fail_site(site, reason, timeout=3.0):
    """Publish the fail-stop of site (a node must be initialised). Returns how many subscribers
    of /site/fail_stop it reached (0: nobody heard it)."""
    import rosgraph
    import rospy
    from aft_msgs.msg import Alarm, Failure
    alarms = rospy.Publisher('/aft/alarms', Alarm, queue_size=10)
    stop = rospy.Publisher('/%s/fail_stop' % site, Failure, queue_size=10, tcp_nodelay=True)
    deadline = time.monotonic() + timeout

    def wait_for(publisher, wanted=lambda: 1):   # until it has the subscribers wanted, or the deadline
        while time.monotonic() < deadline and not rospy.is_shutdown() and publisher.get_num_connections() < wanted():
            time.sleep(0.01)

    asked = {'at': -1.0, 'count': 1}

    def registered():
        # Every subscriber the master knows of (the crash detector, and the site's Recovery, which
        # follows its site's fail-stop too): sent once the first connects, the other could miss it.
        if time.monotonic() - asked['at'] >= 0.2:
            asked['at'] = time.monotonic()
            try:
                subscribers = dict(rosgraph.Master(rospy.get_name()).getSystemState()[1])
                asked['count'] = max(1, len(subscribers.get('/%s/fail_stop' % site, ())))
            except Exception:   # the master cannot be asked: at least one subscriber, as before
                asked['count'] = 1
        return asked['count']
    wait_for(stop, registered)   # the stop first: no wait for alarm listeners delays it
    heard = stop.get_num_connections()
    if heard:
        stop.publish(Failure(site=site, reason=reason, detected=rospy.Time.now()))
        detail = 'site %s told to stop (%d subscriber(s) of /%s/fail_stop): %s' % (site, heard, site, reason)
    else:
        detail = ('site %s could not be told to stop: nothing subscribes to /%s/fail_stop within %.1f s (the site '
                  'is down, or has no crash detector): %s' % (site, site, timeout, reason))
    rospy.logerr('%s: %s', rospy.get_name(), detail)
    wait_for(alarms)
    alarms.publish(Alarm(source=rospy.get_name(), mechanism='adaptation', kind=ALARM_KIND, detail=detail,
                         stamp=rospy.Time.now()))
    time.sleep(0.2)   # rospy writes from a queue thread: let both messages leave before the exit
    return heard


def main(argv=None):
    parser = argparse.ArgumentParser(prog='fail_site', description=__doc__.split('\n\n')[0])
    parser.add_argument('--site', required=True, help='the site that must stop (its /SITE/fail_stop topic)')
    parser.add_argument('--reason', required=True, help='why, for the alarm and the site\'s log')
    parser.add_argument('--timeout', type=float, default=3.0, help='seconds to wait for a subscriber (3)')
    options = parser.parse_args(argv)
    if not options.site.strip('/') or '/' in options.site.strip('/'):
        parser.error('--site must be a site name such as master, got %r' % options.site)
    # Under TLS as the party of the site it stops (the guard runs with its nodes' environment), whose
    # policy names it /fail_site_SITE_*: outside /SITE/, whose nodes the peer's fence stops at once,
    # before this node's alarm would be out (review of session 43). Always that name: the namespace
    # roslaunch gave the process that started the guard (the Monitoring Engine's /aft, a retired
    # node's /SITE) is not this node's. Before rospy is imported: it reads its namespace then.
    os.environ.pop('ROS_NAMESPACE', None)
    import rospy
    from aft_ftm.ros.params import secure_from_environment
    secure_from_environment()   # mutual TLS where AFT_TLS_DIR says so (issue 16)
    rospy.init_node('fail_site_%s' % options.site.strip('/'), anonymous=True, disable_signals=True)
    return 0 if fail_site(options.site.strip('/'), options.reason, options.timeout) else 1


if __name__ == '__main__':
    sys.exit(main())
