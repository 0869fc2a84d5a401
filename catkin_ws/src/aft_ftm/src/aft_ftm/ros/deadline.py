"""Calls that may hang (a stopped server, a frozen witness), made with a deadline.

rospy service calls have no timeout: a persistent connection to a process that stopped blocks the
caller for ever. :class:`Deadline` runs each call on its own worker thread and waits for it at most
``timeout``; a call past it raises :class:`CallTimeout` and is abandoned (its worker stays blocked in
the call and is never reused; a new worker serves the next call).

An abandoned call is not cancelled: the server may still carry it out later. For calls that change
state (a server's set_state), a later call overtaken by an abandoned one would be undone by it (an
older state landing after a newer one). ``Deadline(exclusive=True)`` therefore makes no call while
an abandoned one has not returned: it raises :class:`CallPending` at once instead.

A call of an open :class:`~aft_ftm.ros.persistent_service.PersistentService` needs no worker: it is
made in the caller's thread, its answer awaited at most the timeout
(:meth:`~aft_ftm.ros.persistent_service.PersistentService.call_within`), and past it abandoned the
same way (its future gets the late answer).
"""
import concurrent.futures
import queue
import threading
import time

from ..errors import AftError
from .persistent_service import Busy, LateAnswer, NotConnected


class CallTimeout(AftError):
    """A call did not return within its deadline; it may still complete later (``future``)."""

    def __init__(self, message, future=None):
        super(CallTimeout, self).__init__(message)
        self.future = future


class CallPending(CallTimeout):
    """A call abandoned past its deadline has not returned yet (it may still take effect): no other
    call is made until it has (Deadline(exclusive=True))."""


class _DaemonWorker(object):
    """One worker thread for a Deadline's calls, a daemon: ThreadPoolExecutor's workers are joined when
    the interpreter exits, so a call abandoned past its deadline, blocked in recv on a hung server,
    kept a stopped node alive until roslaunch's SIGKILL (review of session 36)."""

    def __init__(self, name):
        self._queue = queue.Queue()
        threading.Thread(target=self._run, name='%s-worker' % name, daemon=True).start()

    def submit(self, function, *args, **kwargs):
        future = concurrent.futures.Future()
        self._queue.put((future, function, args, kwargs))
        return future

    def shutdown(self, wait=False):
        self._queue.put(None)   # (the call in progress, if any, is left to end when it ends)

    def _run(self):
        while True:
            item = self._queue.get()
            if item is None:
                return
            future, function, args, kwargs = item
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(function(*args, **kwargs))
            except BaseException as e:   # handed to the caller
                future.set_exception(e)


def _not_sent(why):
    """The CallTimeout of a call that was never sent: its future says so (a caller waiting on it must
    not wait for ever)."""
    busy = concurrent.futures.Future()
    busy.set_exception(CallTimeout(why))
    return CallTimeout(why, busy)


class Deadline(object):
    def __init__(self, name='deadline', exclusive=False):
        self.name = name
        self.exclusive = exclusive
        self._executor = None
        self._abandoned = None   # exclusive: the future of the last call abandoned, until it returns
        self._lock = threading.Lock()   # the worker, for callers in several threads
        self._exclusive = threading.Lock()   # exclusive: one call at a time

    def call(self, function, timeout, *args, **kwargs):
        """function(*args, **kwargs), or CallTimeout after timeout seconds (CallPending at once, if
        exclusive and an abandoned call has not returned)."""
        if not self.exclusive:
            return self._call(function, timeout, *args, **kwargs)
        # Exclusive: one call at a time, so that a call abandoned by one caller is recorded before
        # another caller checks for it.
        end = time.monotonic() + timeout
        if not self._exclusive.acquire(timeout=timeout):
            raise _not_sent('%s: another call did not return within %.3f s' % (self.name, timeout))
        try:
            return self._call(function, max(0.0, end - time.monotonic()), *args, **kwargs)
        finally:
            self._exclusive.release()

    def _call(self, function, timeout, *args, **kwargs):
        end = time.monotonic() + timeout
        if getattr(function, 'can_call_within', False):
            self._check_abandoned()
            try:
                return function.call_within(timeout, *args, **kwargs)
            except LateAnswer as e:
                if self.exclusive:
                    self._abandoned = e.future
                raise CallTimeout('no answer within %.3f s' % timeout, e.future)
            except Busy as e:
                raise _not_sent('%s: %s' % (self.name, e))
            except NotConnected:
                # Another caller's late answer took the connection meanwhile: the worker's way, which
                # opens a new one, in the time left.
                timeout = max(0.0, end - time.monotonic())
        self._check_abandoned()
        with self._lock:   # submitted here: another caller's timeout may shut this executor down
            if self._executor is None:
                self._executor = _DaemonWorker(self.name)
            executor = self._executor
            future = executor.submit(function, *args, **kwargs)
        try:
            return future.result(timeout)
        except concurrent.futures.TimeoutError:
            # The worker is stuck in the call: leave it, and give the next call a fresh one.
            with self._lock:
                if self._executor is executor:
                    executor.shutdown(wait=False)
                    self._executor = None
            if self.exclusive:
                self._abandoned = future
            raise CallTimeout('no answer within %.3f s' % timeout, future)

    def close(self):
        """End the worker once its call in progress, if any, is done (a Deadline made for a few calls)."""
        with self._lock:
            executor, self._executor = self._executor, None
        if executor is not None:
            executor.shutdown(wait=False)

    def abandoned(self):
        """exclusive: the future of a call abandoned past its deadline that has not returned yet (it may
        still take effect), or None."""
        abandoned = self._abandoned
        return abandoned if abandoned is not None and not abandoned.done() else None

    def _check_abandoned(self):
        """CallPending if exclusive and a call abandoned past its deadline has not returned yet."""
        abandoned = self._abandoned
        if abandoned is not None:
            if not abandoned.done():
                raise CallPending('%s: a call abandoned past its deadline has not returned yet, and may still '
                                  'take effect: no other call until it has' % self.name, abandoned)
            self._abandoned = None
