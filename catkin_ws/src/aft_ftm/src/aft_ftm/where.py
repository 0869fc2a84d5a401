"""Starting a command on the host a process runs on (emulated hosts on one machine).

The Adaptation Engine starts the new nodes of a site next to the site's running ones. On one
machine with emulated hosts (network namespaces, :mod:`aft_ftm.hosts`), "next to" means in the
site's network namespace, with the site's ROS_IP / ROS_HOSTNAME: otherwise the new nodes would run
on the engine's host, keep running when the site's host loses power, and be reached through the
wrong address. :func:`run_where` rewrites a command line so that it runs in the network namespace
of a given process (``nsenter --net``), with that process's ROS addresses.

Across real machines a process of another machine is not visible here: the command is left as it
is (the engine's host), and roslaunch's ``<machine>`` tags are the way to place nodes there.
"""
import os

import psutil

ROS_ADDRESSES = ('ROS_IP', 'ROS_HOSTNAME', 'ROS_MASTER_URI')


def netns_of(pid):
    """The identity (device, inode) of process pid's network namespace; OSError if it cannot be read."""
    st = os.stat('/proc/%d/ns/net' % pid)
    return st.st_dev, st.st_ino


def run_where(pid, argv, env=None):
    """(argv, env) that start argv on the host of process pid: unchanged when pid shares this
    process's network namespace (or cannot be read), else entered into pid's namespace with pid's
    ROS addresses (absent ones removed, so the namespace's own defaults hold)."""
    env = dict(os.environ if env is None else env)
    try:
        theirs, mine = netns_of(pid), netns_of(os.getpid())
        their_env = psutil.Process(pid).environ()
    except (OSError, psutil.Error):
        return list(argv), env
    if theirs == mine:
        return list(argv), env
    for name in ROS_ADDRESSES:
        if name in their_env:
            env[name] = their_env[name]
        else:
            env.pop(name, None)
    return ['nsenter', '--net=/proc/%d/ns/net' % pid, '--'] + list(argv), env
