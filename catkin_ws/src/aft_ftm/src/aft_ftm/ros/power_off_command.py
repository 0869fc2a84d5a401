"""The ``power_off`` command: a power loss of every node under a name space on this host, as a fault
to inject by hand (the walkthrough, a demo). Every node's process is frozen (SIGSTOP) first, then all
are killed (SIGKILL): no node of the name space runs a step more than another, as when a machine
loses power. Registrations stay at the master, as they would. Nodes on other hosts are named and left
alone: a power loss there needs that host's power switch.
"""
import argparse
import signal
import sys

import psutil

from .fencing import NamespaceFence


def main(argv):
    parser = argparse.ArgumentParser(prog='power_off', description=__doc__)
    parser.add_argument('namespace', help='the name space of the site, e.g. /master')
    options = parser.parse_args(argv)
    namespace = '/' + options.namespace.strip('/')
    fence = NamespaceFence(namespace, '/aft_power_off')
    try:
        fence.learn()
    except Exception as e:   # no master
        print('power_off: cannot ask the ROS master for the nodes of %s: %s' % (namespace, e), file=sys.stderr)
        return 2
    if fence.remote:
        print('power_off: left alone, on other hosts: %s' % ', '.join(sorted(fence.remote)), file=sys.stderr)
    for name, why in sorted(fence.refused.items()):
        print('power_off: left alone: %s is registered under %s, but %s' % (name, namespace, why), file=sys.stderr)
    if not fence.known:
        print('power_off: no node under %s runs on this host' % namespace, file=sys.stderr)
        return 1
    for name, (pid, created) in sorted(fence.known.items()):
        try:
            proc = psutil.Process(pid)
            if proc.create_time() == created:
                proc.send_signal(signal.SIGSTOP)
        except psutil.NoSuchProcess:
            pass
    killed = fence.kill()
    print('power_off: %s: %d nodes frozen then killed: %s' % (namespace, len(killed), ', '.join(killed)))
    return 0 if killed else 1
