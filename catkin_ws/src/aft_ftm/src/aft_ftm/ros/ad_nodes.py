"""Assertion & Duplex (paper Table II: Before, Compute, Assert): user safety assertions on each
request (before it is executed) and on each reply; a violation is an error reply and an alarm."""
import math
import threading
import time

import rospy
from aft_msgs.msg import Reply

from .. import assertions, config
from ..assertions import Copy
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import key
from .alarms import alarm
from .bpa_nodes import AfterNode, BeforeNode
from .deadline import CallPending, CallTimeout, Deadline
from .envelope import deserialize, service_class
from .params import param


def _app_request(request):
    return deserialize(service_class(request.service_type)._request_class, request.payload)


class BoundedRun(object):
    """Calls each assertion on a worker thread of its own and waits for it at most ``timeout`` seconds
    (``~assertion_timeout``; 0: in the caller's thread, unbounded).

    An assertion that hangs (a deadlock, a blocking call in the user's code) hung the node's thread
    with it: A&D's Before or After stopped, and every request behind it waited until the Protocol's
    timeout. Past the bound the check is a violation (assertions.Hung: the request is refused, the
    reply is not passed on) and ``on_hang(name, detail)`` is told once; the abandoned call is not
    made again while it has not returned (every check of that assertion is a violation at once,
    with the same detail, so that TR around A&D sees the same result; no thread piles up), and
    when it returns, the next check calls the assertion again.

    Checks of one assertion run one at a time, each with the whole bound: the wait for the one
    before does not count against it (review of session 39). What the assertion raises, a
    TimeoutError too, is its own verdict, never taken for the bound's."""

    def __init__(self, timeout, on_hang):
        if not (timeout >= 0 and math.isfinite(timeout) and timeout <= threading.TIMEOUT_MAX):
            raise config.ConfigError('~assertion_timeout must be a finite number of seconds >= 0 (0: unbounded), '
                                     'got %r' % (timeout,))
        self.timeout = timeout
        self.on_hang = on_hang
        self.deadlines = {}   # name -> (Deadline, the lock its checks take in turn)
        self.lock = threading.Lock()

    def __call__(self, name, fn, args):
        if not self.timeout:
            return fn(*args)
        with self.lock:
            if name not in self.deadlines:
                self.deadlines[name] = (Deadline('assertion %s' % name, exclusive=True), threading.Lock())
            deadline, turn = self.deadlines[name]
        detail = 'did not return within ~assertion_timeout (%.3f s): the check cannot be evaluated' % self.timeout
        with turn:
            try:
                outcome = deadline.call(_outcome, self.timeout, fn, args)
            except CallPending:
                raise assertions.Hung(detail)   # (its earlier call, abandoned, has not returned yet)
            except CallTimeout:
                outcome = None
        if outcome is None:   # told outside the turn: a slow alarm never delays the next check
            self.on_hang(name, detail)
            raise assertions.Hung(detail)
        raised, value = outcome
        if raised:
            raise value
        return value


def _outcome(fn, args):
    """(False, what fn(*args) returned) or (True, what it raised): an assertion's own exception, a
    TimeoutError too, is handed back as a value, not taken by Deadline for its own timeout. A
    SystemExit or other BaseException is a RuntimeError naming it: a violation, as any exception."""
    try:
        return False, fn(*args)
    except Exception as e:
        return True, e
    except BaseException as e:
        return True, RuntimeError('raised %s: %s' % (type(e).__name__, e))


def _bounded_run(node, mechanism):
    """The node's BoundedRun: ~assertion_timeout (float >= 0, default 1 s), its hangs alarmed
    ``assertion_hangs``."""
    def on_hang(name, detail):
        alarm(node.ports, mechanism, 'assertion_hangs', 'assertion %s %s; it is not called again until that call '
              'returns, and every check of it meanwhile is a violation' % (name, detail))
    return BoundedRun(param('assertion_timeout', config.non_negative_float, 1.0), on_hang)


def _error(msg, detail):
    return Reply(id=msg.id, origin=msg.origin, client=msg.client, oldest_pending=msg.oldest_pending,
                 attempt=msg.attempt, batch=msg.batch, status=Reply.ERROR, error=detail)


class AdBeforeNode(BeforeNode):
    """A&D's Before: checks the request assertions before the request is executed, and gives
    After the request so that reply assertions can look at both.

    Each request (origin, id, attempt) is executed once: a second copy (a publisher heard on two
    connections across a rebind, a message published again on pro2bfr, a Protocol started again) is
    refused with the alarm ``duplicate_request``, as TR's Before refuses one. A copy of a request
    refused gets that refusal again; a copy of one passed on is given to After only, which answers it
    with the first copy's checked reply (again, or once it comes: one answer for both); a copy heard
    while the first is checked gets nothing (the first's outcome answers it). The last 65 536
    requests are remembered (assertions.Copies); an older copy would be checked and executed again.

    Parameters: ~request_assertions (list of package.module:function, default none); ~reply_assertions
        (the After's, read here only to refuse an A&D that checks nothing: both lists empty is a
        ConfigError, not a mechanism that passes everything; review of session 34);
        ~assertion_timeout (float >= 0, default 1 s; 0: unbounded): the longest one assertion may
        take; past it the request is refused (BoundedRun, alarm ``assertion_hangs``)
    Subscribes: pro2bfr (aft_msgs/Request), port ``inp``.
    Publishes: bfr2prd (aft_msgs/Request), port ``out``; bfr2aft (aft_msgs/Request), port ``to_after``;
        aft2pro (aft_msgs/Reply), port ``errors``: refused requests; alarms (aft_msgs/Alarm), port ``alarms``.
    Services: ~rebind (aft_msgs/Rebind)
    """
    MECHANISM = 'ad'
    WAIT_OUTPUTS = ('to_after', 'errors')

    def __init__(self):
        self.checks = assertions.load_all(param('request_assertions', config.name_list, []),
                                          rospy.resolve_name('~request_assertions'))
        if not self.checks and not param('reply_assertions', config.name_list, []):
            raise config.ConfigError('%s: Assertion & Duplex with no assertion at all (~request_assertions and '
                                     '~reply_assertions both empty) would check nothing: name at least one '
                                     '(package.module:function)' % rospy.get_name())
        super(AdBeforeNode, self).__init__(extra_ports=[PortSpec('to_after', PUBLISH, 'aft_msgs/Request'),
                                                        PortSpec('errors', PUBLISH, 'aft_msgs/Reply'),
                                                        PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')])
        self.run = _bounded_run(self, 'ad')
        self.lock = threading.Lock()
        self.copies = assertions.Copies()

    def setup(self, timeout):
        self.ports.bind('to_after', 'bfr2aft')
        self.ports.bind('errors', 'aft2pro')
        self.ports.bind('alarms')
        return super(AdBeforeNode, self).setup(timeout)

    def handle(self, request):
        once = key(request)
        with self.lock:   # taken before it is checked: two copies heard at once do not both pass
            copy, refusal = self.copies.take(once)
            copies = self.copies.copies
        if copy is not Copy.FIRST:
            return self._copy(request, copy, refusal, copies)
        refusal = self._refusal(request) if self.checks else None
        with self.lock:
            self.copies.checked(once, refusal)
        if refusal is not None:
            self.ports.publish('errors', refusal)
            return None
        self.ports.publish('to_after', request)
        return request

    def _refusal(self, request):
        """The error reply refusing request (alarmed), or None if no request assertion is violated."""
        try:
            violations = assertions.check(self.checks, _app_request(request), run=self.run)
        except Exception as e:   # undecodable request: refused, not executed
            violations = [('decoding', str(e))]
        if not violations:
            return None
        detail = '; '.join('request assertion %s violated: %s' % v for v in violations)
        alarm(self.ports, 'ad', 'assertion_violated', detail, request)
        return _error(request, detail)

    def _copy(self, request, copy, refusal, copies):
        """A second copy of a request this Before took: never checked or executed again."""
        if copy == Copy.CHECKING:
            outcome = 'its first copy is being checked, and its outcome answers it'
        elif copy == Copy.PASSED:
            outcome = 'After answers it with the first copy\'s checked reply'
        else:
            outcome = 'its refusal given again' if refusal is not None else 'its refusal was forgotten: no answer'
        alarm(self.ports, 'ad', 'duplicate_request', '%s/%d (attempt %d) refused: taken by this Before already; a '
              'second copy is not executed (%d refused so far); %s' % (
                  request.origin, request.id, request.attempt, copies, outcome), request)
        if copy == Copy.PASSED:
            self.ports.publish('to_after', request)
        elif refusal is not None:
            self.ports.publish('errors', refusal)
        return None


class AdAfterNode(AfterNode):
    """A&D's After: checks the reply assertions on (request, response); a violated assertion turns
    the reply into an error reply and raises an alarm. It never lets an unchecked reply through.

    A reply whose request does not come within ~request_wait (this After started again after Before
    passed the request on) is never passed on unchecked: it is answered with an error, "outcome
    unknown" (the server ran it; its reply could not be shown safe), with the alarm ``unchecked_reply``.
    It was dropped, and the Protocol, which runs one request at a time, waited for it for good: no
    client was answered again (review of session 36). A request whose reply never comes is kept, at
    most ~max_waiting; past that the oldest is forgotten with the alarm ``request_forgotten`` (its
    reply, if it comes, is then answered as above) (assertions.Pairing).

    A request that comes again once answered (a copy, which Before gives to After only, never to
    execute) gets the same answer again: the last 4 096 answers are kept, as far as 8 MiB of their
    payloads allow (one forgotten: no answer, and a warning in the log). A copy of a request whose
    reply has not come waits with it: the reply answers both, once. A copy of a reply answered already
    is ignored (with a warning in the log), not answered again as "outcome unknown".

    Parameters: ~reply_assertions (list of package.module:function, default none);
        ~request_wait (float, 5 s); ~max_waiting (int, 10000); ~assertion_timeout (float >= 0, default
        1 s; 0: unbounded): the longest one assertion may take; past it the reply is answered as a
        violation (BoundedRun, alarm ``assertion_hangs``)
    Subscribes: prd2aft (aft_msgs/Reply), port ``inp``; bfr2aft (aft_msgs/Request), port ``requests``.
    Publishes: aft2pro (aft_msgs/Reply), port ``out``; alarms (aft_msgs/Alarm), port ``alarms``.
    Services: ~rebind (aft_msgs/Rebind)
    """
    MECHANISM = 'ad'

    def __init__(self):
        self.checks = assertions.load_all(param('reply_assertions', config.name_list, []),
                                          rospy.resolve_name('~reply_assertions'))
        super(AdAfterNode, self).__init__(extra_ports=[PortSpec('requests', SUBSCRIBE, 'aft_msgs/Request'),
                                                       PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
                                          extra_callbacks={'requests': self._on_request})
        self.lock = threading.Lock()
        self.pairing = assertions.Pairing(param('request_wait', config.positive_float, 5.0),
                                          param('max_waiting', config.positive_int, 10000))
        self.run = _bounded_run(self, 'ad')

    def setup(self, timeout):
        self.ports.bind('requests', 'bfr2aft')
        self.ports.bind('alarms')
        if not super(AdAfterNode, self).setup(timeout):
            return False
        rospy.Timer(rospy.Duration(min(1.0, self.pairing.wait / 2.0)), self._sweep)
        return True

    def _on_request(self, request):
        k = key(request)
        with self.lock:
            again, answer = self.pairing.again(k)
            reply, evicted = (None, None) if again else self.pairing.request(k, request)
        if again:   # a copy of a request answered already (Before executed it once)
            if answer is not None:
                self.ports.publish('out', answer)
            else:
                rospy.logwarn('%s: %s/%d (attempt %d) came again, answered already; its answer is no longer kept: '
                              'none given', self.name, request.origin, request.id, request.attempt)
            return
        if evicted is not None:
            alarm(self.ports, 'ad', 'request_forgotten', 'request %s/%d forgotten unanswered: %d requests wait for '
                  'their replies (~max_waiting); its reply, if it comes, is not passed on unchecked'
                  % (evicted.origin, evicted.id, self.pairing.max_requests), evicted)
        if reply is not None:
            self.ports.publish('out', self._answered(self._checked(request, reply)))

    def handle(self, reply):
        k = key(reply)
        with self.lock:
            again, _ = self.pairing.again(k)
            request = None if again else self.pairing.reply(k, reply, time.monotonic())
        if again:   # parked, it would have been answered again, "outcome unknown", past ~request_wait
            rospy.logwarn('%s: the reply to %s/%d (attempt %d) came again, answered already: ignored', self.name,
                          reply.origin, reply.id, reply.attempt)
            return None
        if request is None:
            return None   # checked when its request arrives
        return self._answered(self._checked(request, reply))

    def _answered(self, answer):
        """Keep answer, which After gives now: a copy of its request gets it again."""
        with self.lock:
            self.pairing.answer(key(answer), answer)
        return answer

    def _sweep(self, _event):
        with self.lock:
            expired = self.pairing.expired(time.monotonic())
        for reply in expired:
            detail = ('the reply to %s/%d came, but its request did not within %.1f s (this After started again '
                      'after Before passed it on?): it cannot be checked' % (reply.origin, reply.id, self.pairing.wait))
            alarm(self.ports, 'ad', 'unchecked_reply', detail + '; answered "outcome unknown"', reply)
            self.ports.publish('out', self._answered(_error(reply, 'outcome unknown: ' + detail)))

    def _checked(self, request, reply):
        if reply.status != Reply.OK or not self.checks:
            return reply
        try:
            cls = service_class(request.service_type)
            args = (deserialize(cls._request_class, request.payload), deserialize(cls._response_class, reply.payload))
            violations = assertions.check(self.checks, *args, run=self.run)
        except Exception as e:   # an undecodable reply cannot be shown safe
            violations = [('decoding', str(e))]
        if not violations:
            return reply
        detail = '; '.join('reply assertion %s violated: %s' % v for v in violations)
        alarm(self.ports, 'ad', 'assertion_violated', detail, reply)
        # The server ran the request (its state may have changed): not "an error, nothing changed", which
        # a client may retry, applying it twice (review of session 48).
        return _error(reply, 'executed, its reply withheld (outcome unknown to the client): %s' % detail)
