"""The adaptation engine's wait for a service: on the monotonic clock, and saying why it failed."""
import rospy

from aft_ftm.ros import adaptation_engine


class NoProvider(object):
    def __init__(self, caller):
        pass

    def lookupService(self, name):
        raise Exception('no provider for %s' % name)


class Provider(NoProvider):
    def lookupService(self, name):
        return 'rosrpc://127.0.0.1:1'


def never(name, timeout):
    never.calls.append(timeout)
    raise rospy.ROSException('timeout exceeded while waiting for service %s' % name)


def test_a_service_that_never_answers_is_waited_for_in_short_probes_then_said_why(monkeypatch):
    never.calls = []
    monkeypatch.setattr(adaptation_engine.rospy, 'wait_for_service', never)
    monkeypatch.setattr(adaptation_engine.rosgraph, 'Master', NoProvider)
    why = adaptation_engine.wait_for_service('/master/protocol/suspend', 0.3)
    assert why.startswith('no provider registered with the ROS master') and '/master/protocol/suspend' in why
    # Each probe is bounded by what is left, never by the wall clock's idea of the deadline.
    assert never.calls and all(0.05 <= t <= 0.3 for t in never.calls)
    monkeypatch.setattr(adaptation_engine.rosgraph, 'Master', Provider)
    assert adaptation_engine.wait_for_service('/x', 0.1) == 'its provider rosrpc://127.0.0.1:1 does not answer'


def test_a_service_that_answers_is_no_problem(monkeypatch):
    monkeypatch.setattr(adaptation_engine.rospy, 'wait_for_service', lambda name, timeout: None)
    assert adaptation_engine.wait_for_service('/x', 5.0) is None
