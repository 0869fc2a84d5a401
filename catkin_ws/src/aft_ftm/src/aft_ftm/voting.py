"""Time Redundancy's decision: repeat, compare, and let a majority decide (paper Table II: TR)."""
import collections
import enum
import time

from .errors import ConfigError


class Outcome(enum.Enum):
    REPEAT = 0        # not decided yet: restore the state and execute again
    DECIDED = 1       # a value reached the quorum (it is always the last result, so the server's
                      # current state is the one that produced it)
    NO_MAJORITY = 2   # every execution was used and no value reached the quorum


class Vote(object):
    """The verdict on one request. ``masked`` counts the executions that disagreed with the winner."""
    __slots__ = ('outcome', 'value', 'masked', 'executions')

    def __init__(self, outcome, value=None, masked=0, executions=0):
        self.outcome = outcome
        self.value = value
        self.masked = masked
        self.executions = executions

    def __repr__(self):
        return 'Vote(%s, masked=%d, executions=%d)' % (self.outcome.name, self.masked, self.executions)


class TimeRedundancyVote(object):
    """At most ``executions`` executions per request; a value decides once it reaches the quorum
    (a majority of executions). With 3, two agreeing executions decide and a third breaks a tie."""

    def __init__(self, executions=3):
        if isinstance(executions, bool) or not isinstance(executions, int) or executions < 2:
            raise ConfigError('time redundancy needs at least 2 executions, got %r' % (executions,))
        self.executions = executions
        self.quorum = executions // 2 + 1
        self._results = {}

    def add(self, key, result, execution=None):
        """Record one execution's result (any comparable value) for request key; returns a Vote.
        ``execution``, the execution's number where known: a second result of one execution (a
        duplicated message) is not counted again, and None is returned for it (review of session 34:
        one corrupted execution delivered twice decided the vote)."""
        results = self._results.setdefault(key, [])
        if execution is not None and any(e == execution for e, _ in results):
            return None
        results.append((execution, result))
        agreeing = sum(1 for _, r in results if r == result)
        if agreeing >= self.quorum:
            del self._results[key]
            return Vote(Outcome.DECIDED, result, len(results) - agreeing, len(results))
        if len(results) >= self.executions:
            del self._results[key]
            return Vote(Outcome.NO_MAJORITY, None, 0, len(results))
        return Vote(Outcome.REPEAT, None, 0, len(results))

    def forget(self, key):
        """Stop voting on request key (it cannot be executed again): its results are dropped."""
        self._results.pop(key, None)

    def pending(self):
        return len(self._results)


class Stray(enum.Enum):
    """Why TR's After does not count an execution's result: it is not the one outstanding (Votes).
    COUNTED: a copy of a result. NOT_ASKED: ahead of the execution outstanding, past ~executions, or
    not the first execution of an attempt whose vote has not begun. ENDED: a copy, or an execution run
    after its vote gave up (Before stopped past ~repeat_timeout, then resumed). EARLIER: a late result
    of an earlier attempt (or of one a newer attempt superseded). OTHER_ATTEMPT: a vote runs on another
    attempt of the request, and has not waited for its execution long enough to be superseded."""
    COUNTED = 'counted already'
    NOT_ASKED = 'not asked for'
    ENDED = 'its vote has ended'
    EARLIER = 'of an attempt older than the last one voted on'
    OTHER_ATTEMPT = 'the vote running is on another attempt, and not stuck'


class Votes(object):
    """TR's After's votes: for each request (its origin and id) one vote at a time, on one attempt,
    and in it one execution outstanding, the only result counted.

    Before numbers the executions of an attempt 0, 1, ... and executes the next only once After,
    having counted the one before, asks for it (a repeat). So the execution outstanding is the number
    of results counted in the vote running, or execution 0 of a new vote. A vote begins on an attempt
    newer than the last one voted on (an outer mechanism numbers its executions upward). One vote runs
    per request (Before's saved state and its repeat are per request, not per attempt): a newer
    attempt's result is refused while the vote running still waits for its execution, but once that
    vote is stuck (no execution counted for ``stale_after`` s: its result lost, Before restarted), the
    newer attempt's execution 0 supersedes it and its results are dropped. Before replaces the saved
    state of an attempt whose vote never ended by the newer one's; refused for ever, the newer attempt
    left the request unanswerable, every retry refused (review of the first version). Any
    other result (a copy, one of an earlier attempt or of a vote that ended, a number forged or
    published again by anyone on the graph) is refused with its reason (Stray): counted, one not
    asked for decided the vote with a value the server never computed, and the execution asked for,
    when it came, was dropped as a copy (outside review).

    After hears of an attempt only from its results: the first execution 0 heard begins the vote. A
    forged one of another attempt heard before the true one takes the vote (the true results are then
    refused, and the request is left to the Protocol's timeout, whose request is of the true attempt).
    Telling who may publish on the graph is SEC's work.

    The last ``remember`` requests are remembered (their last attempt, and whether its vote runs);
    the oldest is forgotten first (a running vote with it)."""

    def __init__(self, executions=3, remember=65536, stale_after=10.0, clock=time.monotonic):
        self.vote = TimeRedundancyVote(executions)
        self.remember = remember
        self.stale_after = stale_after
        self.clock = clock
        self._requests = collections.OrderedDict()   # request -> [its last attempt, execution outstanding
        #                                              (None: its vote has ended), when it last counted one]

    def add(self, request, attempt, execution, result):
        """The result of ``execution`` of ``request``'s ``attempt``: (its Vote, None) if it was the one
        outstanding, and counted; else (None, the Stray reason) and nothing changes."""
        now = self.clock()
        stray = self._stray(self._requests.get(request), attempt, execution, now - self.stale_after)
        if stray is not None:
            return None, stray
        last = self._requests.get(request)
        if last is not None and last[1] is not None and attempt != last[0]:   # a newer attempt supersedes it
            self.vote.forget(request + (last[0],))
        vote = self.vote.add(request + (attempt,), result, execution)
        self._requests[request] = [attempt, execution + 1 if vote.outcome == Outcome.REPEAT else None, now]
        self._requests.move_to_end(request)
        while len(self._requests) > self.remember:
            old, (old_attempt, _, _) = self._requests.popitem(last=False)
            self.vote.forget(old + (old_attempt,))
        return vote, None

    @staticmethod
    def _stray(last, attempt, execution, stuck_before):
        """Why a result is not the one outstanding, or None. ``last``: its request's [last attempt,
        execution outstanding or None, when it counted the last], or None (not seen, or forgotten); a
        vote running that counted none since ``stuck_before`` may be superseded by a newer attempt."""
        if last is None:
            return None if execution == 0 else Stray.NOT_ASKED
        newest, outstanding, counted = last
        if outstanding is not None and (attempt <= newest or counted > stuck_before):   # a vote runs
            if attempt > newest:
                return Stray.OTHER_ATTEMPT
            if attempt < newest:
                return Stray.EARLIER
            if execution < outstanding:
                return Stray.COUNTED
            return None if execution == outstanding else Stray.NOT_ASKED
        if attempt < newest:
            return Stray.EARLIER
        if attempt == newest:
            return Stray.ENDED
        return None if execution == 0 else Stray.NOT_ASKED

    def end(self, request, attempt):
        """The vote on request's attempt ends undecided (it cannot be executed again): its results are
        dropped, and a result of it heard later is refused (Stray.ENDED)."""
        self.vote.forget(request + (attempt,))
        last = self._requests.get(request)
        if last is not None and last[0] == attempt:
            last[1] = None

    def pending(self):
        """How many votes run."""
        return self.vote.pending()
