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

Two rules decide when a silence is a failure:

- :class:`HeartbeatMonitor`: a fixed ``timeout``.
- :class:`PhiAccrualMonitor`: the phi accrual detector of Hayashibara et al. (2004), as Akka uses
  it. The last ``window`` inter-arrival times (this detector's own stalls taken out) give a
  normal model of when the next beat comes; the suspicion of a silence ``t`` is
  ``phi(t) = -log10(P(next beat later than t))`` with mean ``mu + acceptable_pause`` and standard
  deviation ``max(sigma, min_std)`` (Akka's logistic approximation of the normal tail, computed so
  that it never overflows). The peer is declared failed when phi exceeds ``threshold``: a threshold
  of 8 means a false suspicion once in 10^8 silences, if the model held. So the silence that is
  judged a failure follows the peer's measured regularity: short on a quiet machine, longer while
  beats come irregularly (nodes starting, a loaded core), and longer than any of the recent gaps
  only by the margin the threshold asks. Until ``min_samples`` intervals are known (the first
  beats after the peer is first heard) the model is not trusted, and the fixed
  ``bootstrap_timeout`` decides, as the fixed rule would.

  Why phi accrual rather than Chen et al. (2002): Chen's estimator (mean arrival plus a constant
  safety margin alpha) adapts to the mean only, and on this machine the mean gap stays at the
  period while its spread changes with the load; phi's margin scales with the measured spread,
  which is what a loaded machine changes. Phi with a ``threshold`` and a ``min_std`` is Chen's
  estimator with a margin of (threshold's z-score) x spread, bounded below.

A site that fail-stops on its own (a required node died, its server connection broke, the witness
deposed it) knows it before any silence can tell: its detector's last heartbeat says so
(``stopping``), and the peer declares it failed at the next check (:meth:`HeartbeatMonitor.announced`)
rather than one timeout later. The verdict then goes the way a silence's does (Recovery fences the
site before promoting anyone), so a wrong announcement costs what a false suspicion costs, no more.

Both share the life cycle of :class:`PeerState`, with one change function and these edges:
UNKNOWN -> ALIVE (first beat), ALIVE -> FAILED (the rule fires, or the peer announced its
fail-stop), UNKNOWN -> FAILED (never heard within ``startup_grace``, or announced). FAILED is final: a beat after it is counted (fail-silence broken), the
peer is not revived; a re-joined peer gets a new monitor.
"""
import collections
import enum
import math


# The crash detectors' defaults (the node's parameters, the launch files' arguments, the benchmark's
# "default" row): the rule and its settings. See scripts/bench_detection for the figures behind them.
DEFAULT_RULE = 'timeout'           # or 'phi'
DEFAULT_TIMEOUT = 0.03             # s: the fixed rule; phi's bootstrap timeout
DEFAULT_PHI = {'threshold': 8.0, 'window': 100, 'min_std': 0.005, 'acceptable_pause': 0.0, 'min_samples': 10}
DEFAULT_REALTIME_PRIORITY = 10    # SCHED_FIFO priority of the crash detectors' threads (0: off)


# How a verdict on a peer's own fail-stop begins (the peer said it stops; not a silence judged).
ANNOUNCED = 'it announced its fail-stop'


class PeerState(enum.Enum):
    UNKNOWN = 0   # never heard
    ALIVE = 1
    FAILED = 2    # declared failed; final (fail-silence: it must not come back)


# (from, to) -> why the edge exists. Every state change goes through HeartbeatMonitor._change.
EDGES = {
    (PeerState.UNKNOWN, PeerState.ALIVE): 'the first heartbeat',
    (PeerState.ALIVE, PeerState.ALIVE): 'a further heartbeat',
    (PeerState.ALIVE, PeerState.FAILED): 'the silence is judged a failure by the rule',
    (PeerState.UNKNOWN, PeerState.FAILED): 'never heard within the start-up grace, or its first word was its fail-stop',
}


class Verdict(object):
    """The declaration that the peer failed."""
    __slots__ = ('reason', 'silence', 'last_info')

    def __init__(self, reason, silence, last_info):
        self.reason = reason
        self.silence = silence
        self.last_info = last_info

    def __repr__(self):
        return 'Verdict(%r, silence=%.4f)' % (self.reason, self.silence)


def incarnation(info):
    """(host, launcher pid) a heartbeat names, or None where it names none (pid 0, no heartbeat)."""
    pid = getattr(info, 'pid', 0)
    return (getattr(info, 'host', ''), pid) if pid else None


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
        self.deferred = False       # the last check ended a stall and did not judge
        self.timeout = timeout
        self.startup_grace = startup_grace
        self.started_at = started_at
        self.state = PeerState.UNKNOWN
        self.last_heard = None
        self.last_beat = None          # the last beat in any state (also FAILED); None once a fail-stop is announced
        self.last_info = None
        self.beats = 0
        self.beats_after_failure = 0   # a peer heard after being declared failed: fail-silence broken
        self.announcement = None       # the peer's own fail-stop, until check() reports it

    def announced(self, now, reason, info=None):
        """The peer says it fail-stopped (its last heartbeat): it is declared failed, and the next
        check() returns the verdict. Returns True if this declares it (False: already failed, or
        the announcement is stale).

        Stale: it names another incarnation (host, launcher pid) than the beats heard last. A late
        last word of an old incarnation, after its site was started again and re-joined, says nothing
        of the one that runs, which it would fail over (review of stop 39); a forged one naming another
        process is refused the same way. A forger must first beat as that incarnation, and fencing then
        refuses the tree it names (tests/integration/test_forged_registration.py). Counted in
        ``stale_announcements``; the node raises ``stale_announcement``."""
        said, heard = incarnation(info), incarnation(self.last_info)
        if said is not None and heard is not None and said != heard:
            self.stale_announcements += 1
            return False
        self.last_beat = None   # it said it stops: not heard since
        if self.state == PeerState.FAILED:
            return False
        silence = now - self.last_heard if self.last_heard is not None else 0.0
        self._change(PeerState.FAILED)
        self.last_info = info if info is not None else self.last_info
        self.announcement = Verdict('%s: %s' % (ANNOUNCED, reason), silence, self.last_info)
        return True

    stale_announcements = 0   # fail-stops announced by an incarnation other than the one heard last

    def beat(self, now, info=None):
        """A heartbeat arrived. Returns True if it comes from a peer already declared failed."""
        self.last_beat = now
        if self.state == PeerState.FAILED:
            self.beats_after_failure += 1
            self.last_info = info
            return True
        if self.last_heard is not None:
            self._interval(max(0.0, now - self.last_heard - self.stalled))
        self._change(PeerState.ALIVE)
        self.last_heard = now
        self.stalled = 0.0
        self.last_info = info
        self.beats += 1
        return False

    def check(self, now):
        """Return a Verdict the first time the peer is found failed, else None. The check that ends
        this detector's own stall does not judge a silence: the beats that came meanwhile may still
        be unread in its socket (its receiving thread stalled too, and runs after this one). The next
        check judges, late or not: a detector stalled at every check still declares a dead peer. (In a
        campaign on a loaded machine a detector stalled 81 ms, 24 ms into a gap, and its first check
        declared the peer failed: 34.2 ms not excused.)"""
        stalled = self._note_stall(now)
        if self.announcement is not None:
            verdict, self.announcement = self.announcement, None
            return verdict
        self.deferred = stalled and not self.deferred
        if self.deferred:
            return None
        if self.state == PeerState.ALIVE:
            silence = now - self.last_heard
            rule = self._judge(silence - self.stalled)
            if rule is not None:
                self._change(PeerState.FAILED)
                excused = ', of which %.1f ms this detector was stalled' % (self.stalled * 1e3) if self.stalled else ''
                return Verdict('no heartbeat for %.1f ms%s (%s)' % (silence * 1e3, excused, rule),
                               silence, self.last_info)
        elif self.state == PeerState.UNKNOWN and self.startup_grace > 0:
            silence = now - self.started_at
            if silence > self.startup_grace:
                self._change(PeerState.FAILED)
                return Verdict('never heard within the start-up grace of %.1f s'
                               % self.startup_grace, silence, None)
        return None

    def heard_within(self, now, within):
        """Whether the peer's beats were heard in the last ``within`` seconds, in any state (a peer
        declared failed that beats again runs), with no fail-stop announced since: its site runs."""
        return self.last_beat is not None and now - self.last_beat <= within

    def can_take_over(self, now, within):
        """(alive, why): may the peer take over now? Only if it was heard within ``within`` seconds of real
        time, and is neither declared failed nor announcing its fail-stop. This detector's own stalls are
        not excused here, unlike in the verdict: a node that asks stays with its site when unsure, and
        asks again (aft_ftm.recovery.SiteRole.on_hang)."""
        if self.state == PeerState.FAILED or self.announcement is not None:
            return False, 'declared failed'
        if self.state == PeerState.UNKNOWN:
            return False, 'never heard'
        silence = now - self.last_heard
        if silence > within:
            return False, 'silent for %.1f ms' % (silence * 1e3)
        return True, 'heard %.1f ms ago' % (silence * 1e3)

    def _change(self, state):
        """The one place the peer's state changes; an edge not in EDGES is a bug."""
        if (self.state, state) not in EDGES:
            raise AssertionError('detector: no edge %s -> %s' % (self.state.name, state.name))
        self.state = state

    def _judge(self, silence):
        """The rule: a description of why ``silence`` (own stalls taken out) is a failure, else None."""
        if silence > self.timeout:
            return 'timeout %.1f ms' % (self.timeout * 1e3)
        return None

    def _interval(self, seconds):
        """A new inter-arrival time (own stalls taken out): the fixed rule has no use for it."""

    def _note_stall(self, now):
        """Whether this check comes late (this detector stalled). Add to ``stalled`` the part of a late
        check's gap beyond stall_after that follows the last beat (a stall before the peer was last
        heard is no excuse for a later silence)."""
        previous, self.last_check = self.last_check, now
        if self.stall_after is None or previous is None:
            return False
        stall_start = previous + self.stall_after
        if self.last_heard is not None:
            stall_start = max(stall_start, self.last_heard)
        if now > stall_start and now - previous > self.stall_after:
            self.stalled += now - stall_start
            self.stalls += 1
            return True
        return False


def why_heard_again(last, first, period, timeout):
    """Why a peer declared failed is heard again, from its last beat before the verdict and its first
    after: (seq, sent) pairs, sent by the peer's own clock (s). Tells a sender that stalled (its next
    beat sent past the timeout), one that was slow and whose beat arrived late too, beats sent on time
    that arrived late (delayed on the way, or unread at this receiver), beats not heard at all, and a
    peer that started again. ``period``: the beats' period as configured here. None if either beat is
    unknown."""
    if last is None or first is None:
        return None
    (seq0, sent0), (seq1, sent1) = last, first
    if seq1 <= seq0:
        return 'its beats count from %d again (last %d before the verdict): it started again' % (seq1, seq0)
    gap = sent1 - sent0
    missing = seq1 - seq0 - 1
    if missing:
        # rospy keeps the newest 10 of a backlog: after a stall of this detector, beats it dropped unread
        # count here too.
        return ('%d beat(s) between seq %d and %d were not heard (lost on the way, or dropped unread by this '
                'detector after a stall of its own); the two were sent %.1f ms apart'
                % (missing, seq0, seq1, gap * 1e3))
    if gap > timeout:
        return 'the sender stalled: its next beat (seq %d) was sent %.1f ms after the last one heard' % (seq1, gap * 1e3)
    if gap > 2 * period:
        return ('the sender was slow and its beat late on arrival too: its next beat (seq %d) was sent %.1f ms '
                'after the last one heard (period %.0f ms)' % (seq1, gap * 1e3, period * 1e3))
    return ('the beats were sent on time (seq %d then %d, %.1f ms apart) but arrived late: delayed on the way or '
            'unread by this detector' % (seq0, seq1, gap * 1e3))


# Akka's logistic approximation of the standard normal tail: P(Z > y) ~ 1 / (1 + exp(a(y))).
_A1, _A3 = 1.5976, 0.070566


def _softplus(a):
    """log(1 + exp(a)) without overflow."""
    return a + math.log1p(math.exp(-a)) if a > 0 else math.log1p(math.exp(a))


def phi(silence, mean, std):
    """-log10 of the probability that a beat expected at ``mean`` (+- ``std``, normal) comes later
    than ``silence``: 0.3 at the mean, about 8 at 5.6 standard deviations beyond it."""
    y = (silence - mean) / std
    return _softplus(y * (_A1 + _A3 * y * y)) / math.log(10.0)


def phi_z(threshold):
    """The number of standard deviations beyond the mean at which phi reaches ``threshold``."""
    a = math.log(math.expm1(threshold * math.log(10.0))) if threshold < 300 else threshold * math.log(10.0)
    low, high = -10.0, 100.0
    for _ in range(100):                      # bisection on an increasing cubic: bounded
        mid = (low + high) / 2.0
        if mid * (_A1 + _A3 * mid * mid) < a:
            low = mid
        else:
            high = mid
    return high


class PhiAccrualMonitor(HeartbeatMonitor):
    """Watches one peer's heartbeats with the phi accrual rule (see the module docstring).

    ``threshold``: phi above which the peer is declared failed; ``window``: the inter-arrival
    times kept; ``min_std`` (s): the spread assumed at least (a perfectly regular peer would
    otherwise be declared failed by the first late beat); ``acceptable_pause`` (s): added to the
    mean, a pause tolerated on top of the model; ``min_samples``: intervals needed before the model
    decides, ``bootstrap_timeout`` (s) deciding until then.
    """

    def __init__(self, threshold, bootstrap_timeout, window=100, min_std=0.005, acceptable_pause=0.0,
                 min_samples=10, startup_grace=0.0, started_at=0.0, stall_after=None):
        HeartbeatMonitor.__init__(self, bootstrap_timeout, startup_grace, started_at, stall_after)
        if not threshold > 0:
            raise ValueError('threshold must be > 0, got %r' % (threshold,))
        if isinstance(window, bool) or not isinstance(window, int) or window < 2:
            raise ValueError('window must be an integer >= 2, got %r' % (window,))
        if isinstance(min_samples, bool) or not isinstance(min_samples, int) or not 2 <= min_samples <= window:
            raise ValueError('min_samples must be an integer from 2 to window (%d), got %r' % (window, min_samples))
        if not min_std > 0:
            raise ValueError('min_std must be > 0, got %r' % (min_std,))
        if not acceptable_pause >= 0:
            raise ValueError('acceptable_pause must be >= 0, got %r' % (acceptable_pause,))
        self.threshold = threshold
        self.min_std = min_std
        self.acceptable_pause = acceptable_pause
        self.min_samples = min_samples
        self.intervals = collections.deque(maxlen=window)
        self._sum = 0.0
        self._squares = 0.0

    def _interval(self, seconds):
        if len(self.intervals) == self.intervals.maxlen:
            old = self.intervals[0]
            self._sum -= old
            self._squares -= old * old
        self.intervals.append(seconds)
        self._sum += seconds
        self._squares += seconds * seconds

    def learning(self):
        """True while too few intervals are known for the model to decide."""
        return len(self.intervals) < self.min_samples

    def model(self):
        """(mean with the acceptable pause, standard deviation) of the next arrival, in seconds."""
        n = len(self.intervals)
        mean = self._sum / n
        variance = max(0.0, self._squares / n - mean * mean)   # rounding can make it slightly negative
        return mean + self.acceptable_pause, max(math.sqrt(variance), self.min_std)

    def phi(self, silence):
        """The suspicion of a silence (own stalls taken out); None while learning."""
        if self.learning():
            return None
        mean, std = self.model()
        return phi(silence, mean, std)

    def suspicion_after(self):
        """The silence (own stalls taken out) after which the peer would be declared failed now."""
        if self.learning():
            return self.timeout
        mean, std = self.model()
        return mean + phi_z(self.threshold) * std

    def _judge(self, silence):
        if self.learning():
            if silence > self.timeout:
                return 'timeout %.1f ms while learning (%d of %d intervals)' % (
                    self.timeout * 1e3, len(self.intervals), self.min_samples)
            return None
        value = self.phi(silence)
        if value > self.threshold:
            mean, std = self.model()
            return 'phi %.1f > %g: next beat expected at %.1f +- %.1f ms over %d intervals' % (
                value, self.threshold, mean * 1e3, std * 1e3, len(self.intervals))
        return None
