"""A&D under an assertion that hangs (aft_ftm.ros.ad_nodes.BoundedRun, ``~assertion_timeout``), without
a master: the nodes' ports faked.

Before: an assertion that did not return (a deadlock, a blocking call in the user's code) hung A&D's
Before or After with it, and every request behind it waited until the Protocol's timeout; the reply
it was checking was neither passed on nor refused. Now the check is a violation past the bound (the
request refused, the reply answered as an error), the hang is alarmed once (``assertion_hangs``),
the hung call is not made again while it has not returned (no thread piles up), and the assertion
is called again once it has.
"""
import threading
import time

import pytest
import rospy
from aft_msgs.msg import Reply, Request

from aft_ftm import assertions
from aft_ftm.ros import ad_nodes
from fakes import FakePorts
from aft_ftm.ros.envelope import serialize
from aft_msgs.srv import AccountRequest, AccountResponse

BOUND = 0.2


class Gate(object):
    """An assertion that blocks while the gate is closed; counts its calls."""

    def __init__(self):
        self.open = threading.Event()
        self.calls = 0

    def __call__(self, *args):
        self.calls += 1
        self.open.wait(30)
        return True


def within(seconds, fn, *args, **kwargs):
    """fn(*args, **kwargs) on a thread; its result, or AssertionError if it did not return within seconds."""
    out = []
    thread = threading.Thread(target=lambda: out.append(fn(*args, **kwargs)), daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), '%s did not return within %.1f s: the assertion hung the node' % (
        getattr(fn, '__name__', fn), seconds)
    return out[0]


@pytest.fixture
def no_clock(monkeypatch):
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))


def test_a_hung_assertion_is_a_violation_alarmed_once_and_called_again_once_it_returns():
    hangs = []
    run = ad_nodes.BoundedRun(BOUND, lambda name, detail: hangs.append(name))
    gate = Gate()
    try:
        start = time.monotonic()
        violations = within(5, assertions.check, [('user:gate', gate)], 'request', run=run)
        assert time.monotonic() - start >= BOUND * 0.9
        assert len(violations) == 1 and violations[0][0] == 'user:gate'
        assert violations[0][1].startswith('hangs: did not return within ~assertion_timeout'), violations
        assert hangs == ['user:gate']
        first = violations
        threads = threading.active_count()
        for _ in range(5):   # while the call hangs: a violation at once, no new call, no new thread
            start = time.monotonic()
            violations = within(5, assertions.check, [('user:gate', gate)], 'request', run=run)
            assert time.monotonic() - start < BOUND / 2
            assert violations == first, violations   # the same detail (TR around A&D sees one result)
        assert gate.calls == 1 and hangs == ['user:gate'] and threading.active_count() <= threads
    finally:
        gate.open.set()
    deadline = time.monotonic() + 5
    while assertions.check([('user:gate', gate)], 'request', run=run) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert assertions.check([('user:gate', gate)], 'request', run=run) == []   # it returned: called again, passes
    assert gate.calls >= 2 and hangs == ['user:gate']


def test_other_assertions_are_still_checked_while_one_hangs():
    run = ad_nodes.BoundedRun(BOUND, lambda name, detail: None)
    gate = Gate()
    try:
        def negative(_request):
            return 'negative'
        violations = within(5, assertions.check, [('user:gate', gate), ('user:negative', negative),
                                                   ('user:fine', lambda _r: True)], 'request', run=run)
        assert [name for name, _ in violations] == ['user:gate', 'user:negative'], violations
    finally:
        gate.open.set()


def test_a_timeout_of_zero_calls_the_assertion_in_the_callers_thread_unbounded():
    run = ad_nodes.BoundedRun(0, lambda name, detail: None)
    seen = []
    assert assertions.check([('user:where', lambda _r: seen.append(threading.current_thread()))], 'r', run=run) == []
    assert seen == [threading.current_thread()]


def _request(rid=3):
    return Request(id=rid, origin='/client/proxy', client='c', attempt=1, service_type='aft_msgs/Account',
                   payload=serialize(AccountRequest(op='deposit', amount=5)))


def test_a_before_whose_request_assertion_hangs_refuses_the_request_within_the_bound(no_clock):
    node = ad_nodes.AdBeforeNode.__new__(ad_nodes.AdBeforeNode)
    node.ports, node.lock, node.copies = FakePorts(), threading.Lock(), assertions.Copies()
    node.run = ad_nodes.BoundedRun(BOUND, lambda name, detail: ad_nodes.alarm(node.ports, 'ad', 'assertion_hangs',
                                                                              detail))
    gate = Gate()
    node.checks = [('user:gate', gate)]
    try:
        assert within(5, node.handle, _request()) is None   # not passed on to be executed
        assert node.ports.kinds() == [('alarms', 'assertion_hangs'), ('alarms', 'assertion_violated'),
                                      ('errors', None)], node.ports.kinds()
        refused = node.ports.sent[-1][1]
        assert (refused.id, refused.origin, refused.status) == (3, '/client/proxy', Reply.ERROR)
        assert 'user:gate violated: hangs' in refused.error
        node.ports.sent = []
        assert within(5, node.handle, _request(4)) is None   # still hung: refused at once, not alarmed again
        assert node.ports.kinds() == [('alarms', 'assertion_violated'), ('errors', None)], node.ports.kinds()
    finally:
        gate.open.set()


def test_an_after_whose_reply_assertion_hangs_answers_an_error_within_the_bound(no_clock):
    node = ad_nodes.AdAfterNode.__new__(ad_nodes.AdAfterNode)
    node.ports, node.lock = FakePorts(), threading.Lock()
    node.pairing = assertions.Pairing(wait=5.0, max_requests=10)
    node.run = ad_nodes.BoundedRun(BOUND, lambda name, detail: None)
    gate = Gate()
    node.checks = [('user:gate', gate)]
    request = _request()
    reply = Reply(id=3, origin='/client/proxy', client='c', attempt=1, status=Reply.OK,
                  payload=serialize(AccountResponse(balance=5)))
    try:
        node._on_request(request)
        answer = within(5, node.handle, reply)
        assert answer is not None and answer.status == Reply.ERROR and 'hangs' in answer.error, answer
        assert answer.payload == b''   # the unchecked reply is not passed on
    finally:
        gate.open.set()


def test_the_launch_default_bounds_assertions():
    """mechanism.launch passes ~assertion_timeout (1 s) to A&D's Before and After."""
    import os
    import xml.etree.ElementTree as ET
    launch = os.path.join(os.path.dirname(ad_nodes.__file__), '..', '..', '..', 'launch', 'mechanism.launch')
    root = ET.parse(launch).getroot()
    declared = [a.get('default') for a in root.findall('arg') if a.get('name') == 'assertion_timeout']
    assert declared == ['1.0']
    for node in root.iter('node'):
        if node.get('name') in ('before', 'after'):
            assert [p.get('value') for p in node.iter('param') if p.get('name') == 'assertion_timeout'] == [
                '$(arg assertion_timeout)'], node.get('name')


def test_an_assertion_raising_timeout_error_is_its_own_verdict_not_a_hang():
    """Review of session 39: since Python 3.11 concurrent.futures.TimeoutError is TimeoutError, so an
    assertion raising it (a socket timeout) was taken for the bound's: a false assertion_hangs."""
    hangs = []
    run = ad_nodes.BoundedRun(BOUND, lambda name, detail: hangs.append(name))

    def times_out(_request):
        raise TimeoutError('the map server did not answer')
    violations = assertions.check([('user:map', times_out)], 'r', run=run)
    assert violations == [('user:map', 'raised TimeoutError: the map server did not answer')] and hangs == []
    assert assertions.check([('user:fine', lambda _r: True)], 'r', run=run) == []


def test_a_check_waiting_for_the_one_before_keeps_its_whole_bound():
    """Review of session 39: two checks of one assertion at once (two subscriber threads); the
    second's wait for the first counted against its bound, and a healthy assertion was abandoned
    as hung."""
    hangs = []
    run = ad_nodes.BoundedRun(BOUND, lambda name, detail: hangs.append(name))

    def slow(_request):
        time.sleep(BOUND * 0.6)
        return True
    results = []
    threads = [threading.Thread(target=lambda: results.append(assertions.check([('user:slow', slow)], 'r', run=run)))
               for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert results == [[], []] and hangs == []


@pytest.mark.parametrize('bad', [float('inf'), float('nan'), -1.0, 1e12])
def test_an_assertion_timeout_that_is_no_bound_is_refused(bad):
    from aft_ftm.errors import ConfigError
    with pytest.raises(ConfigError, match='assertion_timeout'):
        ad_nodes.BoundedRun(bad, lambda name, detail: None)


def test_an_assertion_calling_sys_exit_is_a_violation_not_a_dead_thread():
    import sys
    run = ad_nodes.BoundedRun(BOUND, lambda name, detail: None)

    def exits(_request):
        sys.exit(3)
    assert assertions.check([('user:exit', exits)], 'r', run=run) == [('user:exit', 'raised RuntimeError: raised '
                                                                                    'SystemExit: 3')]
