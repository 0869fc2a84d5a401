"""The ``servicectl`` command: start, stop, restart a supervised service, show their status, clear
the safe state. Exit status: 0 done, 1 refused (the message says why), 2 the manager cannot be reached."""
import argparse
import json
import sys

import rospy
from aft_msgs.srv import ServiceCommand
from std_srvs.srv import Trigger


def main(argv):
    parser = argparse.ArgumentParser(prog='servicectl', description=__doc__.split('\n')[0])
    parser.add_argument('--manager', default='/service_manager', help='the manager node (default /service_manager)')
    parser.add_argument('--timeout', type=float, default=5.0, help='how long to wait for the manager (s)')
    parser.add_argument('verb', choices=('status', 'start', 'stop', 'restart', 'clear'))
    parser.add_argument('name', nargs='?', default='', help='the service (all of them, for status)')
    options = parser.parse_args(argv)
    if options.verb in ('start', 'stop', 'restart') and not options.name:
        parser.error('%s needs the name of a service' % options.verb)
    name = options.manager.rstrip('/') + '/' + ('clear_safe_state' if options.verb == 'clear' else options.verb)
    try:
        rospy.wait_for_service(name, options.timeout)
        if options.verb == 'clear':
            answer = rospy.ServiceProxy(name, Trigger)()
        else:
            answer = rospy.ServiceProxy(name, ServiceCommand)(name=options.name)
    except (rospy.ROSException, rospy.ServiceException) as e:
        print('servicectl: cannot reach %s: %s' % (name, e), file=sys.stderr)
        return 2
    if options.verb == 'status' and answer.success:
        status = json.loads(answer.status)
        print('safe state: %s' % (status['safe_state'] or 'no'))
        for service, s in status['services'].items():
            errors = ', '.join('%s %d' % kv for kv in sorted(s['errors'].items())) or 'none'
            print('%-20s %-10s pid %-7s starts %-3d errors: %s  (%s)' % (service, s['state'], s['pid'] or '-',
                                                                          s['starts'], errors, s['reason']))
        return 0
    print(answer.message)
    return 0 if answer.success else 1
