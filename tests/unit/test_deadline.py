"""Calls with a deadline (aft_ftm.ros.deadline): an abandoned call may still land later, so an
exclusive Deadline makes no other call until it has returned. No ROS master."""
import threading
import time

import pytest

from aft_ftm.ros.deadline import CallPending, CallTimeout, Deadline


class SlowServer(object):
    """A state that set() replaces; a call blocks while `held` is clear (a hung server)."""

    def __init__(self):
        self.state = 'S0'
        self.held = threading.Event()
        self.held.set()
        self.applied = []

    def set(self, state):
        self.held.wait(10.0)
        self.state = state
        self.applied.append(state)
        return state


def test_a_call_within_its_deadline_returns_its_value():
    assert Deadline('t').call(lambda x: x * 2, 1.0, 21) == 42


def test_an_exclusive_deadline_makes_no_call_while_an_abandoned_one_may_still_land():
    server, deadline = SlowServer(), Deadline('state', exclusive=True)
    server.held.clear()
    with pytest.raises(CallTimeout) as abandoned:
        deadline.call(server.set, 0.05, 'S1')
    assert not isinstance(abandoned.value, CallPending)
    # A newer state now would be overtaken by S1 when the server thaws: refused at once.
    with pytest.raises(CallPending, match='may still take effect'):
        deadline.call(server.set, 5.0, 'S2')
    assert server.applied == []
    assert deadline.abandoned() is abandoned.value.future   # what a promotion waits for (PBR's After)
    server.held.set()
    abandoned.value.future.result(5.0)
    assert deadline.abandoned() is None
    assert deadline.call(server.set, 5.0, 'S2') == 'S2'
    assert server.applied == ['S1', 'S2'] and server.state == 'S2'


def test_without_exclusivity_the_late_call_overtakes_the_newer_one():
    """What exclusivity prevents: the abandoned S1 lands after S2 and the server ends on the older state."""
    server, deadline = SlowServer(), Deadline('state')
    server.held.clear()
    with pytest.raises(CallTimeout) as abandoned:
        deadline.call(server.set, 0.05, 'S1')
    second = threading.Thread(target=lambda: deadline.call(server.set, 5.0, 'S2'))
    second.start()
    server.held.set()
    second.join(5.0)
    abandoned.value.future.result(5.0)
    assert sorted(server.applied) == ['S1', 'S2']   # both ran: the order is the threads', not the caller's


def test_an_abandoned_call_that_failed_still_frees_the_deadline():
    deadline, gate = Deadline('state', exclusive=True), threading.Event()

    def fails():
        gate.wait(5.0)
        raise RuntimeError('the server refused the state')
    with pytest.raises(CallTimeout) as abandoned:
        deadline.call(fails, 0.05)
    gate.set()
    with pytest.raises(RuntimeError):
        abandoned.value.future.result(5.0)
    assert deadline.call(lambda: 'ok', 1.0) == 'ok'


def test_a_call_abandoned_past_its_deadline_does_not_keep_the_process_from_exiting():
    """Review of session 36: the worker was a ThreadPoolExecutor's, joined at interpreter exit: a call
    blocked on a hung server kept a stopped node alive until roslaunch's SIGKILL."""
    import subprocess
    import sys
    code = ('import sys, threading, time\nsys.path[:0] = %r\n'
            'from aft_ftm.ros.deadline import CallTimeout, Deadline\n'
            'try:\n    Deadline("hung").call(threading.Event().wait, 0.1)\nexcept CallTimeout:\n    print("abandoned")\n'
            % sys.path)
    started = time.monotonic()
    run = subprocess.run([sys.executable, '-c', code], stdout=subprocess.PIPE, timeout=30)
    assert run.stdout.strip() == b'abandoned' and run.returncode == 0
    assert time.monotonic() - started < 10.0
