"""A history checker for the bank campaign (Jepsen-style): what the clients saw, and the servers' final
states, checked against one account applying every answered operation exactly once, in an order
consistent with real time. No ROS.

What a reply proves. The bank's reply to an operation is (balance, count, digest) after it; ``count``
is the operation's position in the account's one sequence, and ``digest`` hashes the whole sequence
(aft_examples.bank). So the answered operations place themselves: the history is linearizable iff

1. no two answered operations claim the same position, and none a position past the final count
   (an answered operation lost by a failover);
2. replaying the sequence from the empty account gives every answered operation's reply exactly
   (balance and digest: a wrong value, an operation executed twice or out of order, or a reply from a
   deposed primary whose sequence diverged all break the chain);
3. the positions no answered operation claims are filled by operations whose outcome the client
   could not know (``indeterminate``: only when that client's own Proxy was killed during the call,
   or ``unfinished``: in flight when the run ended); an operation that failed with a definite outcome
   (``not_executed``, or ``error``: the server's or a mechanism's error, after which nothing changed)
   must never fill one;
4. if operation a completed before operation b was invoked, a's position is before b's (real time);
5. a withdrawal refused for insufficient funds saw, somewhere inside its call, a balance below its
   amount;
6. the final states of the servers still serving agree, and extend the sequence.

The positions of indeterminate operations are searched (bounded). Operations are told apart by
their tag (the campaign's clients give each a unique one, which enters the digest): two executions
of untagged operations with the same op and amount cannot be told apart, so an execution twice of
one could pass for an indeterminate other. An exhausted search is reported as a violation ``undecided``, never as
a pass.

Unavailability (``unavailability``) is measured per fault: the longest time, from the fault on and
before the next one, during which the clients invoked operations and none was answered.
``unavailability_split`` tells apart what the fault itself cost (from the fault to the runner's first
repair action: a failover, a freeze waited out) from what its repair cost (a relaunched site's
re-join, whose state transfer holds the primary's requests).
"""
import collections
import json
import math
import re

from .bank import GENESIS, Account, InsufficientFunds

OUTCOMES = ('ok', 'not_executed', 'error', 'indeterminate', 'unfinished')
DEFINITE = ('ok', 'not_executed', 'error')
INSUFFICIENT = 'cannot withdraw'   # the bank's wording of InsufficientFunds
_REFUSAL = re.compile(r'cannot withdraw -?\d+ from a balance of (-?\d+)')
SEARCH_LIMIT = 20000               # nodes of the search for indeterminate operations' positions


class HistoryError(ValueError):
    """A history that cannot be checked at all (malformed input), named with the record at fault."""


class Op(object):
    """One client operation: invoked at ``invoke``, completed at ``complete`` (wall-clock seconds;
    None while unfinished), with its outcome and, if ok, the reply (balance, count, digest)."""
    __slots__ = ('client', 'index', 'invoke', 'complete', 'op', 'amount', 'outcome', 'reply', 'error', 'tag')

    def __init__(self, client, index, invoke, complete, op, amount, outcome, reply=None, error='', tag=''):
        if outcome not in OUTCOMES:
            raise HistoryError('operation %s#%s: outcome %r is none of %s' % (client, index, outcome,
                                                                             ', '.join(OUTCOMES)))
        if outcome == 'ok' and (reply is None or len(reply) != 3):
            raise HistoryError('operation %s#%s: ok without a reply (balance, count, digest)' % (client, index))
        if complete is None and outcome != 'unfinished':
            raise HistoryError('operation %s#%s: no completion time for outcome %s' % (client, index, outcome))
        if complete is not None and complete < invoke:
            raise HistoryError('operation %s#%s completes (%.6f) before it is invoked (%.6f)'
                               % (client, index, complete, invoke))
        self.client, self.index, self.invoke, self.complete = client, index, invoke, complete
        self.op, self.amount, self.outcome, self.error, self.tag = op, amount, outcome, error, tag or ''
        self.reply = tuple(reply) if reply is not None else None

    @property
    def name(self):
        return '%s#%d' % (self.client, self.index)

    def end(self):
        """When its effect can no longer happen (inf: in flight, or its fate unknown)."""
        return float('inf') if self.complete is None or self.outcome == 'indeterminate' else self.complete

    def to_dict(self):
        return {k: getattr(self, k) for k in self.__slots__}

    @classmethod
    def from_dict(cls, d):
        return cls(**{k: d.get(k) for k in cls.__slots__ if k in d})

    def __repr__(self):
        return '%s(%s %d, %s%s, [%.3f, %s])' % (self.name, self.op, self.amount, self.outcome,
                                                ' %s' % (self.reply,) if self.reply else '', self.invoke,
                                                '%.3f' % self.complete if self.complete is not None else '-')


Violation = collections.namedtuple('Violation', 'kind detail')
KINDS = ('lost', 'duplicated', 'wrong_value', 'real_time', 'unexplained_execution', 'indeterminate_without_cause',
         'unfinished_without_cause', 'wrong_refusal', 'final_states_differ', 'final_state_unreadable',
         'history_missing', 'undecided', 'hung', 'client_silent')


class Result(object):
    """The checker's verdict: violations (empty: the history is linearizable), the sequence found
    (ops by position, None where an indeterminate operation's identity could not matter), counts."""

    def __init__(self):
        self.violations = []
        self.sequence = []
        self.counts = collections.Counter()

    def add(self, kind, detail):
        assert kind in KINDS, kind
        self.violations.append(Violation(kind, detail))

    @property
    def ok(self):
        return not self.violations

    def summary(self):
        return dict(self.counts, violations=len(self.violations))


def _model(state):
    return Account(*state)


def _apply(state, op):
    """(balance, count, digest) after op from state, or None if the bank would refuse it."""
    account = _model(state)
    try:
        return account.apply(op.op, op.amount, op.tag)
    except (ValueError, InsufficientFunds):
        return None


def _fill(state, length, target, candidates, budget):
    """A sequence of `length` distinct candidates that takes state to one whose next step reaches
    target (target(state) -> bool), or None. budget: [nodes left]; raises _Exhausted past it."""
    if length == 0:
        return [] if target(state) else None
    for i, op in enumerate(candidates):
        budget[0] -= 1
        if budget[0] < 0:
            raise _Exhausted()
        nxt = _apply(state, op)
        if nxt is None:
            continue
        rest = _fill(nxt, length - 1, target, candidates[:i] + candidates[i + 1:], budget)
        if rest is not None:
            return [op] + rest
    return None


class _Exhausted(Exception):
    pass


def check(ops, final_states=(), proxy_kills=None, end=None, killed_clients=(), call_limit=None, clients=(),
          stopped=None, silent_after=5.0):
    """Check a campaign's history.

    Parameters:
        ops: every client operation (Op), all clients together.
        final_states: the (balance, count, digest) of every server serving at the end (primary and
            backup once joined); they must agree. None read (or one unreadable: a balance or count that
            is no integer, or a count below 0) is a violation: what only they show (an answered operation lost, an execution
            nothing explains after the last answer) would otherwise pass unchecked.
        proxy_kills: {client: [wall times its Proxy was killed]}: an indeterminate outcome is
            acceptable only for a call in flight at one of them. A time may be a pair (stamped
            before the signal, after it): a call in flight at any instant between counts.
        end: the run's end (wall clock); unfinished operations must have been invoked before it.
        killed_clients: the clients killed at the end, their call in flight: only such a client's last
            operation may be unfinished.
        call_limit: how long a Proxy holds a call before it answers "outcome unknown" (seconds): an
            operation still unfinished at ``end`` after longer is ``hung`` (a call nothing answers is
            never silent; the client was killed in it only because it never returned).
        clients: the clients that were to call until ``stopped`` (when they were told to stop): one
            with no call in flight and none ended within ``silent_after`` s before it is
            ``client_silent`` (it died or gave up early: the faults after went untested under its load).
    Returns a Result. Raises HistoryError if two operations carry the same tag (they could not be
    told apart: one executed twice would pass for the other).
    """
    result = Result()
    proxy_kills = proxy_kills or {}
    tags = collections.Counter(op.tag for op in ops if op.tag)
    repeated = sorted(tag for tag, n in tags.items() if n > 1)
    if repeated:
        raise HistoryError('tags given to more than one operation: %s' % ', '.join(repeated[:5]))
    for op in ops:
        result.counts[op.outcome] += 1
    answered = [op for op in ops if op.outcome == 'ok']
    unknown = [op for op in ops if op.outcome in ('indeterminate', 'unfinished')]
    definite_failed = [op for op in ops if op.outcome in ('not_executed', 'error')]

    last = {}
    for op in ops:
        last[op.client] = max(last.get(op.client, op.index), op.index)
    def killed_during(op):
        for t in proxy_kills.get(op.client, ()):
            before, after = t if isinstance(t, (tuple, list)) else (t, t)
            if op.invoke <= after and before <= op.complete:
                return True
        return False
    for op in unknown:
        if op.outcome == 'indeterminate' and not killed_during(op):
            result.add('indeterminate_without_cause', '%r: outcome unknown to the client, but its Proxy was not '
                       'killed during the call (error: %s)' % (op, op.error))
        if op.outcome == 'unfinished' and (op.client not in killed_clients or op.index != last[op.client]
                                           or (end is not None and op.invoke > end)):
            result.add('unfinished_without_cause', '%r: never ended, but its client was not killed in that call '
                       'at the end of the run' % (op,))
        elif op.outcome == 'unfinished' and call_limit is not None and end is not None and \
                end - op.invoke > call_limit:
            result.add('hung', '%r: in flight for %.1f s when the run ended, past the Proxy\'s call limit of '
                       '%.0f s: nothing answered it' % (op, end - op.invoke, call_limit))
    if stopped is not None:
        for client in clients:
            own = [op for op in ops if op.client == client]
            pending = any(op.complete is None for op in own)
            latest = max([op.complete for op in own if op.complete is not None], default=None)
            if not pending and (latest is None or latest < stopped - silent_after):
                result.add('client_silent', '%s %s before it was told to stop: the faults after ran without its '
                           'load' % (client, 'made no call' if latest is None else
                                     'ended its last call %.1f s' % (stopped - latest)))

    readable = [tuple(s) for s in final_states   # unreadable: ('unreadable: why', -1, '')
                if all(isinstance(x, int) and not isinstance(x, bool) for x in s[:2]) and s[1] >= 0]
    for s in final_states:
        if tuple(s) not in readable:
            result.add('final_state_unreadable', 'a serving server\'s final state could not be read: %s' % (s[0],))
    if not final_states:
        result.add('final_state_unreadable', 'no final state of any server: the final count and state are unchecked')
    finals = sorted(set(readable))
    if len(finals) > 1:
        result.add('final_states_differ', 'the serving servers end in different states: %s' % finals)
    final_count = max((s[1] for s in finals), default=None)

    by_position = collections.defaultdict(list)
    for op in answered:
        by_position[op.reply[1]].append(op)
    for position, claimants in sorted(by_position.items()):
        if len(claimants) > 1:
            result.add('duplicated', 'position %d claimed by %d answered operations: %s'
                       % (position, len(claimants), claimants))
        if final_count is not None and position > final_count:
            for op in claimants:
                result.add('lost', '%r was answered at position %d, but the final state has only %d operations'
                           % (op, position, final_count))
        if position == 0:
            result.add('wrong_value', '%r answered with count 0' % (claimants,))
    length = max([final_count or 0] + list(by_position))

    # Replay: walk the positions, answered ones from their replies, the gaps searched among the
    # operations whose outcome is unknown. state None: unknown (after a gap nothing explains).
    state = (0, 0, GENESIS)
    sequence = [None] * (length + 1)
    balances = [0] * (length + 1)
    pool = sorted(unknown, key=lambda op: op.invoke)
    position = 1
    budget = [SEARCH_LIMIT]
    while position <= length:
        if position in by_position:
            op = by_position[position][0]
            if state is not None:
                got = _apply(state, op)
                if got != op.reply:
                    result.add('wrong_value', '%r replied %s, but position %d after %s gives %s'
                               % (op, op.reply, position, state, got))
            state = op.reply   # go on from what the server said, to find further violations
            sequence[position], balances[position] = op, state[0]
            position += 1
            continue
        gap_end = position
        while gap_end <= length and gap_end not in by_position:
            gap_end += 1
        gap = gap_end - position
        nxt = by_position[gap_end][0] if gap_end <= length else None
        if nxt is not None:
            def target(s, nxt=nxt):
                return _apply(s, nxt) == nxt.reply
        else:
            def target(s):
                return tuple(s) in finals
        # Only operations that could have executed there: invoked before the next answered one completed.
        limit = nxt.complete if nxt is not None else float('inf')
        candidates = [op for op in pool if op.invoke < limit]
        fill = None
        if state is not None and len(candidates) >= gap:
            try:
                fill = _fill(state, gap, target, candidates, budget)
            except _Exhausted:
                result.add('undecided', 'the search for the operations at positions %d..%d gave up after %d steps'
                           % (position, gap_end - 1, SEARCH_LIMIT))
                budget = [SEARCH_LIMIT]
                fill = []
        if fill is None:
            suspects = [op for op in definite_failed if op.invoke < limit]
            result.add('unexplained_execution', 'positions %d..%d (%d operations) were executed, but no operation '
                       'of unknown outcome explains them (%d candidates)%s'
                       % (position, gap_end - 1, gap, len(candidates),
                          '; operations failed with a definite outcome before: %s' % suspects[-3:]
                          if suspects else ''))
        if not fill:
            for p in range(position, gap_end):
                balances[p] = None
            state, position = None, gap_end
            continue
        for op in fill:
            pool.remove(op)
            state = _apply(state, op)
            sequence[position], balances[position] = op, state[0]
            position += 1
    if finals and state is not None and length == final_count and tuple(state) not in finals:
        result.add('wrong_value', 'the replayed sequence ends in %s, the servers in %s' % (state, finals))
    result.sequence = sequence[1:]
    result.counts['positions'] = length

    _check_real_time(result, sequence)
    _check_refusals(result, ops, sequence, balances)
    return result


def _check_real_time(result, sequence):
    """No operation placed after another that was invoked after it completed."""
    placed = [(p, op) for p, op in enumerate(sequence) if op is not None]
    # Walking back from the end: the earliest end of any operation placed later.
    earliest_end, who = float('inf'), None
    for position, op in reversed(placed):
        if earliest_end < op.invoke:
            result.add('real_time', '%r completed before %r was invoked, yet it is placed after it (position %d '
                       'after %d)' % (who, op, who.reply[1] if who.reply else -1, position))
        end = op.end()
        if end < earliest_end:
            earliest_end, who = end, op


def _check_refusals(result, ops, sequence, balances):
    """A withdrawal refused for insufficient funds saw a balance below its amount inside its call."""
    placed = [(p, op) for p, op in enumerate(sequence) if op is not None]
    for op in ops:
        if op.outcome != 'error' or op.op != 'withdraw' or INSUFFICIENT not in (op.error or ''):
            continue
        # Positions whose state the call may have seen: from the last operation completed before it was
        # invoked to the last one invoked before it completed.
        # Positions whose state the call may have seen: from the last operation completed before it was
        # invoked, up to (not including) the first one invoked after it completed (that one, and every
        # later position, came after the refusal was answered).
        low = max([p for p, other in placed if other.end() < op.invoke], default=0)
        high = min([p for p, other in placed if other.invoke > op.complete], default=len(balances)) - 1
        window = range(low, max(low, high) + 1)
        seen = [balances[p] for p in window if p < len(balances) and balances[p] is not None]
        unknown = any(p >= len(balances) or balances[p] is None for p in window)
        if seen and min(seen) >= op.amount:
            result.add('wrong_refusal', '%r was refused for insufficient funds, but the balance was %s at every '
                       'position %d..%d its call could see' % (op, sorted(set(seen))[:5], low, high))
            continue
        said = _refused_balance(op.error)
        if said is not None and not unknown and said not in seen:
            result.add('wrong_refusal', '%r was refused on a balance of %d, which no position %d..%d its call could '
                       'see held (%s)' % (op, said, low, high, sorted(set(seen))[:5]))


def _refused_balance(error):
    """The balance a refusal for insufficient funds names (the bank's 'cannot withdraw A from a balance
    of N'), or None."""
    found = _REFUSAL.search(error or '')
    return int(found.group(1)) if found else None


# -- unavailability ---------------------------------------------------------------------------------

def unavailability(ops, start, stop):
    """The longest time in [start, stop) during which operations were pending and none was answered
    (seconds). Measured from start (a gap open when the fault came counts from the fault), or from
    the first call invoked after the last answer (a client idle meanwhile waited for nothing)."""
    answers = sorted(op.complete for op in ops if op.outcome == 'ok')
    longest = 0.0
    # Only the calls pending somewhere in [start, stop] matter (a whole segment's history is long).
    pending = sorted((op.invoke, op.complete if op.complete is not None else stop) for op in ops
                     if op.invoke < stop and (op.complete is None or op.complete > start))
    last = start
    for t in answers:
        if t < start:
            continue
        if t >= stop:
            break
        longest = max(longest, _waited(pending, last, t))
        last = t
    if last < stop:
        longest = max(longest, _waited(pending, last, stop))
    return longest


def unavailability_split(ops, start, repaired_from, stop):
    """{'unavailable': the whole window [start, stop), 'unavailable_fault': [start, repaired_from),
    'unavailable_repair': [repaired_from, stop)} in seconds; with no repair (repaired_from None) the
    fault's share is the whole window and the repair's 0. A repair action before the fault (a clock
    step) counts as none."""
    whole = unavailability(ops, start, stop)
    if repaired_from is None or not start <= repaired_from < stop:
        return {'unavailable': whole, 'unavailable_fault': whole, 'unavailable_repair': 0.0}
    return {'unavailable': whole, 'unavailable_fault': unavailability(ops, start, repaired_from),
            'unavailable_repair': unavailability(ops, repaired_from, stop)}


def _waited(pending, a, b):
    """How long in [a, b] some call was pending: from the earliest invocation among the calls pending
    then (or a) to b; 0 if none was."""
    invoked = [invoke for invoke, complete in pending if invoke < b and complete > a]
    return b - max(a, min(invoked)) if invoked else 0.0


def percentile(values, q):
    """The q-th percentile (0..100) by nearest rank; None for no values."""
    if not values:
        return None
    values = sorted(values)
    rank = max(0, min(len(values) - 1, int(math.ceil(q / 100.0 * len(values))) - 1))
    return values[rank]


# -- client histories on disk ------------------------------------------------------------------------

def read_history(path, client):
    """A client's JSON-lines history: {"i", "invoke", "op", "amount"} when a call starts, then
    {"i", "complete", "outcome", "reply", "error"} when it ends. A call never ended is unfinished.
    Raises HistoryError naming the line at fault."""
    started, ops = {}, []
    with open(path) as f:
        for number, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
                i = record['i']
                if 'invoke' in record:
                    started[i] = record
                    continue
                begun = started.pop(i)
                ops.append(Op(client, i, begun['invoke'], record['complete'], begun['op'], begun['amount'],
                              record['outcome'], record.get('reply'), record.get('error', ''), begun.get('tag', '')))
            except (ValueError, KeyError, TypeError) as e:
                if line.endswith('\n'):
                    raise HistoryError('%s line %d: %r is not a history record (%s)' % (path, number, line[:80], e))
                # a last line cut by the client's end: its call is unfinished
    for i, begun in sorted(started.items()):
        ops.append(Op(client, i, begun['invoke'], None, begun['op'], begun['amount'], 'unfinished',
                      tag=begun.get('tag', '')))
    return ops


# -- what a failed call tells its client -------------------------------------------------------------

# rospy's words when the request never left the client (no Proxy registered, or none listening).
_NOT_SENT = ('unavailable', 'unable to connect', 'connection refused', 'unable to contact master')
# rospy's words when the request was sent and the connection then broke: its fate is unknown.
_CUT = ('transport error', 'unable to receive data', 'connection reset', 'broken pipe', 'outcome unknown')


def classify_error(text):
    """The outcome of a call that raised, from its error text: 'not_executed' (the request never reached
    a Proxy, or the Proxy answered "not executed"), 'indeterminate' (the connection broke with the
    request sent, or the Proxy gave up: the client cannot know), or 'error' (the server's or a
    mechanism's error: nothing changed)."""
    low = (text or '').lower()
    if 'responded with an error' in low:   # the Proxy answered: its own word, the server's or a mechanism's
        if 'outcome unknown' in low:         # the Proxy's call limit passed: it may still execute
            return 'indeterminate'
        return 'not_executed' if 'not executed' in low else 'error'
    if 'unable to connect' in low:   # rospy's connect and header exchange, before the request is written,
        return 'not_executed'        # whatever broke them (a Proxy just killed: "Connection reset by peer")
    if any(word in low for word in _CUT):
        return 'indeterminate'
    if 'not executed' in low or any(word in low for word in _NOT_SENT):
        return 'not_executed'
    return 'error'
