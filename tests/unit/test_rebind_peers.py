"""A subscribe port's rebind answers "connected" only once each publisher writes to it (its getBusInfo
lists the connection): the subscriber counts its connection when the publisher has answered its header,
a moment before the publisher adds it, and a message published in between was lost (adaptation.test
under load). No master: the publisher's API is faked."""
import pytest

from aft_ftm.ros import fencing
from aft_ftm.ros.ports import _writes_to

TOPIC = '/master/bfr2prd'


class FakeMaster(object):
    def lookupNode(self, name):
        return 'http://host:1234/'


class FakeApi(object):
    def __init__(self, info, fail=False):
        self.info, self.fail = info, fail

    def getBusInfo(self, caller):
        if self.fail:
            raise OSError('connection refused')
        return 1, 'bus info', self.info


@pytest.mark.parametrize('info,writes', [
    ([], False),                                                                          # not added yet
    ([(1, '/master/tr/protocol', 'o', 'TCPROS', TOPIC, True, '')], True),
    ([(1, '/master/tr/protocol', 'i', 'TCPROS', TOPIC, True, '')], False),               # it reads, not writes
    ([(1, '/other', 'o', 'TCPROS', TOPIC, True, '')], False),                             # to another node
    ([(1, '/master/tr/protocol', 'o', 'TCPROS', '/elsewhere', True, '')], False),         # another topic
])
def test_a_publisher_writes_to_the_port_only_once_it_lists_the_connection(monkeypatch, info, writes):
    monkeypatch.setattr(fencing, 'node_api', lambda uri, timeout: FakeApi(info))
    assert _writes_to(FakeMaster(), '/master/before', '/master/tr/protocol', TOPIC, deadline=1e18) is writes


def test_a_publisher_that_cannot_be_asked_holds_nothing_up(monkeypatch):
    monkeypatch.setattr(fencing, 'node_api', lambda uri, timeout: FakeApi([], fail=True))
    assert _writes_to(FakeMaster(), '/master/before', '/master/tr/protocol', TOPIC, deadline=1e18) is True


def test_a_connection_listed_before_the_binding_is_not_taken_for_the_new_one(monkeypatch):
    """CI, stop 38: a rollback bound Proceed's input back a moment after unbinding it; Before still
    listed the old, closed connection to it, the check passed on it, and the first request after the
    resume went there and was lost (30 s later the site fail-stopped). Only a newer connection counts."""
    from aft_ftm.ros.ports import _outbound_to
    old = [(7, '/master/proceed', 'o', 'TCPROS', TOPIC, True, '')]
    monkeypatch.setattr(fencing, 'node_api', lambda uri, timeout: FakeApi(old))

    class Master(FakeMaster):
        def getSystemState(self):
            return [(TOPIC, ['/master/before']), ('/other', ['/x'])], [], []
    assert _outbound_to(Master(), TOPIC, '/master/proceed', timeout=1.0) == {'/master/before': 7}
    assert not _writes_to(FakeMaster(), '/master/before', '/master/proceed', TOPIC, deadline=1e18, above=7)
    both = old + [(9, '/master/proceed', 'o', 'TCPROS', TOPIC, True, '')]
    monkeypatch.setattr(fencing, 'node_api', lambda uri, timeout: FakeApi(both))
    assert _writes_to(FakeMaster(), '/master/before', '/master/proceed', TOPIC, deadline=1e18, above=7)


def test_a_latched_port_rebound_gives_its_last_message_to_the_subscribers_of_its_new_topic(monkeypatch):
    """The watchdog's word on the primary board is latched: rebound (recover(), an adaptation), the new
    publisher held nothing, and a commandManager started later waited for a word that never came
    (review of session 51)."""
    from aft_msgs.msg import PrimaryBoard
    from aft_ftm.ports import PUBLISH, PortSpec
    from aft_ftm.ros import ports as ports_module
    published = []

    class Publisher(object):
        def __init__(self, topic, cls, latch=False, **_kwargs):
            self.topic, self.latch = topic, latch

        def publish(self, msg):
            published.append((self.topic, self.latch, msg.term))

        def unregister(self):
            pass
    monkeypatch.setattr(ports_module.rospy, 'Publisher', Publisher)
    monkeypatch.setattr(ports_module, 'param', lambda name, convert, default=None: default)
    ports = ports_module.Ports([PortSpec('primary', PUBLISH, 'aft_msgs/PrimaryBoard'),
                                PortSpec('events', PUBLISH, 'std_msgs/String')], {})
    ports.bind('primary', '/tjp/primary', latch=True)
    ports.bind('events', '/tjp/events')
    ports.publish('primary', PrimaryBoard(board='board_b', term=2))
    ports.bind('primary', '/car/primary')
    ports.bind('events', '/car/events')   # not latched: nothing again
    assert published == [('/tjp/primary', True, 2), ('/car/primary', True, 2)]
