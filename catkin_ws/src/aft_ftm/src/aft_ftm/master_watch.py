"""Whether the ROS master can be reached, as a replica's Recovery sees it.

A failover needs no master (every connection it uses is opened at set-up), but without one nothing
new can start: no node, no re-join, no adaptation, no new subscription. So an unreachable master is
a degraded state: it is raised once as an alarm when ``misses`` probes in a row went unanswered
(one slow answer on a loaded machine is not a dead master), again every ``repeat`` seconds while it
lasts, and said when it is back. ``now`` is passed in: no ROS here.
"""
import enum


class MasterState(enum.Enum):
    UNKNOWN = 'not probed yet'
    REACHABLE = 'the master answers'
    UNREACHABLE = 'the master does not answer'


class Decision(enum.Enum):
    NOTHING = 'nothing to say'
    ALARM = 'raise (or repeat) the alarm master_unreachable'
    BACK = 'the master answers again: say so'


# (state, probe answered?) -> (next state, why). Each probe result is one edge; an unanswered probe
# follows its edge only once ``misses`` probes in a row went unanswered (before that, the state stays).
EDGES = {
    (MasterState.UNKNOWN, True): (MasterState.REACHABLE, 'first probe answered'),
    (MasterState.UNKNOWN, False): (MasterState.UNREACHABLE, 'the first probes unanswered'),
    (MasterState.REACHABLE, True): (MasterState.REACHABLE, 'still answers'),
    (MasterState.REACHABLE, False): (MasterState.UNREACHABLE, 'stopped answering'),
    (MasterState.UNREACHABLE, True): (MasterState.REACHABLE, 'answers again'),
    (MasterState.UNREACHABLE, False): (MasterState.UNREACHABLE, 'still unanswered'),
}


class MasterWatch(object):
    """The master's state from periodic probes; alarms throttled to one per ``repeat`` seconds."""

    def __init__(self, repeat=60.0, misses=2):
        if repeat <= 0:
            raise ValueError('repeat must be > 0 s, not %r' % (repeat,))
        if misses < 1:
            raise ValueError('misses must be >= 1, not %r' % (misses,))
        self.repeat = repeat
        self.misses = misses
        self.missed = 0          # unanswered probes in a row
        self.first_miss = None   # when the first of them was made
        self.state = MasterState.UNKNOWN
        self.since = None        # when the current state began
        self.last_alarm = None
        self.error = ''

    def probe(self, answered, now, error=''):
        """Record one probe; returns the Decision for the caller to carry out."""
        before = self.state
        self.missed = 0 if answered else self.missed + 1
        if self.missed == 1:
            self.first_miss = now
        if answered or self.missed >= self.misses:
            self.state = EDGES[(before, bool(answered))][0]
        if self.state != before:
            self.since = self.first_miss if self.state == MasterState.UNREACHABLE else now
        self.error = '' if answered else error
        if self.state == MasterState.UNREACHABLE:
            if self.last_alarm is None or now - self.last_alarm >= self.repeat:
                self.last_alarm = now
                return Decision.ALARM
            return Decision.NOTHING
        self.last_alarm = None
        return Decision.BACK if before == MasterState.UNREACHABLE else Decision.NOTHING

    def unreachable_for(self, now):
        """Seconds the master has been unreachable, or None if it is not (or not known to be)."""
        return now - self.since if self.state == MasterState.UNREACHABLE else None
