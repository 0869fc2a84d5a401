"""The programs ``on_failure: run`` starts, watched to their end. No rospy.

The manager starts a failure program and goes on supervising: it must not wait for it. But a program
that fails (exits non-zero, or cannot be started) did not do what the operator configured, and one
that hangs holds whatever it holds for ever; both must be said, and a hung one must end. Each
program runs in a session of its own (its process group is its pid), so that ending it ends every
process it started. :class:`Programs` keeps them: :meth:`Programs.check` reaps those that ended and
kills those past their ``program_timeout``, and returns what to report. ``now`` is always passed in
(monotonic seconds).
"""
import collections
import os
import signal
import subprocess

# One outcome to report: the service, the fault that started the program, what happened, and whether
# it is a failure of the program (an alarm) or its normal end.
Outcome = collections.namedtuple('Outcome', 'service fault failed detail')

_Running = collections.namedtuple('_Running', 'service fault argv popen started deadline killed')


class Programs(object):
    """The failure programs running. ``popen``: subprocess.Popen (a stand-in in tests)."""

    def __init__(self, popen=subprocess.Popen):
        self.popen = popen
        self.running = []
        self.started = self.failed = self.timed_out = 0

    def start(self, service, fault, argv, env, now, timeout):
        """Start ``argv`` for ``service``'s fault; returns an Outcome if it could not start (else None)."""
        try:
            proc = self.popen(argv, env=env, stdin=subprocess.DEVNULL, start_new_session=True)
        except (OSError, ValueError) as e:
            self.failed += 1
            return Outcome(service, fault, True, 'the failure program %s of %s could not start: %s'
                           % (' '.join(argv), service, e))
        self.started += 1
        self.running.append(_Running(service, fault, list(argv), proc, now, now + timeout, False))
        return None

    def next_deadline(self):
        """The earliest timeout of a program running (None: none runs). A program's end is seen at the
        manager's next wake; the caller wakes at least once a second while one runs."""
        return min((r.deadline for r in self.running if not r.killed), default=None)

    def check(self, now):
        """Reap the programs that ended, end those past their timeout. Returns [Outcome]."""
        outcomes, still = [], []
        for r in self.running:
            code = r.popen.poll()
            if r.killed:   # said already: kept only until it is reaped (no wait in the manager's loop)
                if code is None:
                    still.append(r)
                continue
            if code is None and now >= r.deadline:
                self._end(r.popen)
                still.append(r._replace(killed=True, deadline=float('inf')))
                self.timed_out += 1
                self.failed += 1
                outcomes.append(Outcome(r.service, r.fault, True, 'the failure program %s of %s was still running '
                                        'after %.1f s: killed (its whole session)'
                                        % (' '.join(r.argv), r.service, now - r.started)))
            elif code is None:
                still.append(r)
            elif code != 0:
                self.failed += 1
                outcomes.append(Outcome(r.service, r.fault, True, 'the failure program %s of %s exited with %s'
                                        % (' '.join(r.argv), r.service, _status(code))))
            else:
                outcomes.append(Outcome(r.service, r.fault, False, 'the failure program %s of %s ran (%.1f s)'
                                        % (' '.join(r.argv), r.service, now - r.started)))
        self.running = still
        return outcomes

    def end_all(self):
        """The manager shuts down: every program still running ends with it (none outlives it unseen).
        Returns how many were running."""
        ended = [r for r in self.running if not r.killed and r.popen.poll() is None]
        for r in ended:
            self._end(r.popen)
        self.running = []
        return len(ended)

    @staticmethod
    def _end(popen):
        """SIGKILL to the program's whole session (its process group: its pid); reaped at a later check."""
        try:
            os.killpg(popen.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


def _status(code):
    return 'signal %d' % -code if code < 0 else 'status %d' % code
