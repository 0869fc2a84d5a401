"""Launching the PBR demo's three sites as separate roslaunch processes, for the demo, the
integration tests and the benchmarks. Uses the master API only (no rospy node)."""
import os
import time

import rosgraph

from ..sites import Site, wait_until

REPLICA_SERVICES = ('protocol/set_role', 'protocol/rebind', 'after/set_role', 'after/rebind',
                    'before/rebind', 'proceed/rebind', 'crash_detector/rebind',
                    'bank_server/get_state', 'bank_server/set_state', 'account')


def missing_from_graph(services=(), subscriptions=(), caller='/aft_deployment'):
    """The services and (topic, node) subscriptions not yet registered with the master."""
    try:
        _, subs, srvs = rosgraph.Master(caller).getSystemState()
    except Exception as e:   # master not up yet
        return ['master: %s' % e]
    have_srvs = {name for name, _ in srvs}
    have_subs = {(topic, node) for topic, nodes in subs for node in nodes}
    return ([s for s in services if s not in have_srvs] +
            ['%s subscribed by %s' % s for s in subscriptions if s not in have_subs])


def wait_for_graph(services=(), subscriptions=(), timeout=60.0):
    """Wait until everything is registered; returns what is still missing (empty on success)."""
    missing = wait_until(lambda: not missing_from_graph(services, subscriptions), timeout, 0.05)
    return [] if missing else missing_from_graph(services, subscriptions)


def roslaunch(pkg, launch_file, **args):
    return ['roslaunch', '--wait', '--skip-log-check', pkg, launch_file] + \
           ['%s:=%s' % (k, v) for k, v in sorted(args.items())]


class PbrDeployment(object):
    """CLIENT, MASTER and SLAVE sites of the bank demo, each its own process tree."""

    def __init__(self, log_dir, period=0.01, timeout=0.03, env=None):
        self.log_dir = log_dir
        self.env = env
        replica = dict(period=period, timeout=timeout)
        self.sites = {
            'master': Site('master', roslaunch('aft_ftm', 'demo_replica_site.launch', site='master', peer='slave',
                                               role='primary', **replica),
                           env, os.path.join(log_dir, 'master.log')),
            'slave': Site('slave', roslaunch('aft_ftm', 'demo_replica_site.launch', site='slave', peer='master',
                                             role='backup', **replica),
                          env, os.path.join(log_dir, 'slave.log')),
            'client': Site('client', roslaunch('aft_ftm', 'demo_client_site.launch'),
                           env, os.path.join(log_dir, 'client.log')),
        }

    def start(self, timeout=120.0):
        """Start both replicas, then the client site; raise RuntimeError naming what did not come up."""
        os.makedirs(self.log_dir, exist_ok=True)
        started = time.monotonic()
        self.sites['slave'].start()
        self.sites['master'].start()
        for site in ('master', 'slave'):
            missing = wait_for_graph(['/%s/%s' % (site, s) for s in REPLICA_SERVICES],
                                     [('/%s/failures' % site, '/%s/recovery' % site)],
                                     timeout - (time.monotonic() - started))
            if missing:
                raise RuntimeError('site %s did not come up: missing %s (log: %s)'
                                   % (site, ', '.join(missing), self.sites[site].log_path))
        self.sites['client'].start()
        missing = wait_for_graph(['/account', '/proxy/rebind'], [('/ftm/pro2pxy', '/proxy')],
                                 timeout - (time.monotonic() - started))
        if missing:
            raise RuntimeError('client site did not come up: missing %s (log: %s)'
                               % (', '.join(missing), self.sites['client'].log_path))
        return time.monotonic() - started

    def stop(self):
        for site in self.sites.values():
            site.stop(grace=3.0)


def free_port():
    import socket
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def start_master(log_dir, port=None, timeout=30.0):
    """Start a roscore on a free port and point this process (and its children) at it.

    Returns the roscore Site; raises RuntimeError if the master does not answer in time.
    """
    port = port or free_port()
    os.environ['ROS_MASTER_URI'] = 'http://127.0.0.1:%d' % port
    os.makedirs(log_dir, exist_ok=True)
    core = Site('roscore', ['roscore', '-p', str(port)], log_path=os.path.join(log_dir, 'roscore.log')).start()

    def up():
        try:
            rosgraph.Master('/aft_deployment').getPid()
            return True
        except Exception:
            return False
    if not wait_until(up, timeout, 0.05):
        core.stop()
        raise RuntimeError('roscore on port %d did not answer within %.0f s (log: %s)'
                           % (port, timeout, core.log_path))
    return core
