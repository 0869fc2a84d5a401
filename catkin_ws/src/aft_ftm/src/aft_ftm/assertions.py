"""Assertion & Duplex: user safety assertions, named in configuration and loaded at start.

An assertion is an importable callable, named ``package.module:function``:
  * a request assertion is called as f(request) before the request is executed;
  * a reply assertion is called as f(request, response) on each reply.
It passes by returning True or None (or anything true, such as numpy.True_); it is violated by
returning a string (the detail) or anything false (False, numpy.False_, 0, an empty list), or by
raising AssertionError; a value whose truth cannot be told (a numpy array) is a violation. Any other exception is a violation too (a safety check
that cannot be evaluated must not let a reply through).

An assertion that does not return is a violation too: ``check`` takes a ``run`` that calls each
assertion with a bound (A&D's nodes: ``~assertion_timeout``), and :class:`Hung` is how ``run`` says
that an assertion did not return in time, or that its abandoned call has not returned yet.
"""
import enum
import importlib
import numbers

from .errors import AftError, ConfigError
from .once import KeptAnswers, RecentKeys


class Hung(AftError):
    """An assertion did not return within its bound, or an earlier call of it, abandoned, has not
    returned yet (it is not called again until it has): the check cannot be evaluated."""


def _unbounded(_name, fn, args):
    return fn(*args)


def load(spec):
    """Import ``module:function``; returns (spec, callable) or raises ConfigError naming the spec."""
    if not isinstance(spec, str) or spec.count(':') != 1 or not all(spec.split(':')):
        raise ConfigError('assertion %r must be named as package.module:function' % (spec,))
    module_name, attr = spec.split(':')
    try:
        module = importlib.import_module(module_name)
    except Exception as e:   # ImportError, or an error while importing the user's module
        raise ConfigError('assertion %s: cannot import %s: %s' % (spec, module_name, e))
    fn = getattr(module, attr, None)
    if fn is None:
        raise ConfigError('assertion %s: module %s has no %s' % (spec, module_name, attr))
    if not callable(fn):
        raise ConfigError('assertion %s: %s is not callable' % (spec, attr))
    return spec, fn


def load_all(specs, parameter):
    if specs is None:
        return []
    if not isinstance(specs, (list, tuple)):
        raise ConfigError('parameter %s must be a list of package.module:function, got %r' % (parameter, specs))
    return [load(s) for s in specs]


def check(assertions, *args, run=_unbounded):
    """Evaluate assertions on args; returns a list of (name, detail) for those violated.

    run(name, fn, args) calls one assertion (default: in this thread, unbounded); it raises
    :class:`Hung` for an assertion that hangs, a violation whose detail starts with ``hangs:``."""
    violations = []
    for name, fn in assertions:
        try:
            verdict = run(name, fn, args)
        except Hung as e:
            violations.append((name, 'hangs: %s' % e))
            continue
        except AssertionError as e:
            violations.append((name, str(e) or 'assertion failed'))
            continue
        except BaseException as e:   # a check that cannot be evaluated is a violation; sys.exit() in one too:
            # escaping, it dropped the request the node held with no answer (review of session 48)
            violations.append((name, 'raised %s: %s' % (type(e).__name__, e)))
            continue
        if verdict is None or verdict is True:
            continue
        if isinstance(verdict, str):
            violations.append((name, verdict))
            continue
        if _is_nan(verdict):     # bool(nan) is True: it passed (review of session 34)
            violations.append((name, 'returned nan, not a verdict'))
            continue
        try:
            passed = bool(verdict)    # numpy.bool_, 0, [] ... (numpy.all() returns numpy.False_, not False)
        except BaseException as e:    # an array's truth is ambiguous (or its __bool__ exits): not a verdict
            violations.append((name, 'returned %s, not a verdict: %s' % (type(verdict).__name__, e)))
            continue
        if not passed:
            violations.append((name, 'returned %r' % (verdict,)))
    return violations


def _is_nan(verdict):
    """Whether a verdict is NaN-like: a value not equal to itself (a float NaN, numpy's NaN and its 0-d
    arrays, ``Decimal('NaN')``, a complex NaN), or one that cannot even be compared with itself
    (``Decimal('sNaN')``). An int is never one (math.isnan(10**400) raised); an array's comparison is
    ambiguous, which ``bool`` then says (review of session 36: only a real float NaN was caught)."""
    if isinstance(verdict, (bool, str, numbers.Integral)):
        return False
    try:
        differs = verdict != verdict
    except ArithmeticError:   # decimal.InvalidOperation: a signalling NaN
        return True
    except BaseException:     # (one that exits: bool() below says it is no verdict)
        return False
    try:
        return bool(differs)
    except BaseException:     # an array of comparisons: not NaN, but not a verdict either (bool says so)
        return False


class Copy(enum.Enum):
    """What A&D's Before does with a request, by what it did with an earlier copy of it (Copies)."""
    FIRST = 0      # none came before: checked, and passed on to execute if it passes
    CHECKING = 1   # the first copy's request assertions run: ignored (the first's outcome answers it)
    REFUSED = 2    # the first copy was refused: that refusal again (if kept), never an execution
    PASSED = 3     # the first copy was passed on to execute: given to After only, which answers it with
    #                that execution's checked reply (again, or once it comes: Pairing.again)


class Copies(object):
    """What A&D's Before remembers so that a second copy of a request (origin, id, attempt: a publisher
    heard on two connections across a rebind, a message published again on the graph, a Protocol
    started again) is never executed: the last ``remember`` requests it took, and its refusals, as
    far as ``max_bytes`` of their text allow (a copy of one forgotten gets no answer). The caller
    holds its lock around each call: copies heard on two connections come on two threads."""

    def __init__(self, remember=65536, max_bytes=16 * 2 ** 20):
        self.taken = RecentKeys(remember)
        self.passed = RecentKeys(remember)
        self.refusals = KeptAnswers(remember, max_bytes)
        self.checking = set()   # taken, their request assertions still running
        self.copies = 0         # second copies taken

    def take(self, k):
        """A request came: (Copy, the refusal to give it again or None)."""
        if self.taken.add(k):
            self.checking.add(k)
            return Copy.FIRST, None
        self.copies += 1
        if k in self.checking:
            return Copy.CHECKING, None
        if k in self.passed:
            return Copy.PASSED, None
        return Copy.REFUSED, self.refusals.get(k)

    def checked(self, k, refusal=None):
        """The first copy of k was checked: passed on to execute (``refusal`` None), or refused."""
        self.checking.discard(k)
        if refusal is None:
            self.passed.add(k)
        else:
            self.refusals.keep(k, refusal)


class Pairing(object):
    """A&D's After checks each reply against its request, which comes on another topic (from Before)
    and so in either order. Each waits here for the other, by key.

    A reply whose request never comes (After started again after Before passed it on, or the
    request lost) was kept for ever, and only the Protocol's timeout told anything (review of session
    34). Now it waits ``wait`` seconds, then :meth:`expired` hands it back. The caller raises an
    alarm and drops it: a reply is never passed on unchecked. Requests waiting for their reply (a slow
    server) are kept, at most ``max_requests``. Past that the oldest goes, and :meth:`request` returns
    it for the caller to say so.

    After's answers are kept (:meth:`answer`): the keys of the last ``remember``, the last
    ``answers_kept`` answers as far as ``answers_bytes`` allow. A copy of a request (Before gives one to
    After only, never to execute: Copies) gets its answer again (:meth:`again`); a copy of one whose
    reply has not come pairs with it, one answer for both."""

    def __init__(self, wait=5.0, max_requests=10000, remember=65536, answers_kept=4096,
                 answers_bytes=8 * 2 ** 20):
        self.wait, self.max_requests = wait, max_requests
        self.requests = {}   # key -> request, in arrival order (dicts keep it)
        self.replies = {}    # key -> (reply, when it came)
        self.answered = RecentKeys(remember)                      # keys answered
        self.answers = KeptAnswers(answers_kept, answers_bytes)   # their answers, for a copy

    def answer(self, k, reply):
        """After answered k with reply."""
        self.answered.add(k)
        self.answers.keep(k, reply)

    def again(self, k):
        """A request came: (True, its answer if kept, else None) if k was answered already (a copy of
        the request), else (False, None)."""
        if k not in self.answered:
            return False, None
        return True, self.answers.get(k)

    def request(self, k, request):
        """A request came: returns (its reply if it came first or None, a request evicted or None)."""
        parked = self.replies.pop(k, None)
        if parked is not None:
            return parked[0], None
        self.requests[k] = request
        evicted = None
        if len(self.requests) > self.max_requests:
            evicted = self.requests.pop(next(iter(self.requests)))
        return None, evicted

    def reply(self, k, reply, now):
        """A reply came: returns its request, or None (the reply then waits for it)."""
        request = self.requests.pop(k, None)
        if request is None:
            self.replies[k] = (reply, now)
        return request

    def expired(self, now):
        """The replies that waited ``wait`` seconds or more for their request, now forgotten."""
        old = [k for k, (_, since) in self.replies.items() if now - since >= self.wait]
        return [self.replies.pop(k)[0] for k in old]
