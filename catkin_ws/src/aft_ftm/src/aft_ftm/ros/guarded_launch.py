"""A launch that belongs to a site it was not started by: it stops when the site's launcher goes.

``python -m aft_ftm.ros.guarded_launch --owner PID:CREATE_TIME [--owner ...] [--poll S] [--grace S] -- COMMAND ...``

Runs COMMAND (a ``roslaunch``, or the command line of a node started again) as its child, with
the owners in its environment (:data:`aft_ftm.site_guard.OWNERS_ENV`, so that a later adaptation
finds the site of these nodes too), and every ``--poll`` seconds (0.2) looks whether each owner is
still the process it was. Once one is gone, or when the guard gets SIGINT or SIGTERM (the engine's
rollback, an operator), it sends SIGINT to COMMAND (roslaunch stops its nodes as on Ctrl-C) and
kills whatever of the launch still runs ``--grace`` seconds (5) later. If COMMAND ends by itself,
what it left running is killed and the guard exits with its status; with ``--fail-site SITE`` (the
launch holds required nodes of that replica site) it first tells the site to fail-stop, through the
site's own ``/SITE/fail_stop`` topic (:mod:`aft_ftm.ros.fail_site`): the site's crash detector stops
its heartbeats and its peer fences it and takes over, as when one of the site's own nodes fail-stops,
instead of the site heartbeating on without its node. (Killing the site's launcher instead would
kill every site that launcher runs: one roslaunch may run both replicas.) SIGUSR1 disarms that
(:func:`disarm_guard_of`: an adaptation retiring the launch's nodes on purpose, by a signal).

The guard is a child subreaper, so that nodes orphaned by a roslaunch that died stay in its tree,
and COMMAND gets SIGTERM if the guard itself dies (Linux). It is no ROS node (it never talks to
the master); the decisions are :class:`aft_ftm.site_guard.Guard`'s, this module only acts.
Exit status: COMMAND's (128 + signal if a signal ended it), 1 if an owner was gone at the start.
"""
import argparse
import ctypes
import os
import signal
import subprocess
import sys
import time

import psutil

from ..process_start import started
from ..site_guard import OWNERS_ENV, Action, Guard, GuardError, encode_owners, parse_owners, same_process
from ..sites import process_tree, wait_dead

PR_SET_PDEATHSIG = 1
PR_SET_CHILD_SUBREAPER = 36


def guarded(argv, owners, poll=0.2, grace=5.0, fail_site=''):
    """The command line running argv under a guard of these owners (argv itself if none);
    fail_site: the name of the site that fail-stops if the launch ends by itself (it holds
    required nodes of that site), '' for none."""
    if not owners:
        return list(argv)
    command = [sys.executable, '-m', 'aft_ftm.ros.guarded_launch', '--poll', str(poll), '--grace', str(grace)]
    if fail_site:
        command += ['--fail-site', fail_site]
    for owner in owners:
        command += ['--owner', owner.encode()]
    return command + ['--'] + list(argv)


def disarm_guard_of(pid):
    """Tell the guard above process pid, if any, that its launch is about to end on purpose (its
    nodes retired): it will not fail the site. Returns the guard's pid, or None."""
    try:
        for proc in psutil.Process(pid).parents():
            cmdline = proc.cmdline()
            if '-m' in cmdline and 'aft_ftm.ros.guarded_launch' in cmdline:
                proc.send_signal(signal.SIGUSR1)
                return proc.pid
    except psutil.Error:   # gone meanwhile: nothing to disarm
        pass
    return None


def fail_site_command(site, reason):
    """The command line that tells site to fail-stop (aft_ftm.ros.fail_site)."""
    return [sys.executable, '-m', 'aft_ftm.ros.fail_site', '--site', site, '--reason', reason]


def create_time_of(pid):
    """The start of process pid on the boot clock (aft_ftm.process_start: the same in every process,
    whatever the wall clock does); None if there is none, or it is a zombie (it ran its course)."""
    return started(pid)


def _prctl(option, value):
    """Linux prctl(2); False where it is not available."""
    try:
        return ctypes.CDLL(None, use_errno=True).prctl(option, value, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _die_with(parent):
    """preexec_fn of the child: SIGTERM when the guard dies (and at once if it already has)."""
    def preexec():
        _prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent:
            os._exit(1)
    return preexec


def _say(text):
    print('[guarded_launch %d] %s' % (os.getpid(), text), flush=True)


def main(argv=None):
    parser = argparse.ArgumentParser(prog='guarded_launch', description=__doc__.split('\n\n')[0])
    parser.add_argument('--owner', action='append', required=True, help='pid:create_time of a site launcher')
    parser.add_argument('--poll', type=float, default=0.2, help='seconds between looks at the owners (0.2)')
    parser.add_argument('--grace', type=float, default=5.0, help='seconds to stop after SIGINT, then killed (5)')
    parser.add_argument('--fail-site', default='', metavar='SITE',
                        help='if the command ends by itself, tell SITE to fail-stop (on /SITE/fail_stop)')
    parser.add_argument('command', nargs=argparse.REMAINDER, help='-- then the command')
    options = parser.parse_args(argv)
    command = options.command[1:] if options.command[:1] == ['--'] else options.command
    try:
        owners = [o for text in options.owner for o in parse_owners(text)]
        guard = Guard(options.grace, fail_site=bool(options.fail_site))
    except GuardError as e:
        parser.error(str(e))
    if not command or not options.poll > 0:
        parser.error('a command (after --) and a poll > 0 are needed')

    def owners_alive():
        return all(same_process(o, create_time_of(o.pid)) for o in owners)
    if not owners_alive():
        _say('a launcher of the site (%s) is already gone: %s not started' % (encode_owners(owners), command[0]))
        return 1
    asked = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: asked.append(signum))
    def disarm(_signum, _frame):
        guard.disarm()
        _say('disarmed: the launch is retired on purpose, its end fails no site')
    signal.signal(signal.SIGUSR1, disarm)
    _prctl(PR_SET_CHILD_SUBREAPER, 1)
    env = dict(os.environ)
    env[OWNERS_ENV] = encode_owners(owners)
    child = subprocess.Popen(command, env=env, preexec_fn=_die_with(os.getpid()))
    _say('pid %d (%s) belongs to the site of launcher %s: it stops with it' % (child.pid, command[0],
                                                                               encode_owners(owners)))

    def tree():   # every process of the launch still running (zombies ran their course)
        return wait_dead(process_tree(os.getpid())[1:], 0)
    while True:
        decision = guard.poll(time.monotonic(), bool(asked), child.poll() is None, owners_alive,
                              lambda: bool(tree()))
        if decision.reason:
            _say(decision.reason)
        for action in decision.actions:
            if action == Action.INTERRUPT and child.poll() is None:
                child.send_signal(signal.SIGINT)
            elif action == Action.FAIL_SITE:
                code = child.poll()
                reason = '%s, holding required nodes of site %s, ended by itself (status %s)' % (
                    ' '.join(os.path.basename(word) for word in command[:2]), options.fail_site, code)
                try:
                    told = subprocess.run(fail_site_command(options.fail_site, reason), timeout=60).returncode
                except subprocess.TimeoutExpired:
                    told = None
                _say('the site %s fails: %s' % (options.fail_site, {0: 'told on its fail_stop topic'}.get(
                    told, 'its fail_stop topic had no subscriber (see the alarm)' if told == 1 else
                    'the fail_site command failed (status %s)' % told)))
            elif action == Action.KILL:
                for proc in tree():
                    try:
                        proc.kill()
                    except psutil.NoSuchProcess:
                        pass
            elif action == Action.EXIT:
                code = child.poll()
                return 1 if code is None else (128 - code if code < 0 else code)
        time.sleep(options.poll)


if __name__ == '__main__':
    sys.exit(main())
