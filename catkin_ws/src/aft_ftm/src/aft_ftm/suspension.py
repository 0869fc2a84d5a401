"""Suspending a component for an adaptation (paper section 6.1): quiescence and buffering.

The paper's conditions for a consistent reconfiguration are that a component is stopped only
when quiescent (no request inside it) and that requests arriving at a stopped component are
buffered. The paper stops the process with SIGSTOP and leaves the buffering to ROS; a ROS
publisher's queue drops the oldest messages once ``queue_size`` is exceeded, and the kernel's
socket buffers only hide that for small messages (see scripts/bench_ros_buffering). Here the node
itself holds what arrives: a :class:`Gate` sits between a node's subscribers and its callbacks.

While the gate is closed, messages of the held ports are appended to a buffer instead of being
handled; messages of the other ports (results coming back, acknowledgments) still flow, so that
what is inside the component can finish. Opening the gate hands the held messages to their
callbacks in arrival order, before any message that arrives meanwhile.

A suspension cannot strand the component:

- it carries a lease: unless resumed or renewed within it, the gate resumes by itself (whoever
  suspended it may have died, or been stopped, in the middle of an adaptation);
- the buffer is bounded in bytes: the message that would exceed the bound ends the suspension
  (every held message delivered in order, that one last), it is never dropped.

Either way the node is told (``on_self_resume``) and raises an alarm: no degraded state is silent.
Every state change is an edge of :data:`GATE_EDGES`; ``now`` is passed in (or a clock, to wait).
"""
import collections
import enum
import threading
import time

from .errors import AftError


class SuspendError(AftError):
    """A component could not be suspended (not quiescent in time); it runs on as before."""


class GateState(enum.Enum):
    OPEN = 0         # messages are handled as they arrive
    CLOSING = 1      # held ports buffer; waiting until nothing is inside the component
    CLOSED = 2       # quiescent: held ports buffer, nothing runs on their behalf
    OPENING = 3      # the held messages are being delivered; new ones still queue behind them


class Event(enum.Enum):
    """What makes a gate change state."""
    SUSPEND = 'suspend'
    QUIESCENT = 'quiescent'
    TIMEOUT = 'timeout'
    RESUME = 'resume'
    LEASE_EXPIRED = 'lease_expired'
    BUFFER_FULL = 'buffer_full'
    DELIVERED = 'delivered'


# The allowed state changes of a gate: (state, event) -> (new state, why). Nothing else changes it.
# The longest lease a suspension may carry (s). Every suspension carries one so that a node whose
# suspender died resumes by itself; an infinite or huge one (adapt --lease inf, a ~suspend call with
# lease 1e10) never ran out, and a suspender killed in the pause left the node suspended for good,
# unsaid (review of session 48).
MAX_LEASE = 600.0


GATE_EDGES = {
    (GateState.OPEN, Event.SUSPEND):
        (GateState.CLOSING, 'suspend asked: the held ports buffer from now on'),
    (GateState.CLOSING, Event.QUIESCENT):
        (GateState.CLOSED, 'the component is quiescent: the lease starts'),
    (GateState.CLOSING, Event.TIMEOUT):
        (GateState.OPENING, 'not quiescent in time: the suspension is given up'),
    (GateState.CLOSING, Event.RESUME):
        (GateState.OPENING, 'resume asked while suspending: the suspension is given up'),
    (GateState.CLOSING, Event.BUFFER_FULL):
        (GateState.OPENING, 'buffer full before quiescence: the suspension is given up'),
    (GateState.CLOSED, Event.RESUME):
        (GateState.OPENING, 'resume asked: the held messages are delivered'),
    (GateState.CLOSED, Event.LEASE_EXPIRED):
        (GateState.OPENING, 'lease expired (no resume nor renewal in time): resumes by itself'),
    (GateState.CLOSED, Event.BUFFER_FULL):
        (GateState.OPENING, 'buffer full: the suspension is given up rather than drop a message'),
    (GateState.OPENING, Event.DELIVERED):
        (GateState.OPEN, 'every held message delivered: new ones are handled as they arrive'),
}

# The events by which a gate ends a suspension on its own: the node raises an alarm for each.
SELF_RESUMING = (Event.LEASE_EXPIRED, Event.BUFFER_FULL)


def approx_size(msg):
    """A rough estimate of a message's serialized size in bytes, never much below it: the
    lengths of its byte and string fields, 8 bytes per number, through nested messages and
    arrays (the fields of a genpy message are its ``__slots__``). Cheap for a ``uint8[]`` payload
    (a bytes object) and for arrays of numbers."""
    if msg is None:
        return 0
    if isinstance(msg, (bytes, bytearray, str)):
        return 4 + len(msg)
    if isinstance(msg, (bool, int, float)):
        return 8
    if isinstance(msg, (list, tuple)):
        if msg and isinstance(msg[0], (bool, int, float)):
            return 4 + 8 * len(msg)
        return 4 + sum(approx_size(item) for item in msg)
    slots = getattr(type(msg), '__slots__', None)
    if slots:
        return sum(approx_size(getattr(msg, name, None)) for name in slots)
    fields = getattr(msg, '__dict__', None)
    if fields:
        return sum(approx_size(value) for value in fields.values())
    return 8


class Gate(object):
    """Holds the messages of some ports of a node while it is suspended.

    ``callbacks`` maps port names to the node's handlers; ``deliver(port, msg)`` is what the
    subscribers call. ``quiescent()`` (the node's own test, e.g. "no request executing") is
    checked, together with "no handler running", before the gate reports CLOSED.

    A suspension may carry a lease (seconds): once CLOSED, the gate resumes by itself if it is
    neither resumed nor renewed (:meth:`renew`) before the lease runs out (:meth:`expire`, which
    the node calls with the time now). The held buffer is bounded by ``max_bytes`` (None:
    unbounded), counted with ``size(msg)``: the message that would exceed it makes the gate give
    the suspension up (every held message is delivered, that one last) rather than drop it.
    ``on_self_resume(event, detail)`` is told each time the gate ends a suspension on its own
    (:data:`SELF_RESUMING`), after the held messages are delivered.

    A suspension may name its ``owner`` (an adaptation's own token; '' for none, as an operator's):
    while one owner holds the gate, another's close, renew and open are refused (SuspendError). Two
    engines each took the other's suspension for its own, and a resume by one ended the other's
    pause in the middle of its rebinds with nothing said (review of stop 39). An open without an
    owner (an operator's) still opens any suspension: the owner finds out at its own resume
    (:meth:`suspended_by`).
    """

    def __init__(self, callbacks, log_error=None, size=approx_size, max_bytes=None, on_self_resume=None):
        self._callbacks = callbacks
        self._log_error = log_error or (lambda text: None)
        self._size = size
        self.max_bytes = max_bytes
        self._on_self_resume = on_self_resume or (lambda event, detail: None)
        self._cond = threading.Condition()
        self._held = collections.deque()
        self._held_bytes = 0
        self._hold_ports = frozenset()
        self._active = 0
        self._lease = None            # s, of the current suspension (None: until resumed)
        self._lease_until = None      # when it runs out (the clock of close(), renew(), expire())
        self.state = GateState.OPEN
        self.owner = ''               # who holds the current suspension ('' none named, or not suspended)
        self.last_end = ''            # why the last suspension ended (the reason of its edge)
        self.delivered_late = 0       # messages held and delivered on resume, in all
        self.self_resumed = 0         # suspensions the gate ended on its own (lease, buffer)

    def _change(self, event):
        """The one place where the state changes; returns why (the edge's reason)."""
        edge = GATE_EDGES.get((self.state, event))
        if edge is None:
            raise SuspendError('gate: %s is not allowed in state %s' % (event.value, self.state.name))
        self.state, reason = edge
        if self.state == GateState.OPENING:
            self.last_end = reason
            self._lease = self._lease_until = None
            self.owner = ''
        self._cond.notify_all()
        return reason

    @property
    def held(self):
        with self._cond:
            return len(self._held)

    @property
    def held_bytes(self):
        with self._cond:
            return self._held_bytes

    def lease_left(self, now):
        """Seconds left of the current suspension's lease; None if no lease runs (not CLOSED, or
        suspended without one)."""
        with self._cond:
            if self.state != GateState.CLOSED or self._lease_until is None:
                return None
            return self._lease_until - now

    def deliver(self, port, msg):
        """A message arrived on port: hold it, or hand it to the port's handler."""
        with self._cond:
            if port in self._hold_ports:
                size = self._size(msg)
                full = (self.max_bytes is not None and self.state in (GateState.CLOSING, GateState.CLOSED)
                        and self._held_bytes + size > self.max_bytes)
                self._held.append((port, msg))
                self._held_bytes += size
                if not full:
                    return
                # Queued last, behind every held message: the order is kept and nothing is dropped.
                detail = ('%d held messages, %d bytes with this one, over the bound of %d bytes'
                          % (len(self._held), self._held_bytes, self.max_bytes))
                self._change(Event.BUFFER_FULL)
            else:
                self._active += 1
                detail = None
        if detail is None:
            self._run(port, msg)
            return
        delivered = self._drain()
        self.self_resumed += 1
        self._on_self_resume(Event.BUFFER_FULL, 'buffer full (%s): suspension given up, %d held messages '
                             'delivered' % (detail, delivered))

    def _run(self, port, msg):
        try:
            self._callbacks[port](msg)
        finally:
            with self._cond:
                self._active -= 1
                self._cond.notify_all()

    def _check_owner(self, owner, what):
        """SuspendError if another owner holds the suspension (caller holds the lock)."""
        if owner and self.owner and owner != self.owner and self.state in (GateState.CLOSING, GateState.CLOSED):
            raise SuspendError('suspended by %s: not %s\'s to %s' % (self.owner, owner, what))

    def suspended_by(self, owner):
        """Whether the gate is suspended (CLOSED) by ``owner`` now."""
        with self._cond:
            return self.state == GateState.CLOSED and self.owner == owner

    def close(self, ports, quiescent, timeout, clock=time.monotonic, lease=None, owner=''):
        """Hold ports and wait until nothing is inside (no handler running, quiescent() true).

        Returns the number of messages held so far. On timeout the gate opens again (held
        messages delivered) and SuspendError says what was still inside. ``lease`` (s, None for
        none) starts once CLOSED, on ``clock``; closing a CLOSED gate only sets its lease anew
        (refused if another ``owner`` holds it).
        """
        with self._cond:
            self._check_owner(owner, 'suspend')
            if self.state == GateState.CLOSED:
                self._set_lease(lease, clock())
                if owner and not self.owner:
                    self.owner = owner
                return len(self._held)
            if self.state == GateState.CLOSING:
                raise SuspendError('a suspension is already in progress')
            if self.state == GateState.OPENING:
                raise SuspendError('still delivering the messages held by the last suspension: try again')
            self._hold_ports = frozenset(ports)
            self._change(Event.SUSPEND)
            self.owner = owner
            deadline = clock() + timeout
            while True:
                if self.state != GateState.CLOSING:   # given up meanwhile (buffer full, resume asked)
                    raise SuspendError('suspension given up before quiescence: %s' % self.last_end)
                busy = self._active > 0
                if not busy and quiescent():
                    self._change(Event.QUIESCENT)
                    self._set_lease(lease, clock())
                    return len(self._held)
                left = deadline - clock()
                if left <= 0:
                    break
                # Handlers notify when they finish; the node's own state (a timer applying a
                # checkpoint, say) is looked at again every 5 ms.
                self._cond.wait(min(left, 0.005))
            self._change(Event.TIMEOUT)
        detail = 'a handler is still running' if busy else 'the component is not quiescent'
        self._drain()
        raise SuspendError('not quiescent within %.3f s (%s): resumed' % (timeout, detail))

    def _set_lease(self, lease, now):
        self._lease = lease
        self._lease_until = None if lease is None else now + lease

    def renew(self, lease, now, owner=''):
        """Extend the current suspension's lease to ``now + lease``; change nothing else. Returns
        the messages held. SuspendError if the gate is not suspended (saying how it ended), or
        suspended by another owner."""
        with self._cond:
            self._check_owner(owner, 'renew')
            if owner and self.state == GateState.CLOSED and self.owner != owner:
                # Suspended again by nobody named (a join's quiescence, an operator) after this owner's
                # suspension ended: not this owner's suspension, whatever it looks like.
                raise SuspendError('suspended by %s, not by %s: its suspension ended meanwhile (%s)'
                                   % (self.owner or 'someone else', owner, self.last_end or 'resumed'))
            if self.state != GateState.CLOSED:
                ended = ' (last suspension: %s)' % self.last_end if self.last_end else ''
                raise SuspendError('not suspended (%s): nothing to renew%s' % (self.state.name, ended))
            self._set_lease(lease, now)
            return len(self._held)

    def expire(self, now):
        """If the lease has run out at ``now``, resume by itself. Returns the held messages
        delivered, or None if the lease still runs (or none does)."""
        with self._cond:
            if self.state != GateState.CLOSED or self._lease_until is None or now < self._lease_until:
                return None
            lease, late = self._lease, now - self._lease_until
            self._change(Event.LEASE_EXPIRED)
        delivered = self._drain()
        self.self_resumed += 1
        self._on_self_resume(Event.LEASE_EXPIRED, 'lease of %.3g s expired (%.3f s ago) with neither resume nor '
                             'renewal: resumed by itself, %d held messages delivered' % (lease, late, delivered))
        return delivered

    def open(self, owner=''):
        """Deliver the held messages in arrival order, then handle messages as they come.
        Returns how many held messages were delivered (0 if another caller is delivering them).
        SuspendError if another ``owner`` holds the suspension (nothing changes)."""
        with self._cond:
            self._check_owner(owner, 'resume')
            if self.state in (GateState.OPEN, GateState.OPENING):
                return 0
            self._change(Event.RESUME)
        return self._drain()

    def _drain(self):
        """Deliver the held messages (the gate is OPENING: this caller alone does it), then open."""
        delivered = 0
        while True:
            with self._cond:
                if not self._held:
                    # Only now do new messages bypass the buffer: none overtakes a held one.
                    self._hold_ports = frozenset()
                    self._held_bytes = 0
                    self._change(Event.DELIVERED)
                    self.delivered_late += delivered
                    return delivered
                port, msg = self._held.popleft()
                self._active += 1
            try:
                self._run(port, msg)
            except Exception as e:   # one bad message must not keep the others held
                self._log_error('handler of port %s failed on a held message: %s' % (port, e))
            delivered += 1
