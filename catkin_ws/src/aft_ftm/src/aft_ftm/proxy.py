"""The Proxy's bookkeeping: request ids, pending requests, re-sends.

Ids start from the wall-clock time in microseconds so that a restarted Proxy never
reuses an id still remembered by a Protocol's duplicate cache.
"""
import threading

from .errors import AftError


class Full(AftError):
    """The pending table is at its bound in bytes: the request is not sent (nothing was executed)."""


class Pending(object):
    """One request waiting for its reply."""
    __slots__ = ('id', 'client', 'payload', 'sent_at', 'opened_at', 'sends', 'reply', 'done')

    def __init__(self, request_id, client, payload, now):
        self.id = request_id
        self.client = client
        self.payload = payload
        self.sent_at = now
        self.opened_at = now      # sent_at moves with each re-send; this stays
        self.sends = 1
        self.reply = None
        self.done = threading.Event()


class PendingTable(object):
    """Requests sent and not yet answered. Thread-safe: service calls run in parallel."""

    def __init__(self, first_id, max_bytes=0):
        self._lock = threading.Lock()
        self._next = first_id
        self._pending = {}
        self.max_bytes = max_bytes    # 0: no bound
        self.bytes = 0
        self.late_replies = 0     # replies to requests already answered (duplicates)
        self.stale_replies = 0    # replies from a configuration older than one already seen
        self.resends = 0
        self.refused = 0
        self.renumbered = 0       # requests sent again under a new id (ids below those answered already)
        self.epoch = 0            # the newest configuration epoch a reply came from

    def open(self, client, payload, now):
        """Register a new request; returns its Pending entry. Raises Full at the bound in bytes."""
        with self._lock:
            size = len(payload) + 64
            if self.max_bytes and self.bytes + size > self.max_bytes:
                self.refused += 1
                raise Full('not executed: %d requests (%d bytes) wait for their replies, the bound is %d bytes'
                           % (len(self._pending), self.bytes, self.max_bytes))
            entry = Pending(self._next, client, payload, now)
            self._pending[entry.id] = entry
            self.bytes += size
            self._next += 1
            return entry

    def fresh(self, epoch):
        """A reply of configuration epoch arrived: False (and counted) if it is older than one already seen,
        the answer of a replica that no longer serves. 0: a mechanism without epochs."""
        with self._lock:
            if epoch and epoch < self.epoch:
                self.stale_replies += 1
                return False
            self.epoch = max(self.epoch, epoch)
            return True

    def close(self, request_id, reply):
        """A reply arrived. Returns the entry it answers, or None for a late duplicate."""
        with self._lock:
            entry = self._pending.pop(request_id, None)
            if entry is None:
                self.late_replies += 1
                return None
            self.bytes -= len(entry.payload) + 64
        entry.reply = reply
        entry.done.set()
        return entry

    def abandon(self, entry):
        """The caller gave up (timeout): stop re-sending its entry. Returns it, or None if it was answered
        meanwhile (its reply is being handed over). By the entry, not its id: a renumber may change that."""
        with self._lock:
            if self._pending.get(entry.id) is not entry:
                return None
            del self._pending[entry.id]
            self.bytes -= len(entry.payload) + 64
            return entry

    def renumber(self, request_id, first_id):
        """The replicas answered ids up to first_id - 1 already (this Proxy started again, under the same
        name, with a clock behind its predecessor's), and did not execute request_id: the waiting entry
        takes a new id, from first_id on, as do the requests opened after it. Returns the entry, or None
        if request_id does not wait (answered already: the message is a late one) or first_id is not
        above it or past 2**63 (no replica says so)."""
        with self._lock:
            entry = self._pending.get(request_id)
            if entry is None or not request_id < first_id < 1 << 63:
                return None
            del self._pending[request_id]
            self._next = max(self._next, first_id)
            entry.id = self._next
            self._next += 1
            self._pending[entry.id] = entry
            self.renumbered += 1
            return entry

    def unrenumbered(self, request_id, first_id):
        """Why a refusal of request_id's id naming first_id could not be followed, if that leaves the call
        waiting (None when request_id no longer waits: a late message). A replica that says the ids up to
        first_id - 1 were answered, when first_id is not above the waiting request's id or is past 2**63,
        cannot be believed and cannot be obeyed: the call waits for its timeout, and that must be said
        (a forged ``oldest_pending`` without SEC raises the replicas' watermark so)."""
        with self._lock:
            if request_id not in self._pending:
                return None
        return ('request %d waits, and its replicas refuse its id as below those they answered already, naming %d '
                'as the first free one, which is %s: it cannot be renumbered, and the call waits for its timeout '
                '(the replicas hold a watermark this Proxy never sent: forged without SEC, or corrupt)'
                % (request_id, first_id, 'past 2**63' if first_id >= 1 << 63 else 'not above it'))

    def oldest_pending(self):
        """Every id below this one has been answered (or abandoned)."""
        with self._lock:
            return min(self._pending) if self._pending else self._next

    def oldest_age(self, now):
        """How long the oldest unanswered request has waited (s), or None if none waits."""
        with self._lock:
            return max((now - e.opened_at for e in self._pending.values()), default=None)

    def due(self, now, period):
        """Entries to send again: all of them if period is 0, else those not sent for period."""
        with self._lock:
            entries = [e for e in self._pending.values() if period == 0 or now - e.sent_at >= period]
            for entry in entries:
                entry.sent_at = now
                entry.sends += 1
            self.resends += len(entries)
            return sorted(entries, key=lambda e: e.id)

    def __len__(self):
        with self._lock:
            return len(self._pending)
