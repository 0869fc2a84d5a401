"""Crash detection from heartbeat timing.

A site's crash detector sends a heartbeat every ``period`` seconds and watches the
peer's. The peer is declared failed when nothing was heard from it for longer than
``timeout`` (after it was heard once), or for longer than ``startup_grace`` if it was
never heard at all (0 disables that: a peer that never started is not a crash).

Silence is counted only while this detector runs. A detector that was itself not scheduled (its
process starved, the whole machine stalled) cannot tell a silent peer from beats waiting unread
in its own socket; on a loaded 2-core machine such stalls reach tens of milliseconds (see
``scripts/bench_heartbeats``). With ``stall_after`` set, a check that comes more than
``stall_after`` after the previous one marks the excess as this detector's own stall, and that
time is not held against the peer. A crashed peer watched by a running detector is declared
exactly as without it.
"""
import enum


class PeerState(enum.Enum):
    UNKNOWN = 0   # never heard
    ALIVE = 1
    FAILED = 2    # declared failed; final (fail-silence: it must not come back)


class Verdict(object):
    """The declaration that the peer failed."""
    __slots__ = ('reason', 'silence', 'last_info')

    def __init__(self, reason, silence, last_info):
        self.reason = reason
        self.silence = silence
        self.last_info = last_info

    def __repr__(self):
        return 'Verdict(%r, silence=%.4f)' % (self.reason, self.silence)


class HeartbeatMonitor(object):
    """Watches one peer's heartbeats. ``now`` is always passed in (seconds)."""

    def __init__(self, timeout, startup_grace=0.0, started_at=0.0, stall_after=None):
        if timeout <= 0:
            raise ValueError('timeout must be > 0, got %r' % (timeout,))
        if stall_after is not None and stall_after <= 0:
            raise ValueError('stall_after must be > 0 (or None), got %r' % (stall_after,))
        self.stall_after = stall_after
        self.last_check = None
        self.stalled = 0.0          # this detector's own stalls since the peer was last heard
        self.stalls = 0             # how many checks found this detector stalled (diagnostics)
        self.timeout = timeout
        self.startup_grace = startup_grace
        self.started_at = started_at
        self.state = PeerState.UNKNOWN
        self.last_heard = None
        self.last_info = None
        self.beats = 0
        self.beats_after_failure = 0   # a peer heard after being declared failed: fail-silence broken

    def beat(self, now, info=None):
        """A heartbeat arrived. Returns True if it comes from a peer already declared failed."""
        if self.state == PeerState.FAILED:
            self.beats_after_failure += 1
            self.last_info = info
            return True
        self.state = PeerState.ALIVE
        self.last_heard = now
        self.stalled = 0.0
        self.last_info = info
        self.beats += 1
        return False

    def check(self, now):
        """Return a Verdict the first time the peer is found failed, else None."""
        self._note_stall(now)
        if self.state == PeerState.ALIVE:
            silence = now - self.last_heard
            if silence - self.stalled > self.timeout:
                self.state = PeerState.FAILED
                excused = ', of which %.1f ms this detector was stalled' % (self.stalled * 1e3) if self.stalled else ''
                return Verdict('no heartbeat for %.1f ms%s (timeout %.1f ms)'
                               % (silence * 1e3, excused, self.timeout * 1e3), silence, self.last_info)
        elif self.state == PeerState.UNKNOWN and self.startup_grace > 0:
            silence = now - self.started_at
            if silence > self.startup_grace:
                self.state = PeerState.FAILED
                return Verdict('never heard within the start-up grace of %.1f s'
                               % self.startup_grace, silence, None)
        return None

    def _note_stall(self, now):
        """Add to ``stalled`` the part of a late check's gap beyond stall_after that follows the
        last beat (a stall before the peer was last heard is no excuse for a later silence)."""
        previous, self.last_check = self.last_check, now
        if self.stall_after is None or previous is None:
            return
        stall_start = previous + self.stall_after
        if self.last_heard is not None:
            stall_start = max(stall_start, self.last_heard)
        if now > stall_start and now - previous > self.stall_after:
            self.stalled += now - stall_start
            self.stalls += 1
