"""TR's Before and After wired together without a master: a repeat that cannot run (the saved state
refused by the server's state manager) is never told as "failed, nothing changed". No ROS master."""
import collections
import os
import random
import threading
import time

import pytest

from aft_examples.history import classify_error
from aft_ftm.once import KeptAnswers, RecentKeys, answer_size
from aft_ftm.voting import Outcome, Stray, Votes
from fakes import FakeClock

tr = pytest.importorskip('aft_ftm.ros.tr_nodes')
import rospy  # noqa: E402
from aft_ftm.ros.deadline import Deadline  # noqa: E402
from aft_msgs.msg import Reply, Request  # noqa: E402
from aft_msgs.srv import GetStateResponse, Repeat, SetStateResponse  # noqa: E402


class Ports(object):
    def __init__(self):
        self.out = collections.deque()
        self.errors = []   # what Before answers itself: "not executed", or a copy's answer again

    def publish(self, port, msg):
        if port == 'out':
            self.out.append(msg)
        elif port == 'errors':
            self.errors.append(msg)


class Account(object):
    """Withdraws 10 per execution; the first execution's result is corrupted (a transient value fault)."""

    def __init__(self):
        self.balance, self.corrupt_next, self.refuse_restore = 100, True, False

    def get_state(self):
        return GetStateResponse(state=str(self.balance).encode())

    def set_state(self, state):
        if self.refuse_restore:
            return SetStateResponse(success=False, message='StateError: bad state')
        self.balance = int(bytes(state))
        return SetStateResponse(success=True, message='')

    def execute(self, request):
        self.balance -= 10
        payload = b'999' if self.corrupt_next else str(self.balance).encode()
        self.corrupt_next = False
        return Reply(id=request.id, origin=request.origin, attempt=request.attempt, payload=payload)


@pytest.fixture
def wired(monkeypatch):
    alarms = []
    monkeypatch.setattr(tr, 'alarm', lambda ports, mechanism, kind, detail, request=None: alarms.append(kind))
    server = Account()
    before = object.__new__(tr.TrBeforeNode)   # the node's state, without its ROS set-up
    before.__dict__.update(server_timeout=1.0, site='', name='/before', get_state=server.get_state, set_state=server.set_state,
                           held={}, executed=RecentKeys(), answered=KeptAnswers(), refused=KeptAnswers(), copies=0, server_lock=threading.Lock(), lock=threading.Lock(), _deadline=Deadline('c'), _restore_deadline=Deadline('r'),
                           pending_restore=None, capturing_since=None, failed=None, ports=Ports())
    after = object.__new__(tr.TrAfterNode)
    after.__dict__.update(votes=Votes(3), vote_lock=threading.Lock(), site='', failed=None, masked=0, strays=0, ports=Ports(),
                          name='/after', repeat_timeout=5.0, _repeat_deadline=Deadline('repeat'))
    after.repeat = lambda **kw: before._on_repeat(Repeat._request_class(**kw))

    def call(rid):
        answers, executions = [], collections.deque([before.handle(Request(id=rid, origin='/proxy'))])
        while executions:   # bounded: at most ~executions repeats are published
            answer = after.handle(server.execute(executions.popleft()))
            if answer is not None:
                answers.append(answer)
            executions.extend(before.ports.out)
            before.ports.out.clear()
        assert len(answers) == 1
        return answers[0]
    return server, before, after, call, alarms


def test_a_value_fault_is_masked_by_the_vote(wired):
    server, before, after, call, alarms = wired
    answer = call(1)
    assert answer.status == Reply.OK and bytes(answer.payload) == b'90' and server.balance == 90
    assert alarms == ['value_fault_masked'] and before.held == {} and after.votes.pending() == 0


def test_a_repeat_whose_state_cannot_be_restored_is_an_unknown_outcome_with_an_alarm(wired):
    """Review, stop 38: the client was told "time redundancy: cannot execute again" (an error: nothing
    changed) while the server held the unvoted execution; no alarm; the saved state and the votes
    stayed for ever (one whole server state per request)."""
    server, before, after, call, alarms = wired
    server.refuse_restore = True
    answer = call(2)
    assert answer.status == Reply.ERROR and server.balance == 90   # one execution applied
    assert classify_error('service [/account] responded with an error: ' + answer.error) == 'indeterminate'
    assert alarms == ['restore_failed'] and before.held == {} and after.votes.pending() == 0


@pytest.mark.parametrize('seed', [int(os.environ.get('AFT_SEED', 0)) or s for s in range(3801, 3831)])
def test_a_second_copy_of_a_request_is_never_executed_again(wired, seed):
    """Review of session 36 (Limits): a second copy of a request heard in the middle of its vote saved
    the state again, over the one saved before the first execution, and the repeat restored a state
    that held the first execution (the request applied twice); a copy heard after its vote ran it
    again. Copies (the Protocol sends each request once; a rebind or anyone on the graph sends more)
    come here at random points: mid-vote, after the vote, many requests later. Each request is
    answered once, with the balance it left; the server applies each once; each copy is alarmed.

    A copy of a request whose vote ended gets that vote's answer again from Before (its Protocol
    started again may have lost the first); a copy mid-vote gets none (the vote answers it). Before
    session 39 a copy of an executed request got no answer at all (Limits)."""
    server, before, after, _call, alarms = wired
    rng = random.Random(seed)
    sent, answers, copies = [], collections.defaultdict(list), 0
    for rid in range(1, 21):
        server.corrupt_next = rng.random() < 0.5       # a value fault in the first execution, or none
        request = Request(id=rid, origin='/proxy')
        sent.append(request)
        executions = collections.deque([before.handle(request)])
        while executions:   # bounded: each request has at most 3 executions, copies add none
            result = server.execute(executions.popleft())
            again = Reply(id=result.id, origin=result.origin, attempt=result.attempt, payload=result.payload)
            answer = after.handle(result)
            if answer is not None:
                answers[answer.id].append(answer)
            if rng.random() < 0.2:   # the result heard twice (mid-vote or once decided): counted once
                assert after.handle(again) is None, 'seed %d: a copy of a result answered' % seed
            while rng.random() < 0.4:   # a copy of this request (mid-vote or after) or of an older one
                copy = rng.choice(sent[-3:] if rng.random() < 0.7 else sent)
                assert before.handle(Request(id=copy.id, origin=copy.origin, attempt=copy.attempt)) is None, \
                    'seed %d: a copy of %d was executed again' % (seed, copy.id)
                copies += 1
                again = [(a.id, a.status, bytes(a.payload)) for a in before.ports.errors]
                before.ports.errors.clear()
                if copy.id in answers:   # its vote ended: the same answer again
                    first = answers[copy.id][0]
                    assert again == [(first.id, first.status, bytes(first.payload))], \
                        'seed %d: a copy of %d (answered %r) got %r' % (seed, copy.id, bytes(first.payload), again)
                else:                    # mid-vote: none (the vote answers it)
                    assert again == [], 'seed %d: a copy of %d mid-vote got %r' % (seed, copy.id, again)
            executions.extend(before.ports.out)
            before.ports.out.clear()
    assert sorted(answers) == list(range(1, 21)) and all(len(a) == 1 for a in answers.values()), 'seed %d' % seed
    balances = [int(bytes(answers[rid][0].payload)) for rid in range(1, 21)]
    assert balances == list(range(90, -110, -10)) and server.balance == -100, 'seed %d: %s' % (seed, balances)
    assert alarms.count('duplicate_request') == copies and before.copies == copies, 'seed %d' % seed
    assert 'restore_failed' not in alarms, 'seed %d' % seed
    assert before.held == {} and after.votes.pending() == 0, 'seed %d' % seed


def test_a_copy_of_a_request_answered_not_executed_is_not_executed_either(wired):
    """A request whose state could not be saved ran nowhere and was answered "not executed" (the
    Protocol keeps that answer; its client may retry under a new id). A copy of it heard later must
    not execute it: the client would hold "not executed" for a request the server applied, and its
    retry would apply it twice (review of session 38: the first version let the copy run). It gets
    the same answer again: its first may have been lost with a Protocol that restarted."""
    server, before, _after, _call, alarms = wired

    class Refused(object):   # the server's state manager fails (its server died)
        def __call__(self):
            raise rospy.ServiceException('service [/get_state] unavailable')

        def fresh(self):
            return self
    errors = []
    before.ports.publish = lambda port, msg: errors.append((port, msg.status))
    before.get_state = Refused()
    assert before.handle(Request(id=5, origin='/proxy')) is None
    assert errors == [('errors', Reply.ERROR)] and server.balance == 100
    before.get_state = server.get_state   # the server is back; a copy comes (its Protocol restarted, say)
    assert before.handle(Request(id=5, origin='/proxy')) is None
    assert errors == [('errors', Reply.ERROR)] * 2 and server.balance == 100 and alarms == ['duplicate_request']


class HungBefore(object):
    """TR Before's repeat service, stopped until ``go`` is set (SIGSTOP, a deadlock)."""

    def __init__(self, before):
        self.before, self.go, self.done, self.calls, self.answer = before, threading.Event(), threading.Event(), [], None

    def __call__(self, **kw):
        self.calls.append(kw['action'])
        self.go.wait(10.0)
        self.answer = self.before._on_repeat(Repeat._request_class(**kw))
        self.done.set()
        return self.answer

    def fresh(self):
        return self


def test_a_hung_before_is_not_waited_for_ever_the_request_s_outcome_is_unknown(wired):
    """Review of session 36 (Limits): After called Before's repeat with no bound of its own, and a
    stopped Before stopped every TR answer for ever. Now a repeat unanswered within ~repeat_timeout
    is "outcome unknown" (with an alarm), Before is not asked again, and the execution it runs once
    resumed is refused (the vote ended: ``stray_execution``)."""
    server, before, after, _call, alarms = wired
    hung = HungBefore(before)
    after.repeat, after.repeat_timeout = hung, 0.2
    first = before.handle(Request(id=7, origin='/proxy'))   # a value fault: the vote asks for a repeat
    started = time.monotonic()
    answer = after.handle(server.execute(first))
    assert time.monotonic() - started < 2.0 and answer.status == Reply.ERROR
    assert classify_error('service [/account] responded with an error: ' + answer.error) == 'indeterminate'
    assert 'no answer within 0.200 s' in answer.error and alarms == ['restore_failed']
    assert hung.calls == [Repeat._request_class.REPEAT]   # not asked to forget: that would wait again
    hung.go.set()   # Before resumes: it restores and executes again; After ignores that result
    deadline = time.monotonic() + 5.0
    while not before.ports.out and time.monotonic() < deadline:
        time.sleep(0.01)
    late = server.execute(before.ports.out.popleft())
    assert after.handle(late) is None and after.votes.pending() == 0
    assert alarms == ['restore_failed', 'stray_execution']


def test_a_hung_before_in_a_replica_fail_stops_it(wired, monkeypatch):
    _server, before, after, _call, _alarms = wired
    stops = []
    monkeypatch.setattr(tr, 'fail_stop', lambda ports, site, why, mechanism=None: stops.append(why))
    hung = HungBefore(before)
    after.repeat, after.repeat_timeout, after.site = hung, 0.2, '/master'
    ok, why = after._tell_before(Reply(origin='/proxy', id=1), Repeat._request_class.REPEAT)
    hung.go.set()
    assert not ok and why.startswith(tr.FAIL_STOPPED) and 'no answer within 0.200 s' in why
    assert len(stops) == 1 and after.failed


def test_another_attempt_of_a_request_executes_even_if_an_earlier_attempt_s_vote_never_ended(wired):
    """An outer mechanism executing a request again numbers the execution (attempt): it is not a copy.
    An earlier attempt's saved state left behind (its After restarted mid-vote) does not refuse it
    (review of session 38: the first version refused every attempt of a held (origin, id))."""
    server, before, _after, _call, alarms = wired
    server.corrupt_next = False
    assert before.handle(Request(id=9, origin='/proxy', attempt=0)) is not None   # its vote never ends
    again = before.handle(Request(id=9, origin='/proxy', attempt=1))
    assert again is not None and again.attempt == 1 * tr.SPAN and alarms == []
    assert before.handle(Request(id=9, origin='/proxy', attempt=1)) is None and alarms == ['duplicate_request']


def test_a_repeat_that_lands_after_its_vote_gave_up_rewinds_nothing(wired):
    """Review of session 38: outside a replica, a repeat unanswered in time ends its vote as "outcome
    unknown", and the Protocol sends the next request. Before, stopped meanwhile, then handled both
    in any order: the late repeat restored the state saved before the first request, rewinding the
    second, whose client was told it succeeded. Now a new capture drops the older saved state, and
    the late repeat is refused."""
    server, before, after, _call, alarms = wired
    hung, direct = HungBefore(before), after.repeat
    after.repeat, after.repeat_timeout = hung, 0.2
    first = before.handle(Request(id=1, origin='/proxy'))       # a value fault: its vote asks for a repeat
    assert 'no answer within' in after.handle(server.execute(first)).error and server.balance == 90
    server.corrupt_next, after.repeat = False, direct
    second = before.handle(Request(id=2, origin='/proxy'))      # the next request, executed and decided
    assert before.held.keys() == {('/proxy', 2)}
    answer = after.handle(server.execute(second))
    answer = answer or after.handle(server.execute(before.ports.out.popleft()))
    assert bytes(answer.payload) == b'80' and server.balance == 80
    hung.go.set()                                               # Before resumes: the late repeat of 1
    assert hung.done.wait(5.0) and not hung.answer.success and 'no saved state' in hung.answer.message
    assert server.balance == 80 and not before.ports.out        # (before: restored to 100, 1 run again: 90)


def _copy_of(before, rid):
    """What Before answers a copy of request rid with (published on its ``errors`` port)."""
    before.ports.errors.clear()
    assert before.handle(Request(id=rid, origin='/proxy')) is None   # never executed again
    return list(before.ports.errors)


def test_a_copy_of_a_request_whose_vote_ended_gets_the_votes_answer_again(wired):
    """Limits of session 38: a refused copy of a request that was executed got no answer from TR, so a
    Protocol started again, which lost the first answer, waited until its timeout. Each outcome of a
    vote is given again: decided, restore refused (outcome unknown), no majority (set back)."""
    server, before, after, call, alarms = wired
    decided = call(1)
    assert [(a.id, a.status, bytes(a.payload)) for a in _copy_of(before, 1)] == [(1, Reply.OK, bytes(decided.payload))]
    assert server.balance == 90 and alarms.count('duplicate_request') == 1

    server.refuse_restore, server.corrupt_next = True, True   # a repeat is needed and cannot run
    unknown = call(2)
    assert unknown.status == Reply.ERROR and 'outcome unknown' in unknown.error
    assert [(a.id, a.status, a.error) for a in _copy_of(before, 2)] == [(2, Reply.ERROR, unknown.error)]

    server.refuse_restore = False
    payloads = iter([b'1', b'2', b'3'])   # three executions, three results: no majority, set back

    def disagreeing(request):
        server.balance -= 10
        return Reply(id=request.id, origin=request.origin, attempt=request.attempt, payload=next(payloads))
    server.execute = disagreeing
    balance = server.balance
    none = call(3)
    assert none.status == Reply.ERROR and 'no majority' in none.error and server.balance == balance   # set back
    assert [(a.id, a.error) for a in _copy_of(before, 3)] == [(3, none.error)]


def test_a_no_majority_whose_state_was_not_set_back_keeps_no_wrong_answer(wired):
    """RESTORE refused by the server: After answers "outcome unknown", not the "no majority" it gave
    Before with RESTORE; Before keeps that one only once the state is set back, so a copy gets no
    answer rather than a wrong one (said in its alarm)."""
    server, before, after, call, alarms = wired
    payloads = iter([b'1', b'2', b'3'])

    def disagreeing(request):
        server.balance -= 10
        if request.attempt % tr.SPAN == 2:
            server.refuse_restore = True   # the last restore (no majority) is refused
        return Reply(id=request.id, origin=request.origin, attempt=request.attempt, payload=next(payloads))
    server.execute = disagreeing
    answer = call(4)
    assert answer.status == Reply.ERROR and 'outcome unknown' in answer.error
    assert _copy_of(before, 4) == []


def test_the_kept_answers_are_bounded_in_number_and_bytes():
    kept = KeptAnswers(remember=3, max_bytes=1000)
    for rid in range(5):
        kept.keep(('/p', rid, 1), Reply(id=rid, payload=b'x' * 10))
    assert len(kept) == 3 and kept.get(('/p', 0, 1)) is None and kept.get(('/p', 4, 1)).id == 4
    kept.keep(('/p', 9, 1), Reply(id=9, payload=b'x' * 900))   # the older ones go to make room
    assert [k for k in range(10) if kept.get(('/p', k, 1))] == [9] and kept.bytes <= 1000
    # Larger than the bound: not kept, and pushes nothing out (review of session 39: it emptied the store).
    assert not kept.keep(('/p', 10, 1), Reply(id=10, payload=b'x' * 2000))
    assert [k for k in range(11) if kept.get(('/p', k, 1))] == [9] and kept.bytes == answer_size(kept.get(('/p', 9, 1)))


def test_large_answers_never_push_out_a_not_executed_one_and_the_largest_are_not_sent(wired):
    """Review of session 39: "not executed" answers shared the byte bound with every vote's answer,
    so a few large replies pushed them out, and a copy of a request that never ran got no answer."""
    server, before, after, call, alarms = wired

    class Refused(object):
        def __call__(self):
            raise rospy.ServiceException('service [/get_state] unavailable')

        def fresh(self):
            return self
    get_state, before.get_state = before.get_state, Refused()
    before.handle(Request(id=1, origin='/proxy'))              # answered "not executed"
    before.get_state = get_state
    before.answered = KeptAnswers(max_bytes=3000)
    big = iter([b'y' * 2000] * 100)

    def large(request):
        server.balance -= 10
        return Reply(id=request.id, origin=request.origin, attempt=request.attempt, payload=next(big))
    server.execute = large
    server.corrupt_next = False
    for rid in range(2, 6):
        call(rid)
    assert [a.error for a in _copy_of(before, 1)][0].startswith('not executed')
    assert [bytes(a.payload) for a in _copy_of(before, 5)] == [b'y' * 2000]   # the last one fits
    assert _copy_of(before, 3) == []                                          # pushed out by 4 and 5
    huge = iter([b'z' * (tr.ANSWER_SENT_MAX + 1)] * 3)
    server.execute = lambda request: Reply(id=request.id, origin=request.origin, attempt=request.attempt,
                                           payload=next(huge))
    before.answered = KeptAnswers()
    assert bytes(call(6).payload)[:1] == b'z'
    assert _copy_of(before, 6) == []   # not sent to Before: each FORGET would have carried it


def test_only_the_outstanding_execution_of_a_vote_is_counted(wired):
    """Outside review: After counted the result of any execution number it had not counted yet. Results
    of executions not asked for (ahead of the one outstanding, past ~executions, of another attempt:
    forged, or published again by anyone on the graph) decided the vote with a value the server never
    computed, and the real execution asked for was then dropped as "heard twice". Now only the
    outstanding execution of the outstanding attempt is counted; every other result is refused with
    the alarm ``stray_execution``: a copy, a late result after its vote ended, one of an earlier attempt."""
    server, before, after, _call, alarms = wired
    server.corrupt_next = False

    def result(k, attempt=0, payload=b'666'):
        return Reply(id=1, origin='/proxy', attempt=attempt * tr.SPAN + k, payload=payload)

    def refused(*results):
        for r in results:
            number = r.attempt   # (After takes the execution's number off)
            assert after.handle(r) is None, 'attempt field %d counted: %r' % (number, bytes(r.payload))
        assert not before.ports.out, 'executed again for a result not asked for'

    first = before.handle(Request(id=1, origin='/proxy'))   # execution 0 is outstanding
    refused(result(1), result(2), result(7))
    computed = server.execute(first)                         # balance 90
    assert after.handle(computed) is None                    # counted: After asks for execution 1
    (again,) = before.ports.out
    before.ports.out.clear()
    assert again.attempt == 1
    # 0 counted already; 2 not asked for yet; attempt 3's while attempt 0's vote runs
    refused(computed, result(0), result(2), result(0, attempt=3), result(1, attempt=3))
    answer = after.handle(server.execute(again))
    assert answer is not None and answer.status == Reply.OK and bytes(answer.payload) == b'90'
    assert server.balance == 90 and after.masked == 0
    refused(result(1, payload=b'90'), result(2))             # the vote has ended
    # Attempt 1 (an outer mechanism executes the request again): a vote of its own; attempt 0's are refused.
    second = before.handle(Request(id=1, origin='/proxy', attempt=1))
    refused(result(0), result(1, attempt=1))
    assert after.handle(server.execute(second)) is None
    (again,) = before.ports.out
    before.ports.out.clear()
    assert bytes(after.handle(server.execute(again)).payload) == b'80' and server.balance == 80
    assert alarms == ['stray_execution'] * 12, alarms


# (attempt, execution, result) heard in order -> the vote's outcome, or why the result is refused
OUTSTANDING = [
    ('a vote begins with execution 0 only', [(0, 1, 'x')], [Stray.NOT_ASKED]),
    ('agreeing executions decide', [(0, 0, 'x'), (0, 1, 'x')], [Outcome.REPEAT, Outcome.DECIDED]),
    ('a copy is counted once', [(0, 0, 'x'), (0, 0, 'x')], [Outcome.REPEAT, Stray.COUNTED]),
    ('one not asked for yet', [(0, 0, 'x'), (0, 2, 'y')], [Outcome.REPEAT, Stray.NOT_ASKED]),
    ('one past ~executions', [(0, 0, 'x'), (0, 1, 'y'), (0, 3, 'y')],
     [Outcome.REPEAT, Outcome.REPEAT, Stray.NOT_ASKED]),
    ('another attempt while a vote runs', [(0, 0, 'x'), (1, 0, 'y')], [Outcome.REPEAT, Stray.OTHER_ATTEMPT]),
    ('an earlier attempt while a vote runs', [(1, 0, 'x'), (0, 0, 'y')], [Outcome.REPEAT, Stray.EARLIER]),
    ('after its vote ended', [(0, 0, 'x'), (0, 1, 'x'), (0, 2, 'x')],
     [Outcome.REPEAT, Outcome.DECIDED, Stray.ENDED]),
    ('a newer attempt once the vote ended', [(0, 0, 'x'), (0, 1, 'x'), (1, 0, 'y'), (1, 1, 'y')],
     [Outcome.REPEAT, Outcome.DECIDED, Outcome.REPEAT, Outcome.DECIDED]),
    ('an earlier attempt, late', [(1, 0, 'x'), (1, 1, 'x'), (0, 0, 'x')],
     [Outcome.REPEAT, Outcome.DECIDED, Stray.EARLIER]),
    ('a newer attempt starts with execution 0', [(0, 0, 'x'), (0, 1, 'x'), (1, 1, 'y')],
     [Outcome.REPEAT, Outcome.DECIDED, Stray.NOT_ASKED]),
    ('no majority', [(0, 0, 'x'), (0, 1, 'y'), (0, 2, 'z'), (0, 1, 'x')],
     [Outcome.REPEAT, Outcome.REPEAT, Outcome.NO_MAJORITY, Stray.ENDED]),
]


@pytest.mark.parametrize('case, heard, expected', OUTSTANDING, ids=[c[0] for c in OUTSTANDING])
def test_the_votes_count_only_the_execution_outstanding(case, heard, expected):
    votes = Votes(3)
    got = []
    for attempt, execution, result in heard:
        vote, stray = votes.add(('/proxy', 1), attempt, execution, result)
        assert (vote is None) != (stray is None), case
        got.append(stray or vote.outcome)
    assert got == expected, case
    assert votes.add(('/proxy', 2), 0, 0, 'x')[0].outcome == Outcome.REPEAT   # other requests vote apart


def test_a_vote_ended_undecided_refuses_its_results_and_the_memory_is_bounded():
    votes = Votes(3, remember=2)
    votes.add(('/p', 1), 0, 0, 'x')
    votes.end(('/p', 1), 0)   # its repeat could not run
    assert votes.add(('/p', 1), 0, 1, 'x') == (None, Stray.ENDED) and votes.pending() == 0
    for rid in (2, 3):
        votes.add(('/p', rid), 0, 0, 'x')
    assert votes.pending() == 2 and votes.add(('/p', 1), 0, 1, 'x') == (None, Stray.NOT_ASKED)   # forgotten


def test_a_vote_stuck_on_a_lost_execution_is_superseded_by_a_newer_attempt_after_stale_after():
    """Review of the first Votes: a vote whose repeated execution was lost (its result never heard) ran
    for ever, and every newer attempt of the request (the Protocol's retries, each executed by Before,
    which replaces the saved state) was refused as another attempt's: the request could never be
    answered. Within ``stale_after`` of the last execution counted a newer attempt is still refused
    (a forged one cannot cut a vote short); past it, its execution 0 supersedes the stuck vote."""
    clock = FakeClock(100.0)
    votes = Votes(3, stale_after=5.0, clock=lambda: clock.now)
    assert votes.add(('/proxy', 1), 0, 0, 'x')[0].outcome == Outcome.REPEAT   # execution 1 asked for: lost
    clock.now += 4.9
    assert votes.add(('/proxy', 1), 1, 0, 'y') == (None, Stray.OTHER_ATTEMPT)
    clock.now += 0.2
    assert votes.add(('/proxy', 1), 1, 1, 'y') == (None, Stray.NOT_ASKED)     # a newer vote begins with 0 only
    assert votes.add(('/proxy', 1), 1, 0, 'y')[0].outcome == Outcome.REPEAT   # supersedes the stuck vote
    decided = votes.add(('/proxy', 1), 1, 1, 'y')[0]
    assert decided.outcome == Outcome.DECIDED and decided.value == 'y'
    assert votes.add(('/proxy', 1), 0, 1, 'x') == (None, Stray.EARLIER)       # the lost execution, late
    assert votes.pending() == 0                                                # the stuck vote's results dropped
