"""Real-time priority for a short burst of work that must not be starved by the load it repairs.

A failover runs on a machine whose cores are busy with the very application it saves: measured with
scripts/bench_pbr, a Recovery node at the default priority spent 12-34 ms in fail-silence alone (its
signals and /proc reads waiting for a core), where the same calls take 5 ms on an idle machine. Under
SCHED_FIFO for the few milliseconds of a failover, it takes the core as soon as it is ready.
"""
import contextlib
import os


class RealtimeBurst(object):
    """``with burst():`` runs the block, and the threads it starts (they inherit the policy), under
    SCHED_FIFO at ``priority``; the calling thread goes back to SCHED_OTHER after it. priority 0: off.
    A refusal (no CAP_SYS_NICE) is remembered in ``error`` and the block runs at the usual priority."""

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
        boosted = False
        if self.priority and self.error is None:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.priority))
                boosted = True
            except OSError as e:
                self.error = 'SCHED_FIFO %d refused: %s' % (self.priority, e)
        try:
            yield boosted
        finally:
            if boosted:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
