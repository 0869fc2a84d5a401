"""Calls that may hang (a stopped server, a frozen witness), made with a deadline.

rospy service calls have no timeout: a persistent connection to a process that stopped blocks the
caller for ever. :class:`Deadline` runs each call on its own worker thread and waits for it at most
``timeout``; a call past it raises :class:`CallTimeout` and is abandoned (its worker stays blocked in
the call and is never reused; a new worker serves the next call).
"""
import concurrent.futures

from ..errors import AftError


class CallTimeout(AftError):
    """A call did not return within its deadline; it may still complete later (``future``)."""

    def __init__(self, message, future=None):
        super(CallTimeout, self).__init__(message)
        self.future = future


class Deadline(object):
    def __init__(self, name='deadline'):
        self.name = name
        self._executor = None

    def call(self, function, timeout, *args, **kwargs):
        """function(*args, **kwargs), or CallTimeout after timeout seconds."""
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=self.name)
        future = self._executor.submit(function, *args, **kwargs)
        try:
            return future.result(timeout)
        except concurrent.futures.TimeoutError:
            # The worker is stuck in the call: leave it, and give the next call a fresh one.
            self._executor.shutdown(wait=False)
            self._executor = None
            raise CallTimeout('no answer within %.3f s' % timeout, future)
