"""Suspending a component for an adaptation (paper section 6.1): quiescence and buffering.

The paper's conditions for a consistent reconfiguration are that a component is stopped only
when quiescent (no request inside it) and that requests arriving at a stopped component are
buffered. The paper stops the process with SIGSTOP and leaves the buffering to ROS; a ROS
publisher's queue drops the oldest messages once ``queue_size`` is exceeded, and the kernel's
socket buffers only hide that for small messages (see scripts/bench_ros_buffering). Here the node
itself holds what arrives: a :class:`Gate` sits between a node's subscribers and its callbacks.

While the gate is closed, messages of the held ports are appended to an unbounded buffer instead
of being handled; messages of the other ports (results coming back, acknowledgments) still flow,
so that what is inside the component can finish. Opening the gate hands the held messages to
their callbacks in arrival order, before any message that arrives meanwhile.
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


# The allowed state changes of a gate, each with what causes it.
GATE_EDGES = {
    (GateState.OPEN, GateState.CLOSING): 'suspend asked',
    (GateState.CLOSING, GateState.CLOSED): 'the component is quiescent',
    (GateState.CLOSING, GateState.OPEN): 'not quiescent in time: the suspension is given up',
    (GateState.CLOSED, GateState.OPEN): 'resume asked: the held messages are delivered',
}


class Gate(object):
    """Holds the messages of some ports of a node while it is suspended.

    ``callbacks`` maps port names to the node's handlers; ``deliver(port, msg)`` is what the
    subscribers call. ``quiescent()`` (the node's own test, e.g. "no request executing") is
    checked, together with "no handler running", before the gate reports CLOSED.
    """

    def __init__(self, callbacks, log_error=None):
        self._callbacks = callbacks
        self._log_error = log_error or (lambda text: None)
        self._cond = threading.Condition()
        self._held = collections.deque()
        self._hold_ports = frozenset()
        self._active = 0
        self.state = GateState.OPEN
        self.delivered_late = 0     # messages held and delivered on resume, in all

    def _change_state(self, new):
        if (self.state, new) not in GATE_EDGES:
            raise SuspendError('gate state change %s -> %s is not allowed' % (self.state.name, new.name))
        self.state = new
        self._cond.notify_all()

    @property
    def held(self):
        with self._cond:
            return len(self._held)

    def deliver(self, port, msg):
        """A message arrived on port: hold it, or hand it to the port's handler."""
        with self._cond:
            if port in self._hold_ports:
                self._held.append((port, msg))
                return
            self._active += 1
        self._run(port, msg)

    def _run(self, port, msg):
        try:
            self._callbacks[port](msg)
        finally:
            with self._cond:
                self._active -= 1
                self._cond.notify_all()

    def close(self, ports, quiescent, timeout, clock=time.monotonic):
        """Hold ports and wait until nothing is inside (no handler running, quiescent() true).

        Returns the number of messages held so far. On timeout the gate opens again (held
        messages delivered) and SuspendError says what was still inside.
        """
        with self._cond:
            if self.state == GateState.CLOSED:
                return len(self._held)
            if self.state != GateState.OPEN:
                raise SuspendError('a suspension is already in progress')
            self._hold_ports = frozenset(ports)
            self._change_state(GateState.CLOSING)
            deadline = clock() + timeout
            while True:
                busy = self._active > 0
                if not busy and quiescent():
                    self._change_state(GateState.CLOSED)
                    return len(self._held)
                left = deadline - clock()
                if left <= 0:
                    break
                # Handlers notify when they finish; the node's own state (a timer applying a
                # checkpoint, say) is looked at again every 5 ms.
                self._cond.wait(min(left, 0.005))
        detail = 'a handler is still running' if busy else 'the component is not quiescent'
        self._open(GateState.OPEN)
        raise SuspendError('not quiescent within %.3f s (%s): resumed' % (timeout, detail))

    def open(self):
        """Deliver the held messages in arrival order, then handle messages as they come.
        Returns how many held messages were delivered."""
        with self._cond:
            if self.state == GateState.OPEN:
                return 0
        return self._open(GateState.OPEN)

    def _open(self, _target):
        delivered = 0
        while True:
            with self._cond:
                if not self._held:
                    # Only now do new messages bypass the buffer: none overtakes a held one.
                    self._hold_ports = frozenset()
                    if self.state != GateState.OPEN:
                        self._change_state(GateState.OPEN)
                    self.delivered_late += delivered
                    return delivered
                port, msg = self._held.popleft()
                self._active += 1
            try:
                self._run(port, msg)
            except Exception as e:   # one bad message must not keep the others held
                self._log_error('handler of port %s failed on a held message: %s' % (port, e))
            delivered += 1
