"""Starting a command on the host a process runs on (emulated hosts on one machine).

The Adaptation Engine starts the new nodes of a site next to the site's running ones. On one
machine with emulated hosts (network namespaces, :mod:`aft_ftm.hosts`), "next to" means in the
site's network namespace, with the site's ROS_IP / ROS_HOSTNAME: otherwise the new nodes would run
on the engine's host, keep running when the site's host loses power, and be reached through the
wrong address. :func:`run_where` rewrites a command line so that it runs in the network namespace
of a given process (``nsenter --net``), with that process's ROS addresses. Under mutual TLS the new
nodes also take the TLS party of a running node of their site (:func:`site_tls`: each site is a
party of the policy, and the engine's own party may not run a site's nodes), checked against the
engine's own policy and CA, on one host as on several.

Across real machines a process of another machine is not visible here: the command is left as it
is (the engine's host), and roslaunch's ``<machine>`` tags are the way to place nodes there.
"""
import os
import time

import psutil

ROS_ADDRESSES = ('ROS_IP', 'ROS_HOSTNAME', 'ROS_MASTER_URI')
# A node's mutual-TLS setting (aft_ftm.ros.params.secure_from_environment): a node started for a site
# speaks as that site's party, never as the party of the process that starts it (the engine's).
TLS_VARIABLES = ('AFT_TLS_DIR', 'AFT_TLS_PARTY', 'AFT_TLS_POLICY')


class WhereError(Exception):
    """The site's TLS party cannot be given to its new nodes: they would run as another party."""


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


def process_setting(pid):
    """(environment, working directory) of process pid; WhereError if either cannot be read."""
    try:
        proc = psutil.Process(pid)
        return proc.environ(), proc.cwd()
    except (OSError, psutil.Error) as e:
        raise WhereError('the environment of process %d cannot be read (%s): its TLS party is unknown' % (pid, e))


def site_tls(their_env, their_cwd, nodes, own_env, now=None):
    """The TLS variables of new nodes (names ``nodes``) that join the site of a running node whose
    environment and working directory are ``their_env`` and ``their_cwd``: its directory and party,
    this process's own policy (never the other process's: a process registered under a site's name is
    anyone's). None when this process runs without TLS (nothing then would check them).

    Raises WhereError, naming the problem, when that node runs without TLS, its party may not name
    every one of ``nodes`` under this process's policy (or is bound to no names in it), or its
    directory's certificate is not one this process's CA signed for that party, valid now: started
    so, the nodes would be refused by every peer, or would speak as a party they are not."""
    from . import tls
    from .errors import ConfigError
    own_dir, policy = own_env.get('AFT_TLS_DIR'), own_env.get('AFT_TLS_POLICY')
    if not own_dir:
        return None
    if not policy:
        raise WhereError('AFT_TLS_DIR is set here (%s) but not AFT_TLS_POLICY: no policy to check the site\'s party '
                         'against' % own_dir)
    policy = os.path.abspath(policy)   # the new nodes run elsewhere (roslaunch's ROS_HOME)
    directory, party = their_env.get('AFT_TLS_DIR'), their_env.get('AFT_TLS_PARTY')
    if not directory or not party:
        raise WhereError('the site runs without TLS (its node has no AFT_TLS_DIR and AFT_TLS_PARTY) while this '
                         'process runs under TLS: its new nodes would be refused by every peer')
    directory = os.path.normpath(os.path.join(their_cwd or '/', directory))
    try:
        permissions = tls.Permissions.load(policy)
        if permissions.nodes.get(party) is None:
            raise ConfigError('party %s is bound to no node names in the policy %s' % (party, policy))
        for name in nodes:
            why = permissions.names_node(party, name)
            if why:
                raise ConfigError(why)
        tls.check_party_certificate(directory, party, tls.Revocations.of_directory(own_dir).key,
                                    time.time() if now is None else now)
    except ConfigError as e:
        raise WhereError('the site\'s TLS party %s (%s) cannot run %s: %s' % (party, directory, ', '.join(nodes), e))
    return {'AFT_TLS_DIR': directory, 'AFT_TLS_PARTY': party, 'AFT_TLS_POLICY': policy}


def with_tls(env, tls_variables):
    """env with the TLS variables given (None: as it is)."""
    env = dict(env)
    if tls_variables is not None:
        env.update(tls_variables)
    return env
