"""Crash detection from heartbeat timing.

A site's crash detector sends a heartbeat every ``period`` seconds and watches the
peer's. The peer is declared failed when nothing was heard from it for longer than
``timeout`` (after it was heard once), or for longer than ``startup_grace`` if it was
never heard at all (0 disables that: a peer that never started is not a crash).
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

    def __init__(self, timeout, startup_grace=0.0, started_at=0.0):
        if timeout <= 0:
            raise ValueError('timeout must be > 0, got %r' % (timeout,))
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
        self.last_info = info
        self.beats += 1
        return False

    def check(self, now):
        """Return a Verdict the first time the peer is found failed, else None."""
        if self.state == PeerState.ALIVE:
            silence = now - self.last_heard
            if silence > self.timeout:
                self.state = PeerState.FAILED
                return Verdict('no heartbeat for %.1f ms (timeout %.1f ms)'
                               % (silence * 1e3, self.timeout * 1e3), silence, self.last_info)
        elif self.state == PeerState.UNKNOWN and self.startup_grace > 0:
            silence = now - self.started_at
            if silence > self.startup_grace:
                self.state = PeerState.FAILED
                return Verdict('never heard within the start-up grace of %.1f s'
                               % self.startup_grace, silence, None)
        return None
