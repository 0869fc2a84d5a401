"""The car's scenario command and SIGTERM (a test's time limit, a supervisor), without ROS: the signal
ends the run wherever its main thread is, once, and never in the middle of the run's stop (raised
there, it left the master, the recorder or a board running; review of session 50)."""
import signal

import pytest

from tjp_sim.ros.scenario_command import Deferred, Terminated


def test_sigterm_raises_once_and_is_no_exception_a_broad_except_swallows():
    signals = Deferred()
    with pytest.raises(Terminated):
        try:
            signals.terminated(signal.SIGTERM, None)
        except Exception:   # what the set-up's waits do around a master call
            pytest.fail('the signal was swallowed by an except Exception')
    signals.terminated(signal.SIGTERM, None)   # a second one: the stop the first started goes on


def test_sigterm_during_the_stop_is_held_until_the_stop_is_done():
    signals = Deferred()
    stopped = []
    with pytest.raises(Terminated):
        with signals.deferred():
            signals.terminated(signal.SIGTERM, None)   # nothing raised here
            stopped.append('every process')
    assert stopped == ['every process']


def test_a_stop_after_the_signal_raised_adds_nothing():
    signals = Deferred()
    with pytest.raises(Terminated):
        signals.terminated(signal.SIGTERM, None)
    with signals.deferred():   # the run's finally: the stop, the signal already raised
        signals.terminated(signal.SIGTERM, None)
