"""The Proxy's bookkeeping: request ids, pending requests, re-sends.

Ids start from the wall-clock time in microseconds so that a restarted Proxy never
reuses an id still remembered by a Protocol's duplicate cache.
"""
import threading


class Pending(object):
    """One request waiting for its reply."""
    __slots__ = ('id', 'client', 'payload', 'sent_at', 'sends', 'reply', 'done')

    def __init__(self, request_id, client, payload, now):
        self.id = request_id
        self.client = client
        self.payload = payload
        self.sent_at = now
        self.sends = 1
        self.reply = None
        self.done = threading.Event()


class PendingTable(object):
    """Requests sent and not yet answered. Thread-safe: service calls run in parallel."""

    def __init__(self, first_id):
        self._lock = threading.Lock()
        self._next = first_id
        self._pending = {}
        self.late_replies = 0     # replies to requests already answered (duplicates)
        self.resends = 0

    def open(self, client, payload, now):
        """Register a new request; returns its Pending entry."""
        with self._lock:
            entry = Pending(self._next, client, payload, now)
            self._pending[entry.id] = entry
            self._next += 1
            return entry

    def close(self, request_id, reply):
        """A reply arrived. Returns the entry it answers, or None for a late duplicate."""
        with self._lock:
            entry = self._pending.pop(request_id, None)
            if entry is None:
                self.late_replies += 1
                return None
        entry.reply = reply
        entry.done.set()
        return entry

    def abandon(self, request_id):
        """The caller gave up (timeout): stop re-sending it."""
        with self._lock:
            return self._pending.pop(request_id, None)

    def oldest_pending(self):
        """Every id below this one has been answered (or abandoned)."""
        with self._lock:
            return min(self._pending) if self._pending else self._next

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
