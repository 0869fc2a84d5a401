"""Sensor-value fault tolerance of the TJP (second paper, Fig. 6), without rospy.

- :class:`SlidingAverage`: the IMU speed, averaged over a sliding window, with time redundancy:
  a reading far from the window's median is a transient value fault, masked (not averaged in) and
  counted, unless the readings keep disagreeing (then the speed really changed: the window follows).
- :func:`vote`: three lasers measure the gap; the value at least two agree on (within a
  tolerance) wins and a disagreeing laser is named; with no two agreeing there is no majority.
- :class:`LaserVoter`: the readings of the three lasers grouped by sensing instant, a silent
  (crashed) laser noticed, and each group voted.
"""
import collections
import math

from .errors import TjpConfigError


class SlidingAverage(object):
    """Mean of the last ``size`` accepted readings; outliers (farther than ``tolerance`` from the
    window's median) are masked unless ``persist`` of them in a row agree with each other. A
    reading that is not a finite number is always masked (NaN compares false with everything: it
    entered the window and the mean was NaN until it left). Each time the window follows a
    lasting change, ``followed`` counts it and ``jump`` holds (from, to): a collision, or a stuck or
    offset sensor that the window cannot tell from one; the node says so (review, stop 39).

    Readings that are not finite numbers ``persist`` times in a row are not masked any longer: the
    window, no measure of the speed by then, is dropped, :meth:`add` returns None until a finite
    reading comes, and ``given_up`` counts each such run (a sensor sending NaN for good had the
    window's last mean passed on as its speed for as long as it lasted; review of session 34).

    Finite readings masked ``2 * persist`` times in a row (far from the window and not agreeing with
    each other: an IMU giving garbage) end the masking the same way: the window is dropped, ``given_up``
    counts it, and :meth:`add` returns None until ``persist`` readings in a row agree again (the
    window starts from them). ``why`` says which. Masked for ever, the window's last mean was passed on
    as the speed while the car sped up (2 m/s at 10: a safety distance of 5 m for 17; review of
    session 48)."""

    def __init__(self, size=5, tolerance=1.0, persist=3):
        if isinstance(size, bool) or not isinstance(size, int) or size < 1:
            raise TjpConfigError('window size must be an integer >= 1, got %r' % (size,))
        if not isinstance(tolerance, (int, float)) or isinstance(tolerance, bool) or not tolerance > 0:
            raise TjpConfigError('tolerance must be a number > 0, got %r' % (tolerance,))
        if isinstance(persist, bool) or not isinstance(persist, int) or persist < 2:
            raise TjpConfigError('persist must be an integer >= 2, got %r' % (persist,))
        self.size, self.tolerance, self.persist = size, float(tolerance), persist
        self.window = collections.deque(maxlen=size)
        self.suspects = []
        self.masked = 0
        self.followed = 0
        self.jump = None
        self.invalid_run = 0   # readings not finite numbers, in a row
        self.masked_run = 0    # finite readings masked, in a row
        self.doubtful = False  # given up on finite garbage: nothing given until persist readings agree
        self.given_up = 0
        self.why = ''          # why the masking was given up last

    def _median(self):
        values = sorted(self.window)
        mid = len(values) // 2
        return values[mid] if len(values) % 2 else values[mid - 1] / 2.0 + values[mid] / 2.0

    def add(self, value):
        """Take a reading; returns (filtered value, masked: whether this reading was masked)."""
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self.invalid_run += 1
            if self.invalid_run < self.persist and self.window:
                self.masked += 1
                return self.value(), True
            if self.window or self.invalid_run == self.persist:
                self.given_up += 1
                self.why = 'not a number %d times in a row' % self.invalid_run
            self.window.clear()
            self.suspects = []
            self.masked_run = 0   # (still doubtful if it was: one NaN amid garbage must not seed the window)
            return None, False
        self.invalid_run = 0
        if self.doubtful:
            self.suspects = (self.suspects + [value])[-self.persist:]
            if len(self.suspects) == self.persist and max(self.suspects) - min(self.suspects) <= 2 * self.tolerance:
                self.window.clear()
                self.window.extend(self.suspects)
                self.suspects, self.doubtful = [], False
                return self.value(), False
            return None, False
        if self.window and abs(value - self._median()) > self.tolerance:
            self.suspects = (self.suspects + [value])[-self.persist:]
            if len(self.suspects) == self.persist and max(self.suspects) - min(self.suspects) <= 2 * self.tolerance:
                # They agree among themselves: the speed really changed. Follow it; the earlier
                # ones, counted as masked, were not faults after all.
                self.masked -= self.persist - 1
                self.followed += 1
                self.jump = (self.value(), _mean(self.suspects))
                self.window.clear()
                self.window.extend(self.suspects)
                self.suspects = []
                self.masked_run = 0
                return self.value(), False
            self.masked += 1
            self.masked_run += 1
            if self.masked_run >= 2 * self.persist:
                self.given_up += 1
                self.why = ('%d readings in a row far from the window and from each other (%.2f to %.2f m/s)'
                            % (self.masked_run, min(self.suspects), max(self.suspects)))
                self.window.clear()
                self.masked_run, self.doubtful = 0, True
                return None, False
            return self.value(), True
        self.suspects = []
        self.masked_run = 0
        self.window.append(value)
        return self.value(), False

    def value(self):
        return _mean(self.window) if self.window else None


def _mean(values):
    """The mean of finite values, finite too (the sum of readings near the float's limit was inf)."""
    return sum(v / len(values) for v in values)


Vote = collections.namedtuple('Vote', 'value faulty ok')   # faulty: indexes of disagreeing sensors


def vote(values, tolerance=0.2):
    """Majority of three (or more) readings: the mean of the largest group agreeing within
    tolerance, if it is a majority; ``faulty`` lists the others. ok=False: no majority."""
    readings = [(i, v) for i, v in enumerate(values) if v is not None]
    best = []
    for _, anchor in readings:
        group = [(i, v) for i, v in readings if abs(v - anchor) <= tolerance]
        if len(group) > len(best):
            best = group
    if 2 * len(best) <= len(values):
        return Vote(None, [], False)
    members = {i for i, _ in best}
    return Vote(sum(v for _, v in best) / len(best), [i for i in range(len(values)) if i not in members], True)


class LaserVoter(object):
    """Groups the three lasers' readings of one sensing instant (same stamp) and votes on each group.

    Each laser's readings may arrive late or out of order relative to the others' (each topic has
    its own connection and thread). A group is decided once every laser gave its reading for it,
    or once every missing laser has already sent a later reading (it skipped this instant), or once
    ``max_lag`` later instants are waiting (a crashed laser never sends again). A missing laser counts
    as missing: two agreeing lasers still make a majority of three. A laser missing from
    ``silent_after`` decided instants in a row is reported silent (crashed) once. A reading of an
    instant already decided is late: counted in ``late``, not voted.

    "Nothing in range" (None) from a laser that answered is a reading like any other: it agrees with
    another None. Only lasers that gave a reading can be named faulty. A reading that is not a number
    (NaN, REP 117's invalid reading) is counted in ``invalid`` and votes as a missing one: two of them
    never outvote a good laser (they were taken for "nothing in range" and agreed, review of stop 39),
    and a laser that gives nothing else is reported silent.

    A reading stamped more than ``reset_after`` before the last instant voted, while the reader's own
    clock went back too (``clock``, given to ``add``, is before that instant: a /clock reset), starts
    the vote afresh, counted in ``resets`` (review of session 34: every reading was late from then on,
    nothing voted again, and only a throttled log said so). None: never. With the reader's clock going
    on (or not given), such a reading is old, not new: a replayed or delayed one. It is refused and
    counted in ``stale`` (and ``late``): two lasers replaying readings of 3 s before voted them in as
    fresh, a gap that was no more, under a ``clock_reset`` alarm (review of session 36).

    A reading stamped 0 (unset, by ROS convention) names no instant: it is refused, counted per laser
    in ``unstamped``, and ``add`` says so once per laser, again only after ``silent_after`` stamped
    ones in a row (its caller raises an alarm: a laser switching back and forth is not told at
    every switch). The other
    lasers vote without it, as without a crashed one. It was voted as the instant 0 once, then every
    later one was late: nothing was voted again, and only a throttled log said so (review of session 34).

    A reading stamped more than ``ahead_max`` (in the stamps' units; None: no bound) after the reader's
    own clock is refused and counted in ``ahead``: taken, one laser's readings stamped ahead made the
    good lasers' readings late, and nothing was voted until the clock caught up (review of session 48).
    """

    NOTHING = 1e9   # stands for "nothing in range" in the vote
    INVALID = object()   # an invalid reading of one instant: the laser answered, with no value
    UNSTAMPED = type('Unstamped', (tuple,), {})()   # add's answer to a laser's first unstamped reading (empty)

    def __init__(self, count=3, tolerance=0.2, silent_after=5, max_lag=2, reset_after=None, ahead_max=None):
        self.count, self.tolerance, self.silent_after, self.max_lag = count, tolerance, silent_after, max_lag
        self.reset_after = reset_after
        self.ahead_max = ahead_max
        self.ahead = 0
        self.resets = 0
        self.stale = 0
        self.clock_seen = None   # the reader's clock at the newest reading taken (a reset: it goes back)
        self.groups = {}             # stamp -> {index: value}
        self.latest = [None] * count  # the newest stamp heard from each laser
        self.decided_up_to = None
        self.missing_in_a_row = [0] * count
        self.reported_silent = set()
        self.voted = 0
        self.late = 0
        self.invalid = 0
        self.unstamped = [0] * count
        self.unstamped_told = [False] * count
        self.stamped_run = [0] * count   # stamped readings in a row, per laser

    def add(self, index, stamp, value, clock=None):
        """A reading (value None: nothing in range); ``clock``: the reader's own time now, in the units
        of the stamps. Returns [(stamp, Vote, newly_silent), ...] for every group decided by it, oldest
        first; for a reading stamped 0, the first of that laser, UNSTAMPED (else [])."""
        if not 0 <= index < self.count:
            raise TjpConfigError('laser index %r outside 0 .. %d' % (index, self.count - 1))
        if not stamp:
            self.unstamped[index] += 1
            self.stamped_run[index] = 0
            if self.unstamped_told[index]:
                return []
            self.unstamped_told[index] = True
            return self.UNSTAMPED
        if clock and self.ahead_max is not None and stamp > clock + self.ahead_max:
            self.ahead += 1
            return []
        self.stamped_run[index] += 1
        if self.stamped_run[index] >= self.silent_after:   # stamped for a while: told again if it relapses
            self.unstamped_told[index] = False
        if self.decided_up_to is not None and stamp <= self.decided_up_to:
            if self.reset_after is None or self.decided_up_to - stamp <= self.reset_after:
                self.late += 1
                return []
            # A reset only if the reader's own clock went back since the last reading taken (compared with
            # the stamp, a replayed reading in a moment the clock lagged passed for one; review of session 36).
            if not clock or self.clock_seen is None or clock >= self.clock_seen:   # the clock went on: old
                self.late += 1
                self.stale += 1
                return []
            self.resets += 1    # the clock went back: afresh (the missing counts go on: a silent laser stays so)
            self.groups.clear()
            self.latest = [None] * self.count
            self.decided_up_to = None
        if clock:
            self.clock_seen = clock
        if value is not None and not (isinstance(value, (int, float)) and value == value):
            self.invalid += 1
            value = self.INVALID
        self.groups.setdefault(stamp, {})[index] = value
        if self.latest[index] is None or stamp > self.latest[index]:
            self.latest[index] = stamp
        decided = []
        while self.groups:
            when = min(self.groups)
            group = self.groups[when]
            missing = [i for i in range(self.count) if i not in group]
            skipped = all(self.latest[i] is not None and self.latest[i] > when for i in missing)
            waiting = sum(1 for t in self.groups if t > when)
            if missing and not skipped and waiting < self.max_lag:
                break
            del self.groups[when]
            self.decided_up_to = when
            decided.append(self._decide(when, group))
        return decided

    def _decide(self, stamp, group):
        newly_silent = []
        group = {i: v for i, v in group.items() if v is not self.INVALID}
        for i in range(self.count):
            if i in group:
                self.missing_in_a_row[i] = 0
                self.reported_silent.discard(i)
            else:
                self.missing_in_a_row[i] += 1
                if self.missing_in_a_row[i] >= self.silent_after and i not in self.reported_silent:
                    self.reported_silent.add(i)
                    newly_silent.append(i)
        values = [None if i not in group else (self.NOTHING if group[i] is None else group[i])
                  for i in range(self.count)]
        result = vote(values, self.tolerance)
        self.voted += 1
        value = None if result.value is None or result.value >= self.NOTHING else result.value
        return stamp, Vote(value, [i for i in result.faulty if i in group], result.ok), newly_silent
