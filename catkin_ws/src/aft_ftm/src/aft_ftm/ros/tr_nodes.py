"""Time Redundancy (paper Table II): Before saves and restores the server's state, Proceed
computes, After compares the results and a majority decides."""
import threading
import time

import rospy
from aft_msgs.msg import Reply, Request
from aft_msgs.srv import GetState, Repeat, RepeatResponse, SetState

from .. import config, health
from ..errors import ConfigError
from ..once import KeptAnswers, RecentKeys, answer_size
from ..recovery import OnHang
from ..ports import PUBLISH, PortSpec
from ..voting import Outcome, Votes
from .alarms import alarm
from .bpa_nodes import AfterNode, BeforeNode
from .deadline import CallTimeout, Deadline
from .fail_stop import fail_stop
from .params import param
from .persistent_service import PersistentService
from .peer_check import HangRule
from .witness_client import follow_site_role


# Execution k (0, 1, ...) of a request that came with attempt a goes out with attempt a * SPAN + k:
# nested Protocols see each execution as a request of its own, and After restores a.
SPAN = 100
# How Before's ~repeat says that this replica fail-stopped: After then answers nothing (the peer does).
FAIL_STOPPED = 'this replica fail-stopped: '
# How After says that Before's ~repeat did not answer within ~repeat_timeout.
NO_ANSWER = 'no answer within'
# Before keeps the answers of the last this many votes, for copies of their requests.
ANSWERS_KEPT = 4096
# After gives Before no answer larger than this (bytes of payload and error): each would cost a copy on
# every request's FORGET.
ANSWER_SENT_MAX = 64 * 1024


def execution(request, k):
    """A copy of request numbered as its k-th execution."""
    return Request(id=request.id, origin=request.origin, client=request.client,
                   service_type=request.service_type, oldest_pending=request.oldest_pending,
                   attempt=request.attempt * SPAN + k, payload=request.payload, batch=request.batch)


class TrBeforeNode(BeforeNode):
    """TR's Before: saves the server's state before each request; on After's word restores it and
    executes the request again, or forgets it.

    A state capture that does not return within ``~server_timeout`` (a hung server) leaves the
    request not executed. Outside a replica, and in a replica whose site serves alone (as Proceed:
    aft_ftm.recovery.SiteRole), the request is answered "not executed" with an alarm
    (``server_hangs``), so the client may retry; in a replica (``~site`` set) with a peer the replica
    fail-stops, as Proceed does, and its peer takes over. So does a replica whose state manager
    fails (the server died: connection refused): the failure is the replica's, not the request's,
    and its peer's server may execute the request (an LFR follower already has).

    A state restore past ``~server_timeout`` is abandoned, not cancelled: the server may still apply
    it later, rewinding the state to before its request. So until it has returned, nothing executes
    (every request is answered "not executed", the alarm ``server_hangs`` says why); when it lands, the
    request it was for is undone, as its error reply said, and the service goes on (``restore_landed``,
    or ``restore_failed`` if the server refused it: the state then holds one execution of a request
    answered as an error).

    Each request (origin, id, attempt) is executed once: the Protocol sends it once, but a second copy
    can come (a publisher heard on two connections across a rebind, or a message published again by
    anyone on the graph). In the middle of its vote it would have saved the state again, over the one
    saved before the first execution, and a repeat would restore a state holding that execution (the
    request applied twice); after its vote it would have run again. Before remembers the last 65 536
    requests it executed or answered and refuses a second copy with the alarm ``duplicate_request``
    (the Protocol sends each request once: its first copy's outcome is the one its client gets).
    A copy of a request whose vote ended gets that vote's answer again (After gives it with its
    FORGET or RESTORE): a Protocol started again, which lost the first answer, is answered, not left
    to its timeout. The last ANSWERS_KEPT answers are kept, as far as ``~answers_bytes`` (8 MiB) of
    their payloads allow; After gives none larger than ANSWER_SENT_MAX (a copy of that request gets
    no answer). "Not executed" answers are kept apart (as many as copies are refused for, at most
    16 MiB of error text): a flood of large answers never pushes them out. The answer kept is the request's
    true outcome: where After could not learn it (its RESTORE call timed out, but the restore
    went through), the client may have been told "outcome unknown" and a copy "no majority".

    Parameters:
        ~server_timeout (float, 5 s): the longest the server's get_state, or set_state before an
            execution again, may take (a set_state past it: no execution again, the same alarm or
            fail-stop; the request is answered with TR's error).
        ~site (str, default ''): the replica site this mechanism belongs to ('' : none).
        ~witness (str, default '' : none; the launch files give the replica's, one for all its nodes): the service of the witness whose configurations it
            follows in a replica ('' : none); its node's ~configuration beside it.
        ~detector (str, default /<site>/crash_detector): asked whether the peer may take over before a
            hang fail-stops the site (as Proceed's).
        ~answers_bytes (int, 8 MiB): the answers kept for copies, at most this many bytes of payload.
    Services called: get_state, set_state (the server's state manager); <detector>/peer_status.
    Subscribes: pro2bfr (aft_msgs/Request), port ``inp``; <witness>'s configuration
        (aft_msgs/Configuration), in a replica: whether its site serves alone.
    Publishes: bfr2prd (aft_msgs/Request), port ``out``; aft2pro (aft_msgs/Reply), port ``errors``:
        an error reply (not executed) when the state cannot be saved, and a copy's answer; alarms (aft_msgs/Alarm), port
        ``alarms``; fail_stop (aft_msgs/Failure), port ``fail_stop`` (in a replica).
    Services: ~repeat (aft_msgs/Repeat), ~rebind (aft_msgs/Rebind)
    """
    MECHANISM = 'tr'
    WAIT_OUTPUTS = ('errors',)

    def __init__(self):
        self.server_timeout = param('server_timeout', config.positive_float, 5.0)
        self.site = param('site', config.optional_name, '')
        self.witness = param('witness', config.witness_service, '')
        super(TrBeforeNode, self).__init__(extra_ports=[PortSpec('errors', PUBLISH, 'aft_msgs/Reply'),
                                                        PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm'),
                                                        PortSpec('fail_stop', PUBLISH, 'aft_msgs/Failure')])
        self.get_state = PersistentService('get_state', GetState)
        self.set_state = PersistentService('set_state', SetState)
        self.held = {}     # (origin, id) -> [request, state saved before it, executions sent]
        self.executed = RecentKeys()   # (origin, id, attempt) of the requests executed (a copy is refused)
        # Their answers (the vote's, told by After; "not executed", kept apart): a copy gets its answer again.
        self.answered = KeptAnswers(ANSWERS_KEPT, param('answers_bytes', config.positive_int, 8 * 2 ** 20))
        self.refused = KeptAnswers(self.executed.remember, max_bytes=16 * 2 ** 20)   # (error texts only)
        # One state operation of the server at a time (a capture, or a repeat's restore and execution):
        # each is bounded by ~server_timeout.
        self.server_lock = threading.Lock()
        self.copies = 0                # second copies refused
        self.lock = threading.Lock()
        self._deadline = Deadline('state-capture')
        self._restore_deadline = Deadline('state-restore')
        self.pending_restore = None   # (future, (origin, id)): a restore abandoned past its deadline
        self.capturing_since = None   # monotonic time the state capture in progress started
        self.failed = None            # why this replica fail-stopped: nothing more is executed
        self.hang = HangRule(self.site, param('detector', config.optional_name, '') or None)

    def setup(self, timeout):
        self.ports.bind('errors', 'aft2pro')
        self.ports.bind('alarms')
        if self.site:
            self.ports.bind('fail_stop')
        self.configuration = follow_site_role(self.hang.site_role, self.witness, report=lambda detail: alarm(self.ports, 'witness', 'forged_configuration', detail))
        self.hang.start()
        try:
            for name in ('get_state', 'set_state'):
                rospy.wait_for_service(name, timeout)
        except rospy.ROSException:
            rospy.logerr('%s: the server state manager (%s) is not available', self.name,
                         rospy.resolve_name('get_state'))
            return False
        try:
            self.get_state()   # read-only: opens the persistent connection now, not on the first request
        except (rospy.ServiceException, rospy.ROSException):
            self.get_state = self.get_state.fresh()
        try:
            self.set_state.connect()   # opened, not called: the first restore needs no master either
        except rospy.ServiceException:
            self.set_state = self.set_state.fresh()
        rospy.Service('~repeat', Repeat, self._on_repeat)
        return super(TrBeforeNode, self).setup(timeout)

    def health(self):
        since = self.capturing_since
        return health.stage(self.MECHANISM, self.STAGE, None if since is None else time.monotonic() - since,
                            self.server_timeout, self.failed, calls_server=True)

    def _restore_pending(self):
        """Why nothing may execute now (a restore abandoned past its deadline that the server may still
        apply), or None once it has returned (said once, with an alarm)."""
        with self.lock:
            pending = self.pending_restore
            if pending is None:
                return None
            future, key = pending
            if not future.done():
                return ('a restore of the server state (for %s/%d) is still pending: the server hangs, and '
                        'nothing executes until that restore has returned' % key)
            self.pending_restore = None
        try:
            result = future.result()
            failed = None if result.success else result.message
        except Exception as e:   # the call itself failed: the state may not have been restored
            failed = str(e)
        if failed is None:
            alarm(self.ports, 'tr', 'restore_landed', 'the pending restore returned: %s/%d is undone, the service '
                  'goes on' % key)
        else:
            alarm(self.ports, 'tr', 'restore_failed', 'the pending restore for %s/%d failed (%s): the server state '
                  'may hold one execution of it, though it was answered as an error' % (key + (failed,)))
        return None

    def handle(self, request):
        if self.failed:
            return None   # fail-stopped: the next primary executes it
        once = (request.origin, request.id, request.attempt)
        with self.lock:
            # Taken here, before the state is saved: two copies heard at once do not both pass. Kept
            # whatever follows: a copy of a request answered "not executed" must not execute it (its
            # client was told it did not happen: a retry under a new id would apply it twice).
            copy = not self.executed.add(once)
            if copy:
                self.copies += 1
                copies = self.copies
            elif (request.origin, request.id) in self.held:   # another attempt's vote never ended
                rospy.logwarn('%s: %s/%d attempt %d replaces the saved state of an earlier attempt whose vote never '
                              'ended', self.name, request.origin, request.id, request.attempt)
        if copy:
            with self.lock:
                answer = self.refused.get(once) or self.answered.get(once)
            alarm(self.ports, 'tr', 'duplicate_request', '%s/%d (attempt %d) refused: executed (or answered) by this '
                  'Before already; a second copy is not executed (%d refused so far)%s' % (
                      once + (copies, '; its answer given again' if answer else
                              '; no answer kept for it (its vote runs, its vote gave no answer to keep, or its '
                              'answer was too large or forgotten)')), request)
            if answer is not None:
                self.ports.publish('errors', answer)
            return None
        with self.server_lock:
            return self._capture(request)

    def _capture(self, request):
        """Save the state before request and return its first execution, or None (not executed:
        answered so, or fail-stopped)."""
        pending = self._restore_pending()
        if pending:
            alarm(self.ports, 'tr', 'server_hangs', '%s: %s/%d not executed' % (pending, request.origin, request.id))
            return self._not_executed(request, pending)
        self.capturing_since = time.monotonic()
        try:
            state = self._deadline.call(self.get_state, self.server_timeout).state
        except CallTimeout:
            problem = 'the server state manager %s did not answer within %.3f s (it hangs)' % (
                rospy.resolve_name('get_state'), self.server_timeout)
            self.get_state = self.get_state.fresh()
            if self.hang.on_hang() == OnHang.FAIL_STOP:
                self._fail_stop(problem)
                return None
            alarm(self.ports, 'tr', 'server_hangs', '%s: %s/%d not executed%s' % (
                problem, request.origin, request.id, self._alone()))
            return self._not_executed(request, problem)
        except (rospy.ServiceException, rospy.ROSException) as e:
            self.get_state = self.get_state.fresh()
            if self.site:
                # This replica's server is gone (connection refused, broken) or its state manager
                # failed: a failure of this replica, not of the request. Its peer's server may well
                # execute the request (an LFR follower already does), so "not executed" would be a
                # lie once the peer takes over: the replica fail-stops instead.
                self._fail_stop('the server state manager %s failed: %s' % (rospy.resolve_name('get_state'), e))
                return None
            return self._not_executed(request, str(e))
        finally:
            self.capturing_since = None
        with self.lock:
            # The one request of its vote: its Protocol sends the next only once this one is answered. An
            # older saved state (its vote answered "outcome unknown" when this Before did not answer in
            # time) goes: a repeat of it landing now would rewind this request (review of session 38).
            stale = [k for k in self.held if k != (request.origin, request.id)]
            for k in stale:
                del self.held[k]
            self.held[(request.origin, request.id)] = [request, state, 1]
        if stale:
            rospy.logwarn('%s: the saved states of %s dropped: their votes ended without a word to this Before '
                          '(a repeat of theirs coming late is refused)', self.name,
                          ', '.join('%s/%d' % k for k in stale))
        return execution(request, 0)

    def _alone(self):
        return (' (%s)' % self.hang.why_wait()) if self.site else ''

    def _fail_stop(self, problem):
        """This replica fail-stops: nothing more is executed or answered; its peer takes over."""
        self.failed = problem
        fail_stop(self.ports, self.site, problem, mechanism='tr')

    def _not_executed(self, request, why):
        """Answer request "not executed" (its state could not be saved, nothing ran): the client may retry.
        The answer is kept: a copy of the request gets it again (its first may have been lost with a
        Protocol that restarted), never an execution."""
        reply = Reply(id=request.id, origin=request.origin, client=request.client,
                      oldest_pending=request.oldest_pending, attempt=request.attempt, batch=request.batch,
                      status=Reply.ERROR, error='not executed: time redundancy cannot save the server state: %s' % why)
        with self.lock:
            self.refused.keep((request.origin, request.id, request.attempt), reply)
        self.ports.publish('errors', reply)
        return None

    def _on_repeat(self, req):
        # Under server_lock: a repeat of a vote that gave up, held back while this Before was stopped,
        # must not take its saved state while a new capture drops it, then restore it over the new
        # request (review of session 38).
        with self.server_lock:
            return self._repeat(req)

    def _repeat(self, req):
        key = (req.origin, req.id)
        with self.lock:
            held = self.held.get(key) if req.action == req.REPEAT else self.held.pop(key, None)
        if held is None:
            return RepeatResponse(success=False, message='no saved state for %s/%d' % key)
        request, state, sent = held
        if req.action in (req.REPEAT, req.RESTORE):
            if self.failed:
                return RepeatResponse(success=False, message=FAIL_STOPPED + self.failed)
            pending = self._restore_pending()
            if pending:
                return RepeatResponse(success=False, message='state not restored: %s' % pending)
            try:
                result = self._restore_deadline.call(self.set_state, self.server_timeout, state)
            except CallTimeout as e:
                # A hung server must not hang the vote: bounded, and never silent. The abandoned call
                # may still land: until it has, nothing executes (handle).
                with self.lock:
                    self.pending_restore = (e.future, key)
                problem = ('the server state manager %s did not restore the state within %.3f s (it hangs); '
                           'nothing executes until that restore has returned, which undoes %s/%d' % (
                               (rospy.resolve_name('set_state'), self.server_timeout) + key))
                self.set_state = self.set_state.fresh()
                if self.hang.on_hang() == OnHang.FAIL_STOP:
                    self._fail_stop(problem)
                    return RepeatResponse(success=False, message=FAIL_STOPPED + problem)
                alarm(self.ports, 'tr', 'server_hangs', '%s: %s/%d not executed again%s' % (
                    (problem,) + key + (self._alone(),)))
                return RepeatResponse(success=False, message='state not restored: %s' % problem)
            except (rospy.ServiceException, rospy.ROSException) as e:
                self.set_state = self.set_state.fresh()
                if self.site:   # this replica's failure: its peer executes the request (see handle)
                    problem = 'the server state manager %s failed: %s' % (rospy.resolve_name('set_state'), e)
                    self._fail_stop(problem)
                    return RepeatResponse(success=False, message=FAIL_STOPPED + problem)
                return RepeatResponse(success=False, message='state not restored: %s' % e)
            if not result.success:
                return RepeatResponse(success=False, message='state not restored: %s' % result.message)
        if req.action == req.REPEAT:
            held[2] += 1
            self.ports.publish('out', execution(request, sent))
        else:
            self._keep_answer(request, req.answer)
        return RepeatResponse(success=True, message='')

    def _keep_answer(self, request, answer):
        """Keep the answer After gives request's vote (with FORGET, or with a RESTORE that set the state
        back): a copy of the request gets it again."""
        if (answer.origin, answer.id, answer.attempt) != (request.origin, request.id, request.attempt):
            return   # none given (or not this request's)
        with self.lock:
            self.answered.keep((request.origin, request.id, request.attempt), answer)


class TrAfterNode(AfterNode):
    """TR's After: compares the results of repeated executions; a value that reaches a majority of
    ~executions decides; a disagreement is a transient value fault masked (alarm); no majority is
    an error reply and the state saved before the request is restored.

    TR Before out of reach (its repeat service broken: it died) is, in a replica (``~site`` set), the
    replica's failure, not the request's: an error answer would be a lie once the peer, whose TR is
    whole, executes the request (an LFR follower already has). The replica fail-stops and answers
    nothing; outside a replica the request gets TR's error.

    TR Before that does not answer within ``~repeat_timeout`` (stopped, deadlocked: its own calls
    of the server are bounded by its ``~server_timeout``) is out of reach as well: in a replica the
    replica fail-stops; outside one the request is answered "outcome unknown" (Before may still
    execute it again later: its result is then refused, the vote having ended).

    Only the execution outstanding is counted: execution 0 of a new vote, then the one After asked
    Before for (aft_ftm.voting.Votes). Any other result (a copy, one of an earlier attempt or of a vote
    that ended, one not asked for: forged, or published again by anyone on the graph) is refused with
    the alarm ``stray_execution``, its reason and the count so far, never counted in a vote.

    Parameters: ~executions (int >= 2, default 3); ~site (str, default ''): the replica site this
        mechanism belongs to ('' : none); ~server_timeout (float, 5 s): TR Before's; ~repeat_timeout
        (float, default twice ~server_timeout + 2 s): the longest Before's repeat may take (it
        restores the state first: it must exceed ~server_timeout, or the node refuses to start).
    Services called: repeat (aft_msgs/Repeat): remap to TR Before's ~repeat.
    Subscribes: prd2aft (aft_msgs/Reply), port ``inp``.
    Publishes: aft2pro (aft_msgs/Reply), port ``out``; alarms (aft_msgs/Alarm), port ``alarms``;
        fail_stop (aft_msgs/Failure), port ``fail_stop`` (in a replica).
    Services: ~rebind (aft_msgs/Rebind)
    """
    MECHANISM = 'tr'

    def __init__(self):
        executions = param('executions', config.non_negative_int, 3)
        if executions >= SPAN:
            raise ConfigError('parameter %s must be below %d, got %d' % (rospy.resolve_name('~executions'),
                                                                         SPAN, executions))
        self.site = param('site', config.optional_name, '')
        super(TrAfterNode, self).__init__(extra_ports=[PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm'),
                                                       PortSpec('fail_stop', PUBLISH, 'aft_msgs/Failure')])
        self.failed = None   # why this replica fail-stopped (TR Before out of reach): nothing more answered
        self.repeat = PersistentService('repeat', Repeat)
        server_timeout = param('server_timeout', config.positive_float, 5.0)   # (TR Before's: the same launch arg)
        self.repeat_timeout = param('repeat_timeout', config.positive_float, 2 * server_timeout + 2.0)
        if self.repeat_timeout <= server_timeout:
            raise ConfigError('parameter %s (%g s) must exceed ~server_timeout (%g s): a repeat restores the state '
                              'first, which may take that long' % (rospy.resolve_name('~repeat_timeout'),
                                                                    self.repeat_timeout, server_timeout))
        self._repeat_deadline = Deadline('repeat')
        # Each request's vote counts only the execution it asked Before for (review: any number not counted yet
        # was); a vote that waited past a repeat's bound for its execution is stuck: a newer attempt supersedes it.
        self.votes = Votes(executions, stale_after=self.repeat_timeout)
        self.vote_lock = threading.Lock()   # the votes, for results heard on several threads
        self.masked = 0
        self.strays = 0   # results refused: not the execution outstanding (alarm stray_execution)

    def setup(self, timeout):
        self.ports.bind('alarms')
        if self.site:
            self.ports.bind('fail_stop')
        try:
            rospy.wait_for_service('repeat', timeout)
        except rospy.ROSException:
            rospy.logerr('%s: TR Before\'s repeat service (%s) is not available', self.name,
                         rospy.resolve_name('repeat'))
            return False
        # Forgetting a request Before never saw changes nothing: it opens the persistent connection now.
        self._tell_before(Reply(origin='', id=0), Repeat._request_class.FORGET)
        return super(TrAfterNode, self).setup(timeout)

    def _tell_before(self, reply, action, answer=None):
        """Call Before's repeat with action for reply's request (answer: the vote's answer, which
        Before keeps for a copy of the request); returns (success, message)."""
        if answer is not None and answer_size(answer) > ANSWER_SENT_MAX:
            answer = None   # (a copy of this request gets no answer)
        try:
            result = self._repeat_deadline.call(self.repeat, self.repeat_timeout, origin=reply.origin, id=reply.id,
                                                action=action, answer=answer or Reply())
            return result.success, result.message
        except (rospy.ServiceException, rospy.ROSException, CallTimeout) as e:
            self.repeat = self.repeat.fresh()
            if isinstance(e, CallTimeout):
                e = '%s %.3f s (it hangs)' % (NO_ANSWER, self.repeat_timeout)
            if self.site:   # this replica's TR is broken: its peer executes the request
                self.failed = 'TR Before (%s) out of reach: %s' % (rospy.resolve_name('repeat'), e)
                fail_stop(self.ports, self.site, self.failed, mechanism='tr')
                return False, FAIL_STOPPED + self.failed
            return False, str(e)

    def handle(self, reply):
        if self.failed:
            return None   # fail-stopped: the peer answers
        execution = reply.attempt % SPAN
        reply.attempt //= SPAN   # back to the attempt the request came with
        request = (reply.origin, reply.id)
        with self.vote_lock:   # (copies heard on two connections come on two threads)
            vote, stray = self.votes.add(request, reply.attempt, execution,
                                         (reply.status, reply.error, bytes(reply.payload)))
            if stray is not None:
                self.strays += 1
                strays = self.strays
        if stray is not None:
            # Counted, a result not asked for could decide the vote with a value the server never computed; one
            # heard after its vote ended would ask Before to execute again a request it no longer holds.
            alarm(self.ports, 'tr', 'stray_execution', 'execution %d of %s/%d (attempt %d) refused: %s; only the '
                  'execution outstanding is counted in the vote (%d refused so far)' % (
                      execution, reply.origin, reply.id, reply.attempt, stray.value, strays), reply)
            return None
        if vote.outcome == Outcome.REPEAT:
            ok, why = self._tell_before(reply, Repeat._request_class.REPEAT)
            if ok or why.startswith(FAIL_STOPPED):   # fail-stopped: the peer answers it
                return None
            # Not executed again, and the state saved before the request not (or not surely) set back:
            # the server holds an execution the vote never confirmed. Never told as "failed, nothing
            # changed" (a retry would apply it twice); the saved state and the votes are let go.
            with self.vote_lock:
                self.votes.end(request, reply.attempt)
            detail = ('cannot execute %s/%d again (%s): the server state may hold an execution the vote did '
                      'not confirm' % (reply.origin, reply.id, why))
            answer = self._error(reply, 'outcome unknown: ' + detail)
            if not why.startswith(NO_ANSWER):   # (a hung Before is not asked again: another timeout)
                self._tell_before(reply, Repeat._request_class.FORGET, answer)
            alarm(self.ports, 'tr', 'restore_failed', detail, reply)
            return answer
        if vote.outcome == Outcome.DECIDED:
            ok, why = self._tell_before(reply, Repeat._request_class.FORGET, reply)
            if not ok and why.startswith(FAIL_STOPPED):
                return None   # fail-stopped: the peer answers it (it answered all the same; review of session 34)
            if vote.masked:
                self.masked += vote.masked
                alarm(self.ports, 'tr', 'value_fault_masked', '%d of %d executions disagreed with the majority'
                      % (vote.masked, vote.executions), reply)
            return reply
        # Before keeps this answer only if it set the state back (success): otherwise the answer differs.
        ok, why = self._tell_before(reply, Repeat._request_class.RESTORE,
                                    self._error(reply, 'no majority among %d executions' % vote.executions))
        if not ok and why.startswith(FAIL_STOPPED):
            return None
        detail = 'no majority among %d executions%s' % (vote.executions, '' if ok else
                                                         '; the state could not be restored: %s' % why)
        alarm(self.ports, 'tr', 'no_majority', detail, reply)
        # Restored, nothing changed; not restored, the state holds an execution: the outcome is unknown.
        return self._error(reply, detail if ok else 'outcome unknown: ' + detail)

    @staticmethod
    def _error(reply, detail):
        return Reply(id=reply.id, origin=reply.origin, client=reply.client, oldest_pending=reply.oldest_pending,
                     attempt=reply.attempt, batch=reply.batch, status=Reply.ERROR,
                     error='time redundancy: %s' % detail)
