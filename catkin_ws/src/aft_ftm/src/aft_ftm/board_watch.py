"""The watchdog's view of the boards of a replicated pub/sub node, without rospy
(:mod:`aft_ftm.ros.watchdog_node` carries its decisions out).

Every board is watched by its heartbeats (one :class:`aft_ftm.detector.HeartbeatMonitor` each, the
same timeout; the watchdog's own stalls are not held against a board) and by its After's
acknowledgments, and has a standing (:class:`Standing`; the edges in :data:`STANDING_EDGES`,
changed only in :meth:`BoardWatch._change`):

- PRIMARY: its outputs are the system's. Its silence while a backup can take over is a failure:
  it is powered off (fail-silence: it must not come back as a second primary) and the backup
  promoted (:class:`Failover`). Silent with no backup, it is reported and left alone: killing the
  only controller would gain nothing, and it may only have stalled.
- BACKUP: it acknowledged a checkpoint of the primary and its promotion connections are open: it
  is promoted if the primary fails. Silent, refusing a checkpoint or restarted, it is JOINING again.
- JOINING: heard, but holding no state of the primary's that the watchdog knows of: not yet
  acknowledged at start, back after a failure (restarted empty), silent, or it refused a checkpoint.
  It is never promoted. Its next acknowledgment of the primary's checkpoint makes it the backup
  (CONNECTING first if its promotion connections must be opened: :class:`Connect`).
- PROMOTING: the primary failed; its promotion calls are under way (:meth:`BoardWatch.promoted`).
- FAILED: a primary declared failed and powered off. Heartbeats of the incarnation that failed (the
  same launcher pid on the same host) are counted and ignored.

A board that was FAILED or silent and is heard from a new incarnation (another launcher pid) came
back, started again: JOINING, with an alarm, and an alarm again once it re-joined.

A board's last heartbeat may say it fail-stops (``stopping``: a node of it found it cannot serve, e.g.
its controller hangs): it is then declared silent at the next check, without waiting out the
timeout, as the crash detectors do. One that names another incarnation than the beats heard last
is stale (a late last word, or forged) and ignored (counted in its monitor's ``stale_announcements``).

Invariants: at most one board is PRIMARY or PROMOTING; only a BACKUP is ever promoted, so a board
that came back is never promoted before it re-joined; only a primary with a backup to replace it is
powered off; every change that degrades the pair, and a board coming back and re-joining, is
reported with an alarm. ``now`` is always passed in.
"""
import collections
import enum

from .detector import HeartbeatMonitor, PeerState
from .errors import ConfigError, RoleError


class Standing(enum.Enum):
    PRIMARY = 0
    BACKUP = 1
    JOINING = 2
    CONNECTING = 3
    PROMOTING = 4
    FAILED = 5


STANDING_EDGES = {
    (Standing.JOINING, Standing.BACKUP): 'it acknowledged a checkpoint of the primary and its promotion '
                                         'connections are open (the first backup: opened at set-up)',
    (Standing.JOINING, Standing.CONNECTING): 'it acknowledged a checkpoint of the primary: its promotion '
                                             'connections are being opened',
    (Standing.CONNECTING, Standing.BACKUP): 'its promotion connections are open: it is promoted if the primary fails',
    (Standing.CONNECTING, Standing.JOINING): 'its promotion connections could not be opened, or it refused a '
                                             'checkpoint, fell silent or restarted',
    (Standing.BACKUP, Standing.JOINING): 'it refused a checkpoint, fell silent or restarted: it may no longer '
                                         'mirror the primary',
    (Standing.BACKUP, Standing.PROMOTING): 'the primary failed: it is promoted',
    (Standing.PROMOTING, Standing.PRIMARY): 'it took over',
    (Standing.PROMOTING, Standing.JOINING): 'its promotion failed: it holds no state it may serve',
    (Standing.PRIMARY, Standing.FAILED): 'silent while a backup could take over: powered off, the backup promoted',
    (Standing.PRIMARY, Standing.JOINING): 'silent with no backup, then heard from a new incarnation: it was started '
                                          'again and holds nothing (there is no primary)',
    (Standing.FAILED, Standing.JOINING): 'a new incarnation of it is heard: it restarted empty and must re-join',
}

# What a standing means for promotion, in the words of a report.
_MEANING = {Standing.PRIMARY: 'the primary', Standing.BACKUP: 'the backup',
            Standing.JOINING: 'joining (it holds no state of the primary\'s, or is silent)',
            Standing.CONNECTING: 're-joined, its promotion connections not open yet',
            Standing.PROMOTING: 'being promoted', Standing.FAILED: 'failed (powered off)'}


# -- what the watchdog's node carries out ----------------------------------------------------------
# The primary ``board`` failed (``verdict``): power it off, then promote ``nodes`` of board ``to``;
# then call BoardWatch.promoted(to, problems, now).
Failover = collections.namedtuple('Failover', 'board verdict to nodes')
# Open the promotion connections to ``nodes`` of ``board``; then call BoardWatch.connected(board, error, now).
Connect = collections.namedtuple('Connect', 'board nodes')
# Log ``detail``; raise an alarm (mechanism pbr) of ``kind`` if ``alarm``; publish ``record`` (a dict) if given.
Report = collections.namedtuple('Report', 'kind detail alarm record')


def boards_param(name, value):
    """The boards of a watchdog from a parameter: {board: [node to promote, ...], ...}, two boards or
    more. Returns an ordered dict; ConfigError names the parameter and the value."""
    if not isinstance(value, dict) or len(value) < 2:
        raise ConfigError('parameter %s must map at least two board names to the lists of nodes to promote, got %r'
                          % (name, value))
    bad = [board for board in value if not isinstance(board, str) or not board.strip()]
    if bad:
        raise ConfigError('parameter %s: board names must be non-empty strings, got %r' % (name, bad[0]))
    boards = collections.OrderedDict()
    for board in sorted(value):
        nodes = value[board]
        if not isinstance(nodes, list) or not nodes or not all(isinstance(n, str) and n.strip() for n in nodes):
            raise ConfigError('parameter %s: board %s must have a non-empty list of node names, got %r'
                              % (name, board, nodes))
        boards[board.strip()] = [n.strip() for n in nodes]
    return boards


class Board(object):
    """One board as the watchdog sees it."""

    def __init__(self, name, nodes, standing, monitor, connected):
        self.name = name
        self.nodes = list(nodes)
        self.standing = standing
        self.monitor = monitor
        self.connected = connected      # its promotion connections are open
        self.incarnation = None         # (host, launcher pid) from its heartbeats
        self.failed_incarnation = None  # the incarnation declared failed
        self.stray_beats = 0            # heartbeats of the failed incarnation (late, or fail-silence broken)
        self.stray_told = False         # fail_silence_broken said for the failed incarnation
        self.stray_since = None         # when the first of those beats came
        self.silent_since = None        # declared silent (not FAILED) at, until heard again
        self.silent_verdict = None      # a silent primary's verdict: it is failed over once a backup is ready
        self.stale_told = set()         # incarnations told stale_announcement (bounded)
        self.lost_at = None             # FAILED or silent at, until a new incarnation is heard
        self.back_at = None             # when a new incarnation was heard, until it re-joins
        self.failures = 0


class BoardWatch(object):
    """The boards of one replicated node, by role (see the module's docstring).

    ``boards``: {name: [nodes to promote]}; ``primary``: the board that starts as primary (the others
    start JOINING: a backup is promoted only once it acknowledged a checkpoint); ``connected``: the
    boards whose promotion connections are already open; ``stall_after``: a check that comes later
    than this after the previous one was the watchdog's own stall (aft_ftm.detector).
    """

    def __init__(self, boards, primary, timeout, now, startup_grace=0.0, connected=(), stall_after=None):
        if primary not in boards:
            raise ConfigError('the primary board %r is not one of the boards (%s)' % (primary, ', '.join(boards)))
        self.timeout = timeout
        self.stall_after = stall_after
        self.boards = collections.OrderedDict()
        for name, nodes in boards.items():
            self.boards[name] = Board(name, nodes, Standing.PRIMARY if name == primary else Standing.JOINING,
                                      self._monitor(now, startup_grace), name in connected)

    def _monitor(self, now, startup_grace=0.0):
        return HeartbeatMonitor(self.timeout, startup_grace, now, stall_after=self.stall_after)

    # -- queries ---------------------------------------------------------------------------------
    def standing(self, name):
        return self.boards[name].standing

    def _the(self, standing):
        return next((b for b in self.boards.values() if b.standing == standing), None)

    @property
    def primary(self):
        board = self._the(Standing.PRIMARY)
        return board.name if board else None

    @property
    def backup(self):
        board = self._the(Standing.BACKUP)
        return board.name if board else None

    def describe(self):
        return ', '.join('%s %s' % (b.name, _MEANING[b.standing]) for b in self.boards.values())

    # -- the one place where a standing changes --------------------------------------------------
    def _change(self, board, new):
        if (board.standing, new) not in STANDING_EDGES:
            raise RoleError('board %s: %s -> %s is not allowed' % (board.name, board.standing.name, new.name))
        board.standing = new

    # -- inputs ----------------------------------------------------------------------------------
    def beat(self, name, now, host, pid, info=None):
        """A heartbeat of board name, from the launcher ``pid`` on ``host``. Returns actions."""
        board = self.boards.get(name)
        if board is None:
            return []
        incarnation = (host, pid)
        if board.standing == Standing.FAILED:
            if incarnation == board.failed_incarnation:
                board.stray_beats += 1
                if board.stray_since is None:
                    board.stray_since = now
                # Beats that keep coming over more than a timeout (a backlog of late ones comes at once),
                # a timeout after the verdict.
                if board.lost_at is not None and now - board.lost_at > self.timeout and \
                        now - board.stray_since > self.timeout and not board.stray_told:
                    # Not a late beat: the incarnation declared failed still runs (a remote board not powered
                    # off, a frozen one resumed), beside the promoted board. Said once (review of stop 39).
                    board.stray_told = True
                    return [Report('fail_silence_broken', 'board %s, declared failed %.2f s ago, still beats (launcher '
                                   'pid %d on %s): it was not silenced and may still publish beside board %s'
                                   % (name, now - board.lost_at, pid, host, self.primary), True, None)]
                return []
            self._change(board, Standing.JOINING)
            return self._heard_again(board, now, incarnation, info)
        stopping = getattr(info, 'stopping', '') if info is not None else ''
        if stopping and board.incarnation is not None and board.incarnation != incarnation:
            # Not the incarnation heard: a late last word of an old one, or forged. Said once per incarnation.
            board.monitor.stale_announcements += 1
            if incarnation in board.stale_told or len(board.stale_told) >= 64:
                return []
            board.stale_told.add(incarnation)
            return [Report('stale_announcement', 'board %s announced a fail-stop (%s) from launcher pid %d on %s, not '
                           'the incarnation heard (pid %d on %s): ignored; a late last word, or forged'
                           % (name, stopping, pid, host, board.incarnation[1], board.incarnation[0]), True, None)]
        if stopping and board.silent_since is not None:
            return []   # its last word: it stays silent (a beat would have it heard again)
        if board.silent_since is not None:
            return self._heard_again(board, now, incarnation, info)
        if stopping:   # its last word: silent from now on (the next check fails it over)
            board.incarnation = incarnation
            board.monitor.announced(now, stopping, info)
            return []
        actions = []
        if board.incarnation is not None and board.incarnation != incarnation and board.standing != Standing.PRIMARY:
            # Restarted faster than its silence could be noticed: whatever it held is gone.
            board.connected = False
            if board.standing in (Standing.BACKUP, Standing.CONNECTING):
                self._change(board, Standing.JOINING)
                actions.append(Report('backup_restarted', 'backup board %s restarted (launcher pid %d on %s): it is '
                                      'not promoted until it re-joins' % (name, pid, host), True, None))
        board.incarnation = incarnation
        board.monitor.beat(now, info)
        return actions

    def _heard_again(self, board, now, incarnation, info):
        """A board declared failed or silent is heard: watched afresh; a new incarnation came back."""
        board.monitor = self._monitor(now)
        board.monitor.beat(now, info)
        silent_since, board.silent_since, board.silent_verdict = board.silent_since, None, None
        if incarnation == board.incarnation:   # it only stalled
            return [Report('board_heard', 'board %s (%s) is heard again after %.0f ms of silence'
                           % (board.name, _MEANING[board.standing], (now - silent_since) * 1e3), False, None)]
        lost_at = board.lost_at
        board.incarnation, board.connected, board.back_at = incarnation, False, now
        if board.standing == Standing.PRIMARY:
            self._change(board, Standing.JOINING)
        return [Report('board_back', 'board %s is heard again (launcher pid %d on %s), %.1f s after it was lost: it '
                       'holds no state and is not promoted until it re-joins (%s)'
                       % (board.name, incarnation[1], incarnation[0], now - lost_at, self.describe()), True,
                       {'kind': 'board_back', 'board': board.name})]

    def ack(self, name, ok, to, now):
        """Board name's After answered a checkpoint of the After ``to`` ('' if it does not say).
        Returns actions."""
        board = self.boards.get(name)
        primary = self._the(Standing.PRIMARY)
        if board is None or primary is None or board is primary or (to and to not in primary.nodes):
            return []
        if board.silent_since is not None:
            return []   # its heartbeats first: a board the watchdog cannot watch is not promoted
        if not ok:
            if board.standing not in (Standing.BACKUP, Standing.CONNECTING):
                return []
            self._change(board, Standing.JOINING)
            return [Report('backup_refused', 'board %s refused a checkpoint of %s: it is not promoted until it '
                           're-joins' % (name, primary.name), False, None)]   # its After raises the alarm
        if board.standing != Standing.JOINING:
            return []
        if board.connected:
            self._change(board, Standing.BACKUP)
            return self._rejoined(board, primary, now) + self._take_over_silent(now)
        self._change(board, Standing.CONNECTING)
        return [Connect(name, list(board.nodes))]

    def connected(self, name, error, now):
        """The promotion connections to board name are open ('' error), or could not be opened."""
        board = self.boards[name]
        if board.standing != Standing.CONNECTING:
            return []   # it failed, fell silent or refused a checkpoint meanwhile
        if error:
            self._change(board, Standing.JOINING)
            return [Report('backup_unreachable', 'board %s re-joined but cannot be promoted (%s): tried again at its '
                           'next acknowledgment' % (name, error), True, None)]
        board.connected = True
        self._change(board, Standing.BACKUP)
        return self._rejoined(board, self._the(Standing.PRIMARY), now) + self._take_over_silent(now)

    def _take_over_silent(self, now):
        """A backup is ready while the primary is silent, left running for want of one: failed over now. It
        was never heard since its verdict (a beat would have cleared it), and a primary that fail-stopped
        never beats again: left, nobody would serve (review of session 37: a board that fail-stopped while
        its joiner was still being connected)."""
        primary = self._the(Standing.PRIMARY)
        if primary is None or primary.silent_since is None or primary.silent_verdict is None:
            return []
        verdict, primary.silent_verdict, primary.silent_since = primary.silent_verdict, None, None
        failures, lost_at = primary.failures, primary.lost_at
        actions = self._silent(primary, verdict, now)
        primary.failures, primary.lost_at = failures, lost_at   # the same failure, counted once
        return actions

    def _rejoined(self, board, primary, now):
        if board.back_at is None:   # the first backup at start, or one that only stalled
            return [Report('backup_ready', 'board %s follows %s: it is promoted if %s fails'
                           % (board.name, primary.name, primary.name), False, None)]
        since, board.back_at = now - board.back_at, None
        return [Report('board_rejoined', 'board %s re-joined %.2f s after it came back: it follows %s and is promoted '
                       'if %s fails' % (board.name, since, primary.name, primary.name), True,
                       {'kind': 'rejoin', 'board': board.name, 'primary': primary.name, 'since_back': since})]

    def check(self, now):
        """Look for silent boards. Returns actions."""
        actions = []
        for board in self.boards.values():
            if board.standing not in (Standing.FAILED, Standing.PROMOTING) and board.silent_since is None:
                verdict = board.monitor.check(now)
                if verdict is not None:
                    actions += self._silent(board, verdict, now)
        return actions

    def _silent(self, board, verdict, now):
        board.failures += 1
        board.lost_at = now
        if board.standing == Standing.PRIMARY:
            backup = self._the(Standing.BACKUP)
            if backup is not None and backup.monitor.state == PeerState.FAILED:
                backup = None   # it announced its own fail-stop: not promoted (its verdict comes at this check)
            if backup is not None:
                self._change(board, Standing.FAILED)
                board.failed_incarnation, board.connected, board.back_at = board.incarnation, False, None
                board.stray_told, board.stray_since = False, None
                self._change(backup, Standing.PROMOTING)
                return [Failover(board.name, verdict, backup.name, list(backup.nodes))]
            board.silent_since, board.silent_verdict = now, verdict
            others = ', '.join('%s is %s' % (b.name, _MEANING[b.standing])
                               for b in self.boards.values() if b is not board)
            return [Report('primary_silent', 'primary board %s is silent (%s) and no board may take over (%s): it is '
                           'left running' % (board.name, verdict.reason, others), True, None)]
        board.silent_since = now
        was = board.standing
        if was in (Standing.BACKUP, Standing.CONNECTING):
            self._change(board, Standing.JOINING)
        return [Report('board_silent', 'board %s (%s) is silent (%s): it is not promoted until it is heard again and '
                       'acknowledges a checkpoint' % (board.name, _MEANING[was], verdict.reason), True, None)]

    def promoted(self, name, problems, now):
        """The promotion of board name is done (``problems``: [] if every node took the role)."""
        board = self.boards[name]
        if board.standing != Standing.PROMOTING:
            return []
        self._change(board, Standing.JOINING if problems else Standing.PRIMARY)
        return []
