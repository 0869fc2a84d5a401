"""Real-time priority for a short burst of work that must not be starved by the load it repairs.

A failover runs on a machine whose cores are busy with the very application it saves: measured with
scripts/bench_pbr, a Recovery node at the default priority spent 12-34 ms in fail-silence alone (its
signals and /proc reads waiting for a core), where the same calls take 5 ms on an idle machine. Under
SCHED_FIFO for the few milliseconds of a failover, it takes the core as soon as it is ready.
"""
import contextlib
import os


class RealtimeBurst(object):
    """``with burst():`` runs the block in the calling thread under SCHED_FIFO at ``priority``, and
    the thread goes back to its own policy after it. Threads and processes the block starts do not
    inherit it (SCHED_RESET_ON_FORK): a timer or a fence agent it starts runs at the usual priority.
    priority 0: off. A refusal (no CAP_SYS_NICE) is remembered in ``error`` and the block runs at the
    usual priority."""

    def __init__(self, priority):
        if not 0 <= priority <= 99:
            raise ValueError('real-time priority %r: give 0 (off) to 99' % (priority,))
        self.priority = priority
        self.error = None

    def check(self):
        """Try the priority once (and leave it at once): the error text if it is refused, else None."""
        with self():
            pass
        return self.error

    @contextlib.contextmanager
    def __call__(self):
        before = None
        if self.priority and self.error is None:
            try:
                before = (os.sched_getscheduler(0), os.sched_getparam(0))
                os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(self.priority))
            except OSError as e:
                before = None
                self.error = 'SCHED_FIFO %d refused: %s' % (self.priority, e)
        try:
            yield before is not None
        finally:
            if before is not None:
                os.sched_setscheduler(0, *before)
