"""Unregistering dead nodes from the ROS master (aft_ftm.ros.graph.unregister), each registration on
its own. No ROS master: a fake one."""
import pytest

from aft_ftm.ros import graph


class FakeMaster(object):
    def __init__(self, gone=()):
        self.gone = set(gone)   # services unregistered between the listing and the lookup
        self.removed = []

    def getSystemState(self):
        return ([['/ticks', ['/dead', '/live']]], [['/tocks', ['/dead']]],
                [['/dead/a', ['/dead']], ['/dead/b', ['/dead']], ['/dead/c', ['/dead']], ['/live/x', ['/live']]])

    def lookupNode(self, name):
        return 'http://host:2/'

    def lookupService(self, service):
        if service in self.gone:
            raise RuntimeError('no provider')   # what rosgraph's MasterError says
        return 'rosrpc://host:1/%s' % service

    def as_node(self, name):
        master = self

        class AsNode(object):
            def __getattr__(self, method):
                return lambda what, api: master.removed.append((name, method, what, api))
        return AsNode()


def test_a_service_gone_between_listing_and_lookup_is_skipped_and_the_rest_removed():
    master = FakeMaster(gone={'/dead/b'})
    removed = graph.unregister(master, ['/dead'], {'/dead': 'http://host:2/'}, master_as=master.as_node)
    assert removed == 4
    assert master.removed == [
        ('/dead', 'unregisterPublisher', '/ticks', 'http://host:2/'),
        ('/dead', 'unregisterSubscriber', '/tocks', 'http://host:2/'),
        ('/dead', 'unregisterService', '/dead/a', 'rosrpc://host:1//dead/a'),
        ('/dead', 'unregisterService', '/dead/c', 'rosrpc://host:1//dead/c')]   # not /live's, not /dead/b


def test_a_master_refusing_one_removal_still_gets_the_others():
    master = FakeMaster()

    def as_node(name):
        class Refusing(object):
            def unregisterPublisher(self, what, api):
                raise RuntimeError('the master refused')

            def __getattr__(self, method):
                return lambda what, api: master.removed.append((method, what))
        return Refusing()
    assert graph.unregister(master, ['/dead'], {'/dead': 'http://host:2/'}, master_as=as_node) == 4
    assert ('unregisterSubscriber', '/tocks') in master.removed and len(master.removed) == 4


def test_no_master_cleans_nothing():
    class Gone(object):
        def getSystemState(self):
            raise OSError('connection refused')
    assert graph.unregister(Gone(), ['/dead'], {}) == 0


@pytest.mark.parametrize('gone', [set(), {'/dead/b'}])
def test_rosnodes_own_cleanup_raised_where_this_one_goes_on(gone, monkeypatch):
    """The control: rosnode.cleanup_master_blacklist, used before, raised out at the first service gone."""
    import rosnode

    class Node(object):
        def __init__(self, name):
            pass

        def __getattr__(self, method):
            return lambda *a: None
    monkeypatch.setattr(rosnode.rosgraph, 'Master', Node)
    master = FakeMaster(gone=gone)
    if gone:
        with pytest.raises(RuntimeError, match='no provider'):
            rosnode.cleanup_master_blacklist(master, ['/dead'])
    else:
        rosnode.cleanup_master_blacklist(master, ['/dead'])
    assert graph.unregister(master, ['/dead'], {'/dead': 'http://host:2/'}, master_as=master.as_node) == 5 - len(gone)
