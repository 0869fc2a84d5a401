"""The Protocol of an FTM graph: duplicate detection and one request at a time.

A Protocol receives requests from Proxies, answers duplicates from a reply cache,
and hands other requests to Before one batch at a time (so that a state captured after a
batch reflects exactly the requests of the batches before it and of this one). A batch is one
request unless ``max_batch`` is above 1 (PBR's group commit: the requests that queued while a
batch executed and was checkpointed go as the next batch, executed back to back, and covered by
one checkpoint; each carries ``batch``: how many of its batch are left including itself, and the
batch's size, so that After knows the last, and knows if one is missing). In a backup replica it does not
execute anything: it stores the replies that checkpoints carry, so that after a
failover re-sent requests that were already executed are answered from the cache.

Requests and replies are any objects with ``origin``, ``id`` attributes (and
``oldest_pending`` for requests): the ROS adapter passes aft_msgs messages.
"""
import collections
import enum

from .errors import RoleError


def key(msg):
    """What identifies a request (and its reply): its Proxy, its id, and which execution it is
    (a mechanism that executes a request again numbers the executions, see aft_msgs/Request)."""
    return (msg.origin, msg.id, getattr(msg, 'attempt', 0))


def reply_size(reply):
    """Bytes a stored reply costs: its payload and error text, and a fixed overhead."""
    return len(getattr(reply, 'payload', b'') or b'') + len(getattr(reply, 'error', '') or '') + 64


class DuplicateCache(object):
    """Stored replies per (origin, request id).

    A Proxy tells, with each request, the oldest id it is still waiting for; replies to
    older ids can never be asked for again and are forgotten. ``capacity`` (entries) and
    ``max_bytes`` bound it against Proxies that never advance: once either is reached the cache is
    ``full()`` and new requests are refused, never a reply forgotten. A reply evicted to make room
    let a captured request run twice: its id was still at or above its origin's watermark, so neither
    the SEC gate nor the Protocol refused the replay (review of SEC, session 33: an insider with
    many origins filled 100 000 entries in 1.7 s). ``evicted`` stays 0 (kept for diagnostics).
    """

    def __init__(self, capacity=100000, max_bytes=0):
        self._capacity = capacity       # 0: no bound in entries
        self.max_bytes = max_bytes      # 0: no bound in bytes
        self.bytes = 0
        self._replies = collections.OrderedDict()   # key -> reply, in insertion order
        self._by_origin = collections.defaultdict(set)
        self.evicted = 0

    def __len__(self):
        return len(self._replies)

    def __contains__(self, key):
        return key in self._replies

    def lookup(self, request_key):
        """Return the stored reply of the request with this key (see key()), or None."""
        return self._replies.get(request_key)

    def full(self):
        """True when the cache holds max_bytes or more, or capacity entries: a new request must be
        refused, not executed."""
        return bool(self.max_bytes) and self.bytes >= self.max_bytes or \
            bool(self._capacity) and len(self._replies) >= self._capacity

    def why_full(self):
        return 'the reply cache holds %d replies (bound %s) and %d bytes (bound %s) its clients have not ' \
               'confirmed' % (len(self._replies), self._capacity or 'none', self.bytes, self.max_bytes or 'none')

    def replies(self):
        """Every stored reply, oldest first (a state transfer carries them)."""
        return list(self._replies.values())

    def store(self, reply):
        """Remember a reply (never one forgotten to make room: see full()). Returns None."""
        k = key(reply)
        if k in self._replies:
            self.bytes += reply_size(reply) - reply_size(self._replies[k])
            self._replies[k] = reply
            return None
        self._replies[k] = reply
        self.bytes += reply_size(reply)
        self._by_origin[reply.origin].add(k)
        return None

    def highest(self, origin):
        """The highest request id of origin with a stored reply, or 0."""
        return max((k[1] for k in self._by_origin.get(origin, ())), default=0)

    def forget_below(self, origin, watermark):
        """Forget the replies of origin whose id is below watermark (already received)."""
        keys = self._by_origin.get(origin)
        if not keys:
            return 0
        old = [k for k in keys if k[1] < watermark]
        for k in old:
            keys.discard(k)
            self.bytes -= reply_size(self._replies.pop(k))
        return len(old)


class Role(enum.Enum):
    """Role of a replica (and of its Protocol and After nodes)."""
    BACKUP = 0    # receives checkpoints, executes nothing
    PRIMARY = 1   # executes requests and checkpoints them to a live backup
    ALONE = 2     # executes requests, no backup (lost, or none configured)


# Allowed role changes, each with the event that causes it.
MAX_AHEAD = 4096   # checkpoint numbers kept beyond a gap (a state transfer closes any gap)

ROLE_EDGES = {
    (Role.BACKUP, Role.ALONE): 'the primary failed: the backup takes over',
    (Role.PRIMARY, Role.ALONE): 'the backup failed: the primary goes on without checkpoints',
    (Role.ALONE, Role.PRIMARY): 'a backup joined: every reply is checkpointed to it again',
}


def check_role_change(current, new):
    """Raise RoleError unless current -> new is an allowed edge (or no change)."""
    if current == new:
        return
    if (current, new) not in ROLE_EDGES:
        raise RoleError('role change %s -> %s is not allowed (allowed: %s)' % (
            current.name, new.name,
            ', '.join('%s -> %s' % (a.name, b.name) for a, b in ROLE_EDGES)))


class Forward(object):
    """Action: send this request to Before."""
    __slots__ = ('request',)

    def __init__(self, request):
        self.request = request

    def __repr__(self):
        return 'Forward(%s/%s)' % (self.request.origin, self.request.id)


class Answer(object):
    """Action: send this reply to the Proxies. ``cached`` tells a duplicate answered from the cache."""
    __slots__ = ('reply', 'cached')

    def __init__(self, reply, cached=False):
        self.reply = reply
        self.cached = cached

    def __repr__(self):
        return 'Answer(%s/%s%s)' % (self.reply.origin, self.reply.id, ', cached' if self.cached else '')


class Renumber(object):
    """Action: the request's id is below ids this replica answered already (its Proxy started again,
    under the same name, with a clock behind its predecessor's): it is not executed, and its Proxy is
    told to send it again under an id from ``first_id`` on. No outcome: a Proxy that had that id
    answered already ignores it."""
    __slots__ = ('request', 'first_id')

    def __init__(self, request, first_id):
        self.request = request
        self.first_id = first_id

    def __repr__(self):
        return 'Renumber(%s/%s from %d)' % (self.request.origin, self.request.id, self.first_id)


class Refuse(object):
    """Action: answer this request with a definite "not executed" error (nothing was changed)."""
    __slots__ = ('request', 'reason')

    def __init__(self, request, reason):
        self.request = request
        self.reason = reason

    def __repr__(self):
        return 'Refuse(%s/%s: %s)' % (self.request.origin, self.request.id, self.reason)


class ProtocolStats(object):
    def __init__(self):
        self.requests = 0            # requests received (including duplicates)
        self.executed = 0            # requests handed to Before
        self.cached_answers = 0      # duplicates answered from the cache
        self.joined = 0              # duplicates of a request still queued or executing
        self.stray_results = 0       # results that match no executing request
        self.stored = 0              # replies stored from checkpoints (backup)
        self.refused = 0             # new requests refused, not executed (the reply cache is full)
        self.dropped = 0             # queued requests dropped: their Proxy has their answer already
        self.stale_ids = 0           # requests numbered below ids answered already (a Proxy's clock behind)


class ProtocolCore(object):
    """Duplicate detection and sequencing, as an explicit state machine.

    Pipeline state: idle (``executing`` empty) or executing the batch ``executing`` (request key ->
    request, in the order forwarded; one request unless max_batch > 1). A new batch starts only once
    every result of the previous one came back. Role: see Role. Each method returns the list of
    actions (Forward, Answer) for the adapter to carry out.
    """

    def __init__(self, role, cache_capacity=100000, cache_bytes=0, max_batch=1):
        if max_batch < 1:
            raise ValueError('max_batch must be at least 1, not %r' % (max_batch,))
        self.max_batch = max_batch
        self.role = role
        self.epoch = 0              # the configuration epoch, stamped on every answer
        self.cache = DuplicateCache(cache_capacity, cache_bytes)
        self.queue = collections.deque()
        self.queued_keys = set()
        self.executing = collections.OrderedDict()
        self.started_at = None
        self.batches = 0            # batches forwarded (requests forwarded: stats.executed)
        self.last_stored_seq = 0    # the checkpoints of stored_sender whose replies are all stored: up to here
        self.stored_sender = None
        self._ahead = set()         # checkpoint numbers stored beyond a gap
        self._highest = 0           # the highest checkpoint number of stored_sender heard
        self._first_seq = 0         # stored_sender's first checkpoint number, when it said it
        self.holding = False        # suspended once quiescent: nothing starts executing until release()
        self.refused = {}           # request key -> why it was refused: every copy gets that answer
        self.watermarks = {}        # origin -> the highest oldest_pending it sent: it has every answer below
        self.stored_high = {}       # origin -> the highest request id whose reply a checkpoint brought (backup)
        self.seen_high = {}         # origin -> the highest request id received
        self.stats = ProtocolStats()

    # -- requests and results -------------------------------------------------
    def on_request(self, request, now):
        """A request arrived from a Proxy."""
        self.stats.requests += 1
        self._forget_below(request.origin, request.oldest_pending)
        if request.id < self.watermarks[request.origin]:
            # Its Proxy has its answer already (a late copy: a backup hears the Proxy on one connection and
            # the checkpoints that say so on another): its reply may be forgotten, it must not execute.
            # Or a Proxy started again under the same name numbers from a wall clock stepped back below
            # its predecessor's ids: dropped in silence, its every call hung. The primary tells it the ids
            # to use (a Proxy that had that id answered already ignores it).
            self.stats.dropped += 1
            if self.role == Role.BACKUP or request.oldest_pending > request.id:
                return []   # (its own oldest_pending says its Proxy has it answered: a late copy)
            self.stats.stale_ids += 1
            return [Renumber(request, self._highest_id(request.origin) + 1)]
        self.seen_high[request.origin] = max(request.id, self.seen_high.get(request.origin, 0))
        k = key(request)
        cached = self.cache.lookup(k)
        if cached is not None and self.role != Role.BACKUP:
            self.stats.cached_answers += 1
            return [self._answer(cached, cached=True)]
        if k in self.refused:
            # A copy of a request refused already (sent again before its Proxy had the answer): the same
            # definite answer, never an execution the client was told did not happen.
            self.stats.refused += 1
            return [Refuse(request, self.refused[k])]
        if k in self.queued_keys or k in self.executing:
            # A re-send of a request not answered yet: its reply will answer both.
            self.stats.joined += 1
            return []
        if self.role != Role.BACKUP and self.cache.full():
            return [self._refuse(request)]
        # A backup answers nothing (one replica answers the clients: an excluded backup's cached reply
        # would be of an older epoch) and refuses nothing (its primary may execute the request: a backup
        # cannot say "not executed"). It queues the request; the queue is bounded by the Proxies' pending
        # requests (what is below a Proxy's oldest_pending is dropped), and checked against the cache
        # once promoted.
        self.queue.append(request)
        self.queued_keys.add(k)
        return self._dispatch(now)

    def on_result(self, reply, now):
        """The result of an executing request came back from After (the next batch starts once the
        whole batch's results did)."""
        if self.executing.pop(key(reply), None) is None:
            self.stats.stray_results += 1
            return []
        self.epoch = max(self.epoch, getattr(reply, 'epoch', 0))
        self.cache.store(reply)
        if self.executing:
            self.started_at = now   # the batch progresses: the rest of it has its own time again
            return [self._answer(reply)]
        self.started_at = None
        return [self._answer(reply)] + self._dispatch(now)

    def on_refusal(self, reply, now):
        """A refusal came back from After: this Protocol's own (the backup holds it now, so a copy sent
        to it after a failover gets the same answer), or an inner mechanism's refusal of the executing
        request. It is the request's outcome: kept and answered."""
        if key(reply) in self.executing:
            return self.on_result(reply, now)
        self.epoch = max(self.epoch, getattr(reply, 'epoch', 0))
        self.cache.store(reply)
        return [self._answer(reply)]

    def on_stored(self, reply, seq, sender=None, first_seq=0):
        """A backup stores the reply carried by checkpoint ``seq`` of After ``sender`` (a group
        commit's replies come one by one with the same seq).

        Sequence numbers are per sending After: when an adaptation replaces the After, the count
        starts again from the new one's first checkpoint, ``first_seq`` (0: unknown, the first number
        heard from it then counts as its first). Checkpoints are counted without a gap
        (``last_stored_seq``): a lost message (a broken connection, a Protocol restarted) leaves its
        replies missing, and can_take_over false, until a state transfer (the After sends one when it
        is promoted) brings every reply it holds.
        """
        if reply is not None:
            self._store(reply)
        self._count(seq, sender, first_seq)

    def on_state_transfer(self, replies, seq, sender, first_seq=0):
        """A backup joined, or its After is taking over: the replies its primary's clients may ask for
        again, as of checkpoint seq (``first_seq``: the sender's first number, as on its checkpoints:
        without it, a transfer from an After started again under the same name left the old first
        number, and its next checkpoint counted as a gap at the transfer, review of stop 39)."""
        for reply in replies:
            self._store(reply)
        self._count(seq, sender, first_seq, full=True)

    @property
    def stored_gap(self):
        """The first checkpoint number whose replies never came, while later ones did; else None."""
        return self.last_stored_seq + 1 if self._highest > self.last_stored_seq else None

    def _store(self, reply):
        self._forget_below(reply.origin, reply.oldest_pending)
        if reply.id >= self.watermarks[reply.origin]:   # (below, its Proxy has it: a late state transfer's copy)
            self.cache.store(reply)
        self.stored_high[reply.origin] = max(reply.id, self.stored_high.get(reply.origin, reply.id))
        self.stats.stored += 1

    def _count(self, seq, sender, first_seq=0, full=False):
        # An After started again under its name (a rollback) numbers from a new first_seq: a new sender.
        if sender != self.stored_sender or (first_seq and self._first_seq and first_seq != self._first_seq):
            self.stored_sender = sender
            self._first_seq = 0
            self._ahead = set()
            self.last_stored_seq = self._highest = seq if full or not first_seq else first_seq - 1
        if first_seq:
            self._first_seq = first_seq
        self._highest = max(self._highest, seq)
        if full:
            if seq > self.last_stored_seq:
                self.last_stored_seq = seq
                self._ahead = {s for s in self._ahead if s > seq}
        elif seq == self.last_stored_seq + 1:
            self.last_stored_seq = seq
        elif seq > self.last_stored_seq + 1 and len(self._ahead) < MAX_AHEAD:
            self._ahead.add(seq)   # (beyond the bound a gap only stays longer: never a wrong take-over)
        while self._ahead and self.last_stored_seq + 1 in self._ahead:
            self.last_stored_seq += 1
            self._ahead.discard(self.last_stored_seq)

    def overdue(self, now, timeout):
        """The first executing request whose result has not come back if no result of its batch came for
        longer than timeout per request still executing (a batch's results come together, once its
        checkpoint is acknowledged: its requests run one after the other, each bounded), else None."""
        if self.executing and now - self.started_at > timeout * len(self.executing):
            return next(iter(self.executing.values()))
        return None

    @property
    def current(self):
        """The first executing request whose result has not come back, or None when idle."""
        return next(iter(self.executing.values())) if self.executing else None

    # -- suspension -------------------------------------------------------------
    def hold(self):
        """Suspended (found quiescent): nothing new starts executing, not even after a promotion, until
        release(). An After captures a state transfer meanwhile: it must hold exactly the requests whose
        replies it carries (a promotion that executed the backup's queue under it broke that)."""
        self.holding = True

    def release(self, now):
        """Resumed: what was queued meanwhile starts."""
        self.holding = False
        return self._dispatch(now)

    # -- role -------------------------------------------------------------------
    def can_take_over(self, last_seq):
        """True when the replies of every checkpoint up to last_seq are stored (none missing below it)."""
        return self.last_stored_seq >= last_seq

    def set_role(self, role, now, epoch=0):
        """Change role (guarded); a new primary starts executing queued requests."""
        check_role_change(self.role, role)
        if self.role == Role.BACKUP and role != Role.BACKUP:
            self._drop_dealt_with()
        self.role = role
        self.epoch = max(self.epoch, epoch)
        return self._dispatch(now)

    def _refuse(self, request):
        """Bounded memory: push back (the client may retry) rather than grow or forget a reply."""
        self.stats.refused += 1
        self.refused[key(request)] = 'not executed: %s' % self.cache.why_full()
        return Refuse(request, self.refused[key(request)])

    def _highest_id(self, origin):
        """The highest id of origin this replica knows of (received, answered, or below its watermark)."""
        return max(self.watermarks.get(origin, 1) - 1, self.seen_high.get(origin, 0),
                   self.stored_high.get(origin, 0), self.cache.highest(origin))

    def _answer(self, reply, cached=False):
        if hasattr(reply, 'epoch'):
            reply.epoch = self.epoch    # answered in this configuration (a cached reply too)
        return Answer(reply, cached)

    # -- internals --------------------------------------------------------------
    def _forget_below(self, origin, watermark):
        """Proxy ``origin`` has the answer of every request below ``watermark`` (or gave up on it): forget
        those replies and refusals, and drop those requests if queued. A backup queues the requests its
        clients send while it is promoted; one of them may meanwhile be answered from a reply a checkpoint
        brought: executing it once promoted would apply it twice. The highest watermark of each origin is
        kept (Proxy ids grow across restarts): a copy arriving after it is dropped by on_request."""
        watermark = max(watermark, self.watermarks.get(origin, watermark))
        self.watermarks[origin] = watermark
        self.cache.forget_below(origin, watermark)
        if self.refused:
            for k in [k for k in self.refused if k[0] == origin and k[1] < watermark]:
                del self.refused[k]
        if self.queue and any(r.origin == origin and r.id < watermark for r in self.queue):
            kept = collections.deque()
            for r in self.queue:
                if r.origin == origin and r.id < watermark:
                    self.queued_keys.discard(key(r))
                    self.stats.dropped += 1
                else:
                    kept.append(r)
            self.queue = kept

    def _drop_dealt_with(self):
        """Taking over: drop the requests queued as a backup that its primary dealt with although their
        reply is not in the cache (the message that stored it was lost). A Proxy sends a request to
        both replicas over connections that keep its order, and a Protocol takes them in that order:
        once a reply to a later request of the same Proxy was stored, the earlier one's outcome was
        stored before it, or forgotten (its Proxy has it). Without losses nothing is dropped here; a
        Proxy still waiting for a dropped request sends it again, and it executes then."""
        kept = collections.deque()
        for r in self.queue:
            if r.id < self.stored_high.get(r.origin, r.id) and self.cache.lookup(key(r)) is None:
                self.queued_keys.discard(key(r))
                self.stats.dropped += 1
            else:
                kept.append(r)
        self.queue = kept

    def _dispatch(self, now):
        actions = []
        if self.role == Role.BACKUP or self.executing or self.holding:
            return actions
        while self.queue and len(self.executing) < self.max_batch:
            request = self.queue.popleft()
            k = key(request)
            self.queued_keys.discard(k)
            cached = self.cache.lookup(k)
            if cached is not None:
                # Queued while a backup, and executed by the old primary meanwhile.
                self.stats.cached_answers += 1
                actions.append(self._answer(cached, cached=True))
                continue
            if self.cache.full():   # queued while a backup: refused now, by the replica that serves
                actions.append(self._refuse(request))
                continue
            self.executing[k] = request
            self.stats.executed += 1
            actions.append(Forward(request))
        if self.executing:
            self.started_at = now
            self.batches += 1
            if self.max_batch > 1:   # else 0: the messages as they were before group commit
                batch = [a.request for a in actions if isinstance(a, Forward)]
                for i, request in enumerate(batch):
                    request.batch = (len(batch) - i, len(batch))
        return actions
