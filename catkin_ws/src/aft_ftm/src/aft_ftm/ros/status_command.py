"""rosrun aft_ftm status [--wait S] [--verbose]

Listens to /diagnostics for a few seconds and prints one line per replica site of the running
FTMs: mechanism, role, epoch, health (OK, WARN: degraded, ERROR: cannot serve) and why, as
``servicectl status`` does for services. --verbose adds every node's report.
Exit status: 0 all OK, 1 something degraded or failed, 2 no FTM node heard.
"""
import argparse
import sys
import threading

import rospy
from diagnostic_msgs.msg import DiagnosticArray

from ..health import Level, summary
from .diagnostics import report_of


def main(argv):
    parser = argparse.ArgumentParser(prog='status', description=__doc__.split('\n\n')[1])
    parser.add_argument('--wait', type=float, default=2.5, help='seconds to listen (2.5; nodes report each second)')
    parser.add_argument('--verbose', action='store_true', help="print every node's report too")
    args = parser.parse_args(rospy.myargv(argv))
    reports = {}
    lock = threading.Lock()

    def on_array(array):
        with lock:
            for status in array.status:
                entry = report_of(status)
                if entry is not None:
                    reports[entry[0]] = entry[1]
    from aft_ftm.ros.params import secure_from_environment
    secure_from_environment()   # mutual TLS where AFT_TLS_DIR says so (issue 16)
    rospy.init_node('aft_status', anonymous=True, disable_signals=True)
    rospy.Subscriber('/diagnostics', DiagnosticArray, on_array)
    rospy.sleep(args.wait)
    with lock:
        heard = dict(reports)
    if not heard:
        print('status: no FTM node reported on /diagnostics within %.1f s' % args.wait, file=sys.stderr)
        return 2
    lines = summary(heard)
    for _, _, text in lines:
        print(text)
    if args.verbose:
        for name, report in sorted(heard.items()):
            print('  %-28s %-5s %s  [%s]' % (name, report.level.name, report.message,
                                            ', '.join('%s=%s' % kv for kv in report.values)))
    return 0 if all(level == Level.OK for _, level, _ in lines) else 1
