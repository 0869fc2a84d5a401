"""Services waited for or asked with care: the adaptation engine's wait (monotonic clock, why it failed), and
a replica node's question to its crash detector before a hang fail-stops its site."""
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


# -- a replica node asks its site's crash detector about the peer (aft_ftm.ros.peer_check) ----------

def test_the_peer_check_tells_alive_failed_unknown_and_no_detector_apart(monkeypatch):
    import threading
    import types
    from aft_ftm.ros import peer_check
    check = peer_check.PeerCheck('master', timeout=0.2)
    assert check.service == '/master/crash_detector/peer_status'
    registered = {'value': True}

    class Master(object):
        def __init__(self, caller):
            pass

        def lookupService(self, name):
            if not registered['value']:
                raise peer_check.rosgraph.MasterError('no provider')
            return 'rosrpc://127.0.0.1:1'
    monkeypatch.setattr(peer_check.rosgraph, 'Master', Master)

    class Proxy(object):
        def __init__(self, answer):
            self.answer = answer

        def __call__(self):
            if isinstance(self.answer, Exception):
                raise self.answer
            if isinstance(self.answer, threading.Event):   # a frozen detector
                self.answer.wait(5.0)
                return types.SimpleNamespace(alive=True, why='late')
            return self.answer

        def fresh(self):
            return self
    check.proxy = Proxy(types.SimpleNamespace(alive=True, why='site slave: heard 3.0 ms ago'))
    assert check.alive() is True and check.why == 'site slave: heard 3.0 ms ago'
    check.proxy = Proxy(types.SimpleNamespace(alive=False, why='site slave: declared failed'))
    assert check.alive() is False
    check.proxy = Proxy(rospy.ServiceException('unable to connect'))
    assert check.alive() is None and 'cannot be asked' in check.why   # registered, but not answering
    registered['value'] = False
    assert check.alive() is True and 'no crash detector offers' in check.why   # a launch without one
    # Frozen: no answer within the timeout; asked again while that question hangs, None at once.
    frozen = threading.Event()
    check.proxy = Proxy(frozen)
    assert check.alive() is None and 'did not answer' in check.why
    assert check.alive() is None
    frozen.set()


def test_a_hang_rule_outside_a_replica_asks_nobody_and_waits():
    from aft_ftm.recovery import OnHang
    from aft_ftm.ros.peer_check import HangRule
    rule = HangRule('')
    assert rule.peer is None and rule.on_hang() == OnHang.WAIT
    assert rule.why_wait() == 'not in a replica: nobody else can execute it'
