"""The campaign's host-level backend drives aft_ftm.hosts_exec.Hosts as the schedule says: a fake Hosts
records the calls. No ROS master, no namespaces."""
import random

import pytest

from aft_examples.schedule import Fault
from aft_examples.ros.campaign import CampaignError, HostsBackend, ProcessBackend


class FakeHosts(object):
    def __init__(self):
        self.calls = []

    def __getattr__(self, name):
        if name in ('partition', 'heal', 'rate', 'unrate', 'power_off'):
            return lambda *args: self.calls.append((name,) + args)
        raise AttributeError(name)


HOST_OF = {'master': 'h_master', 'slave': 'h_slave', 'witness': 'h_witness', 'proxy1': 'h_client'}


def fault(kind, target, duration=0.01):
    return Fault(0, 0, 'pbr', kind, target, duration, 0.0)


@pytest.mark.parametrize('kind,target,expected', [
    ('partition', 'primary', [('partition', 'h_slave'), ('heal', 'h_slave')]),
    ('partition_pair', 'client-witness', [('partition', 'h_client', 'h_witness'), ('heal', 'h_client', 'h_witness')]),
    ('partition_pair', 'primary-backup', [('partition', 'h_slave', 'h_master'), ('heal', 'h_slave', 'h_master')]),
    ('bandwidth', 'backup', [('rate', 'h_master', HostsBackend.RATE_KBIT), ('unrate', 'h_master')]),
    ('power_loss', 'primary', [('power_off', 'h_slave')]),
])
def test_host_faults_reach_the_hosts_of_the_roles_serving_now(kind, target, expected):
    hosts = FakeHosts()
    backend = HostsBackend(hosts, HOST_OF)
    roles = {'primary': 'slave', 'backup': 'master'}   # after a failover
    done = backend.inject(fault(kind, target), None, roles.get, random.Random(0))
    assert hosts.calls == expected
    assert done['end'] >= done['start'] and done['proxy_killed'] is None


def test_one_host_refuses_what_needs_hosts_by_name():
    assert 'hosts' not in ProcessBackend.offered and 'hosts' in HostsBackend.offered
    with pytest.raises(CampaignError, match='partition is not a fault of one host'):
        ProcessBackend().inject(fault('partition', 'primary'), None, {'primary': 'master'}.get, random.Random(0))
