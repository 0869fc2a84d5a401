"""The campaign on emulated hosts, its pure parts: which site runs on which host, the hosts' calls made
from one thread (the root namespace's), a partition whose host the power switch fenced meanwhile.
No namespaces, no ROS master."""
import random
import threading

import pytest

from aft_examples.schedule import Fault
from aft_examples.ros.campaign_hosts import HostedBackend, RootHosts, plan


def test_plan_gives_every_client_a_host_of_its_own_with_its_proxy():
    hosts, host_of = plan(3)
    assert hosts == ('rosmaster', 'witness', 'master', 'slave', 'client1', 'client2', 'client3')
    for k in (1, 2, 3):
        assert host_of['proxy%d' % k] == host_of['client%d' % k] == 'client%d' % k
    assert {host_of[n] for n in ('witness', 'master', 'slave')} == {'witness', 'master', 'slave'}
    assert set(host_of.values()) <= set(hosts)


@pytest.mark.parametrize('bad', [0, -1, None, 1.5])
def test_plan_refuses_no_client(bad):
    with pytest.raises(ValueError, match='at least one client'):
        plan(bad)


class FakeHosts(object):
    def __init__(self, off=()):
        self.calls = []
        self.off = set(off)
        self.threads = set()
        self.powered_off_at = {}

    def __getattr__(self, name):
        if name in ('partition', 'heal', 'rate', 'unrate', 'power_off', 'power_on'):
            def call(*args):
                self.threads.add(threading.current_thread().name)
                self.calls.append((name,) + args)
                if name == 'power_off':
                    self.off.add(args[0])
                    return [1, 2, 3]
            return call
        raise AttributeError(name)

    def state(self, name):
        return 'off' if name in self.off else 'up'


def test_root_hosts_runs_every_call_in_its_own_thread_and_hands_back_errors():
    fake = FakeHosts()
    root = RootHosts(fake)
    try:
        root.partition('master')
        assert root.power_off('slave') == [1, 2, 3]
        assert root.powered_off_at == {}          # attributes pass through
        assert fake.threads == {'root-hosts'}
        with pytest.raises(AttributeError):
            root.no_such_method()
    finally:
        root.stop()


class FakeCampaign(object):
    def __init__(self, hosts):
        self.root = hosts
        self.host_of = plan(2)[1]
        self.core = None


def fault(kind, target, duration=0.01):
    return Fault(0, 0, 'pbr', kind, target, duration, 0.0)


def test_a_partitioned_host_fenced_meanwhile_is_left_off_not_healed():
    fake = FakeHosts()
    backend = HostedBackend(FakeCampaign(fake))
    # the power switch powers the cut host off while the partition holds (the peer's Recovery)
    original = fake.__getattr__('partition')
    fake.partition = lambda *hosts: (original(*hosts), fake.off.update(hosts))
    done = backend.inject(fault('partition', 'primary'), None, {'primary': 'master'}.get, random.Random(0))
    assert ('heal', 'master') not in fake.calls
    assert 'fenced' in done['what']


@pytest.mark.parametrize('seed', range(5))
def test_client_faults_reach_every_client_host(seed):
    fake = FakeHosts()
    backend = HostedBackend(FakeCampaign(fake))
    rng = random.Random(seed)
    for _ in range(40):
        backend.inject(fault('partition', 'client'), None, {}.get, rng)
    cut = {call[1] for call in fake.calls if call[0] == 'partition'}
    assert cut == {'client1', 'client2'}, 'seed %d' % seed
