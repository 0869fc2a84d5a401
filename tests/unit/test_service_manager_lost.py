"""A service instance that ended while no service manager watched it (it died with its manager, or
while none ran) is a fault the next manager counts, as an exit, and acts on by the service's policy.
Before session 39 it was started again as if nothing had happened: a service killing its manager
each time, or dying with it, kept a fresh restart allowance and no back-off (Limits of session 38).
Not counted: a warm spare's end (never the service's work), and processes recorded under another
boot of the machine (the machine stopped, not the service). No master: the node's pid-file reading
with a real pid file and real processes."""
import os
import subprocess
import sys
import threading

import pytest

from aft_service_manager import trust
from aft_service_manager.services import State, Supervisor, parse_config

node_module = pytest.importorskip('aft_service_manager.ros.service_manager_node')

BOOT = 'this-boot'


def ended_process():
    """The description (pid, start time, command line) of a process that has ended."""
    import psutil
    proc = subprocess.Popen([sys.executable, '-c', 'pass'])
    described = trust.describe(psutil.Process(proc.pid))
    proc.wait(10)
    return described


@pytest.fixture
def node(tmp_path):
    n = node_module.ServiceManagerNode.__new__(node_module.ServiceManagerNode)
    n.supervisor = Supervisor(parse_config('services:\n  a: {command: x, restart_limit: 2}\n  b: {command: y}\n',
                                           source='test.yaml'))
    n.pid_file = str(tmp_path / 'm.pids')
    n.boot, n.lost = BOOT, {}
    n.children, n.spares, n.own_trees, n.instances = {}, {}, [], 0
    n.lock = threading.RLock()
    return n


def write_pids(node, **entries):
    trust.write_private_json(node.pid_file, {name: dict(entry, service=name.split(' ')[0], tree='t-' + name)
                                             for name, entry in entries.items()})


def test_an_instance_gone_since_the_last_manager_is_counted_others_are_not(node):
    write_pids(node, **{'a': dict(ended_process(), spare=False, boot=BOOT),          # died with its manager
                        'a (spare)': dict(ended_process(), spare=True, boot=BOOT),   # a spare: not its work
                        'b': dict(ended_process(), spare=False, boot='an-earlier-boot')})   # a reboot
    assert node._kill_orphans() == []
    assert sorted(node.lost) == ['a'] and 'ended while no manager watched it' in node.lost['a']


def test_a_pid_taken_by_another_process_means_the_recorded_one_ended(node):
    import psutil
    other = dict(trust.describe(psutil.Process(os.getpid())), spare=False, boot=BOOT)
    other['create_time'] -= 1000.0   # recorded earlier than this process began
    write_pids(node, a=other)
    node._kill_orphans()
    assert sorted(node.lost) == ['a'] and 'another process now' in node.lost['a']


def test_a_machine_whose_boot_cannot_be_told_counts_nothing(node):
    node.boot = ''
    write_pids(node, a=dict(ended_process(), spare=False, boot=''))
    node._kill_orphans()
    assert node.lost == {}


def test_the_lost_instance_is_acted_on_as_an_exit_within_the_restart_limit(node, monkeypatch):
    """Counted as an exit, the service is restarted by its policy; once the restart limit (restored
    from the record) is exhausted, it is FAILED and the safe state is escalated, as under one manager."""
    acted = []
    monkeypatch.setattr(node, '_act', lambda decision, now: acted.append(decision), raising=False)
    monkeypatch.setattr(node, '_event', lambda *a, **k: None, raising=False)
    node.lost = {'a': 'pid 1 is gone: it ended while no manager watched it'}
    node._lost_fault('a', 10.0)
    s = node.supervisor['a']
    assert dict(s.errors) == {'exit': 1} and s.state == State.RESTARTING and len(s.restarts) == 1
    assert acted[-1].escalate is None
    s.restarts.append(s.clock(10.5))   # a second restart within the window (from the record, say)
    node._lost_fault('a', 11.0)
    assert s.state == State.FAILED and 'restart limit exhausted' in acted[-1].escalate
