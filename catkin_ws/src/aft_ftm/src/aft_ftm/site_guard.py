"""Nodes an adaptation launches belong to the site they join, and stop with it.

A site is a roslaunch process tree (:mod:`aft_ftm.sites`). The Adaptation Engine starts new nodes
with a roslaunch of its own: a child of the engine, not of the site's launcher, so stopping the
site would leave them running. So the engine names the site's launcher (its *owner*: pid and
create time, which together identify a process even once its pid is reused) and runs the launch
under a guard (:mod:`aft_ftm.ros.guarded_launch`) that stops the launch's whole process tree once
an owner is gone. The guard does nothing when the engine exits: the nodes outlive the engine.

This module is the pure part, without processes:

- :class:`Owner`, its text form (``pid:create_time``, comma-separated in :data:`OWNERS_ENV`);
- :func:`same_process`: is an owner still the process it was?
- :func:`neighbours` and :func:`launcher_among`: which running nodes share a new node's site,
  and which ancestor of a node's process is its site's launcher;
- :class:`Guard`: the guard's state machine (:data:`GUARD_EDGES`), ``now`` passed in.

Invariants: a guard never stops its launch while every owner runs and nobody asked it to; once
it stops it, every process of the launch is gone (asked first with SIGINT, as Ctrl-C would, then
killed after the grace) before the guard exits.
"""
import collections
import enum
import os

from .errors import AftError

OWNERS_ENV = 'AFT_SITE_OWNERS'   # set in a guarded launch's environment: its nodes carry their site's owners
CREATE_TIME_TOLERANCE = 0.005    # s: half a clock tick (create times are counted in ticks of 10 ms)


class GuardError(AftError):
    """A guard was given owners it cannot read."""


class Owner(collections.namedtuple('Owner', 'pid create_time')):
    """A site's launcher: its pid and its start (s since boot: aft_ftm.process_start, the same in every
    process whatever the wall clock does)."""
    __slots__ = ()

    def encode(self):
        return '%d:%.3f' % (self.pid, self.create_time)


def encode_owners(owners):
    return ','.join(o.encode() for o in owners)


def parse_owners(text):
    """Owners from their text form: ``pid:create_time[,pid:create_time...]``. GuardError names
    what it cannot read."""
    owners = []
    for part in (p.strip() for p in str(text).split(',')):
        pid, _, created = part.partition(':')
        try:
            owner = Owner(int(pid), float(created))
        except ValueError:
            raise GuardError('an owner is pid:create_time (e.g. 4242:1718000000.25), got %r' % part)
        if owner.pid <= 0 or owner.create_time <= 0:
            raise GuardError('an owner is pid:create_time with both > 0, got %r' % part)
        owners.append(owner)
    return owners


def same_process(owner, create_time):
    """True if the process now under owner.pid, created at create_time (None: no such process,
    or a zombie), is the owner itself."""
    return create_time is not None and abs(create_time - owner.create_time) < CREATE_TIME_TOLERANCE


def namespaces(name):
    """The namespaces of a graph name, deepest first, without the root: /a/b/c -> /a/b, /a."""
    parts = name.strip('/').split('/')[:-1]
    return ['/' + '/'.join(parts[:i]) for i in range(len(parts), 0, -1)]


def neighbours(name, running, exclude=()):
    """The running nodes of the deepest namespace of name that has any (not name itself, not
    those in exclude), sorted: the nodes whose site a new node joins. Empty for a node of the
    root namespace, which is no site's."""
    others = sorted(set(running) - set(exclude) - {name})
    for ns in namespaces(name):
        found = [n for n in others if n.startswith(ns + '/')]
        if found:
            return found
    return []


def is_roslaunch(cmdline):
    """A roslaunch process: ``roslaunch ...`` or ``python .../roslaunch ...``."""
    return any(os.path.basename(arg) == 'roslaunch' for arg in list(cmdline)[:2])


def launcher_among(chain):
    """The launcher of a node's site from its process and its ancestors, nearest first, as
    (pid, create_time, cmdline) triples: the nearest roslaunch above the node. None if none."""
    for pid, create_time, cmdline in list(chain)[1:]:
        if is_roslaunch(cmdline):
            return Owner(pid, create_time)
    return None


class GuardState(enum.Enum):
    RUNNING = 0     # the launch runs; every owner is alive
    STOPPING = 1    # asked to stop with SIGINT: waiting for its processes to end, within the grace
    KILLING = 2     # killing whatever of the launch still runs
    DONE = 3        # nothing of the launch runs: the guard exits


class Cause(enum.Enum):
    OWNER_GONE = 'owner gone'
    ASKED = 'asked to stop'
    CHILD_EXITED = 'launch exited'
    GRACE_OVER = 'grace over'
    ALL_GONE = 'all gone'


# (state, cause) -> (new state, why). The only state changes of a guard.
GUARD_EDGES = {
    (GuardState.RUNNING, Cause.OWNER_GONE):
        (GuardState.STOPPING, 'a launcher of its site is gone (its pid ended, or belongs to another process now): '
                              'the launch stops with its site'),
    (GuardState.RUNNING, Cause.ASKED):
        (GuardState.STOPPING, 'asked to stop (SIGINT or SIGTERM: a rollback, an operator)'),
    (GuardState.RUNNING, Cause.CHILD_EXITED):
        (GuardState.KILLING, 'the launch ended by itself: whatever it left running is killed'),
    (GuardState.STOPPING, Cause.CHILD_EXITED):
        (GuardState.KILLING, 'the launch stopped: whatever it left running is killed'),
    (GuardState.STOPPING, Cause.GRACE_OVER):
        (GuardState.KILLING, 'still running after the grace: every process of the launch is killed'),
    (GuardState.KILLING, Cause.ALL_GONE):
        (GuardState.DONE, 'nothing of the launch runs any more'),
    (GuardState.KILLING, Cause.GRACE_OVER):
        (GuardState.DONE, 'processes that do not die even killed are left behind (the guard gives up)'),
}


class Action(enum.Enum):
    INTERRUPT = 'interrupt'   # SIGINT to the launch (roslaunch stops its nodes, as on Ctrl-C)
    KILL = 'kill'             # SIGKILL to every process of the launch still running
    EXIT = 'exit'             # the guard's work is done
    FAIL_SITE = 'fail_site'   # tell the site to fail-stop (aft_ftm.ros.fail_site), as its own nodes do


Decision = collections.namedtuple('Decision', 'actions reason')


class Guard(object):
    """Decides, at each poll, what the guard of one launch does. ``grace`` (s): how long the
    launch has to stop after SIGINT before it is killed, and how long killing is tried.
    ``fail_site``: the launch holds required nodes (an adaptation's replacement of a site's
    Before, Proceed or After): if it ends by itself (one of them died), the site fail-stops with
    it, as a site does when one of its own nodes cannot serve; a launch asked
    to stop (a rollback, an operator), stopping with its site, or disarmed first (:meth:`disarm`: an
    adaptation retiring its nodes) never fails it."""

    def __init__(self, grace=5.0, fail_site=False):
        if not grace > 0:
            raise GuardError('the grace must be > 0 s, got %r' % (grace,))
        self.grace = grace
        self.fail_site = fail_site
        self.state = GuardState.RUNNING
        self.deadline = None

    def disarm(self):
        """The launch is about to end on purpose (an adaptation retires its nodes, by a signal):
        its end no longer fails the site."""
        self.fail_site = False

    def _change(self, cause, now):
        new, reason = GUARD_EDGES[(self.state, cause)]
        self.state = new
        if new in (GuardState.STOPPING, GuardState.KILLING):
            self.deadline = now + self.grace
        return reason

    def poll(self, now, asked, child_alive, owners_alive, tree_alive):
        """One look: ``asked`` (a stop signal came), ``child_alive`` (the launch process runs),
        ``owners_alive()`` and ``tree_alive()`` (any process of the launch runs), called only
        when needed (they cost /proc reads). Returns a Decision: actions to take, in order, and
        the reason of the state change ('' if none)."""
        if self.state == GuardState.RUNNING:
            if not child_alive:
                decision = self._killing(Cause.CHILD_EXITED, now, tree_alive)
                if self.fail_site and not asked:   # asked, its launch may end before the guard saw why
                    return Decision([Action.FAIL_SITE] + decision.actions, decision.reason + '; it held required '
                                    'nodes of its site: the site stops with it')
                return decision
            if asked:
                return Decision([Action.INTERRUPT], self._change(Cause.ASKED, now))
            if not owners_alive():
                return Decision([Action.INTERRUPT], self._change(Cause.OWNER_GONE, now))
            return Decision([], '')
        if self.state == GuardState.STOPPING:
            if not child_alive:
                return self._killing(Cause.CHILD_EXITED, now, tree_alive)
            if now >= self.deadline:
                return self._killing(Cause.GRACE_OVER, now, tree_alive)
            return Decision([], '')
        if self.state == GuardState.KILLING:
            if not tree_alive():
                return Decision([Action.EXIT], self._change(Cause.ALL_GONE, now))
            if now >= self.deadline:
                return Decision([Action.EXIT], self._change(Cause.GRACE_OVER, now))
            return Decision([Action.KILL], '')
        return Decision([Action.EXIT], '')

    def _killing(self, cause, now, tree_alive):
        reason = self._change(cause, now)
        if not tree_alive():
            return Decision([Action.EXIT], reason + '; ' + self._change(Cause.ALL_GONE, now))
        return Decision([Action.KILL], reason)
