"""Starting a command on the host a process runs on (emulated hosts on one machine).

The Adaptation Engine starts the new nodes of a site next to the site's running ones. On one
machine with emulated hosts (network namespaces, :mod:`aft_ftm.hosts`), "next to" means in the
site's network namespace, with the site's ROS_IP / ROS_HOSTNAME: otherwise the new nodes would run
on the engine's host, keep running when the site's host loses power, and be reached through the
wrong address. :func:`run_where` rewrites a command line so that it runs in the network namespace
of a given process (``nsenter --net``), with that process's ROS addresses. Under mutual TLS the new
nodes also take that process's TLS party (each site is a party of the policy, and the engine's own
party may not run a site's nodes), on one host as on several.

Across real machines a process of another machine is not visible here: the command is left as it
is (the engine's host), and roslaunch's ``<machine>`` tags are the way to place nodes there.
"""
import os

import psutil

ROS_ADDRESSES = ('ROS_IP', 'ROS_HOSTNAME', 'ROS_MASTER_URI')
# A node's mutual-TLS party (aft_ftm.ros.params.secure_from_environment): a node started for a site
# speaks as that site's party, never as the party of the process that starts it (the engine's).
TLS_VARIABLES = ('AFT_TLS_DIR', 'AFT_TLS_PARTY', 'AFT_TLS_POLICY')


class WhereError(Exception):
    """The site's TLS party cannot be known: its nodes would be started as another party."""


def netns_of(pid):
    """The identity (device, inode) of process pid's network namespace; OSError if it cannot be read."""
    st = os.stat('/proc/%d/ns/net' % pid)
    return st.st_dev, st.st_ino


def _take(env, theirs, names):
    for name in names:
        if name in theirs:
            env[name] = theirs[name]
        else:
            env.pop(name, None)


def run_where(pid, argv, env=None):
    """(argv, env) that start argv as a process of process pid's site: with pid's TLS party (its
    AFT_TLS_* variables, absent ones removed), and, when pid is in another network namespace (an
    emulated host), entered into that namespace with pid's ROS addresses (absent ones removed, so the
    namespace's own defaults hold). Raises WhereError if pid's environment cannot be read while env
    names a TLS directory (the nodes would speak as this process's party, which every peer refuses
    for a site's names); without TLS such a pid leaves argv and env unchanged."""
    env = dict(os.environ if env is None else env)
    try:
        their_env = psutil.Process(pid).environ()
    except (OSError, psutil.Error) as e:
        if env.get('AFT_TLS_DIR'):
            raise WhereError("the environment of process %d cannot be read (%s): its site's TLS party is unknown"
                             % (pid, e))
        return list(argv), env
    _take(env, their_env, TLS_VARIABLES)
    try:
        theirs, mine = netns_of(pid), netns_of(os.getpid())
    except OSError:
        return list(argv), env
    if theirs == mine:
        return list(argv), env
    _take(env, their_env, ROS_ADDRESSES)
    return ['nsenter', '--net=/proc/%d/ns/net' % pid, '--'] + list(argv), env
