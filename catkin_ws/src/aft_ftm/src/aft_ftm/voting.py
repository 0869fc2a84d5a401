"""Time Redundancy's decision: repeat, compare, and let a majority decide (paper Table II: TR)."""
import enum

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
