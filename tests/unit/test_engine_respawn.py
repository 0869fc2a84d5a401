"""A rollback that starts a killed node again (the paper order's kills undone), against a master that
still holds the registration of the node's dead predecessor: the real Engine's undo, the master, the
nodes' XML-RPC APIs and the new process faked (no master, no process started or signalled).

A node killed with SIGKILL (the engine's kill, 5 s after a SIGINT it did not end on) never
unregisters: its name, its services (~rebind among them) and its XML-RPC URI stay with the master
until a new process registers under that name (the master then drops them all). The wait after the
respawn took that registration for the new node set up: the rollback said the node was started again
while the new process was still starting (or had already failed), and the next undo called a dead URI.
"""
import types

import pytest
import rosgraph

from aft_ftm import adaptation
from aft_ftm.ros import adaptation_engine

NODE = '/master/proceed'
DEAD_URI, NEW_URI = 'http://localhost:40001/', 'http://localhost:40002/'
DEAD_PID, NEW_PID = 4194304 + 7, 4194304 + 8   # above any pid_max: never a process of this machine


class Graph(object):
    """The master's registrations and the XML-RPC APIs that answer (uri -> pid): the dead node's
    registration is there, its URI answers nothing. The new process registers (its name, services,
    URI, as rosmaster does: the dead one's registrations dropped) once the master has been asked
    ``registers_after`` times, or never (None); it exits once asked ``exits_after`` times (None: never)."""

    def __init__(self, registers_after=None, exits_after=None):
        self.registrations = {NODE: (DEAD_URI, [NODE + '/rebind', NODE + '/suspend', NODE + '/resume'])}
        self.answering = {}          # uri -> pid of a live XML-RPC API
        self.asked = 0
        self.registers_after, self.exits_after = registers_after, exits_after
        self.started = None          # the respawned FakeSite
        self.new_registered = False

    def tick(self):
        self.asked += 1
        if self.started is None:
            return
        if self.exits_after is not None and self.asked >= self.exits_after:
            self.started.exited = True
        elif self.registers_after is not None and self.asked >= self.registers_after and not self.new_registered:
            self.registrations[NODE] = (NEW_URI, [NODE + '/rebind', NODE + '/suspend', NODE + '/resume'])
            self.answering[NEW_URI] = NEW_PID
            self.new_registered = True

    # the master
    def getSystemState(self):
        self.tick()
        pubs = [('/rosout', sorted(self.registrations))]
        srvs = [(service, [node]) for node, (_, services) in self.registrations.items() for service in services]
        return pubs, [], srvs

    def lookupNode(self, node):
        self.tick()
        if node not in self.registrations:
            raise rosgraph.MasterError('unknown node')
        return self.registrations[node][0]

    # a node's XML-RPC API (aft_ftm.ros.fencing.visible_pid)
    def visible_pid(self, uri, caller_id, node, timeout=1.0):
        if uri not in self.answering:
            raise ConnectionRefusedError(111, 'Connection refused')   # a dead process's URI
        return self.answering[uri]


class FakeSite(object):
    """The respawned node's process (no guard: the node itself)."""

    def __init__(self, graph, log_path=None):
        self.graph = graph
        self.log_path = log_path
        self.pid = NEW_PID
        self.exited = False
        self.stopped = False

    def start(self):
        self.graph.started = self
        return self

    def alive(self):
        return not self.exited and not self.stopped

    def output(self):
        return '[ERROR] [1.0]: cannot import aft_ftm.nodes\n' if self.exited else ''

    def stop(self, grace=5.0):
        self.stopped = True


def engine(graph, monkeypatch, tmp_path):
    monkeypatch.setattr(adaptation_engine.Engine, 'master', property(lambda self: graph))
    monkeypatch.setattr(adaptation_engine, 'visible_pid', graph.visible_pid)
    monkeypatch.setattr(adaptation_engine, 'Site', lambda name, argv, env=None, cwd=None, log_path=None:
                        FakeSite(graph, log_path))

    def nothing_started(*args, **kwargs):
        raise AssertionError('a node without a site launcher is started here, as it was')
    monkeypatch.setattr(adaptation_engine, 'run_where', nothing_started)
    return adaptation_engine.Engine(log=lambda text: None, log_dir=str(tmp_path))


# The node's command line: an FTM node offers ~rebind once set up; another node is set up once registered.
COMMAND_LINES = {
    'an FTM node': ['/opt/ros/lib/aft_ftm/proceed', '__name:=proceed', '__ns:=/master'],
    'a node of another package': ['/opt/ros/lib/other_pkg/proceed', '__name:=proceed', '__ns:=/master'],
}


def respawn(cmdline):
    return adaptation.Step('respawn', NODE, adaptation_engine.Killed(DEAD_PID, cmdline, '/', {}, []))


@pytest.mark.parametrize('kind', sorted(COMMAND_LINES))
def test_a_node_started_again_is_not_taken_for_set_up_on_its_sigkilled_predecessors_registration(
        kind, monkeypatch, tmp_path):
    graph = Graph(registers_after=6)
    said = engine(graph, monkeypatch, tmp_path)._undo(respawn(COMMAND_LINES[kind]))
    assert graph.new_registered, (
        'the rollback said "%s" while the master still held the dead process\'s registration at %s: the new '
        'process had not registered yet' % (said, graph.registrations[NODE][0]))
    assert said == 'started again, pid %d' % NEW_PID
    # What the rollback calls next on the node reaches the new process.
    assert graph.registrations[NODE][0] == NEW_URI and graph.visible_pid(NEW_URI, '/x', NODE) == NEW_PID


@pytest.mark.parametrize('kind', sorted(COMMAND_LINES))
def test_a_node_started_again_that_exits_before_it_registers_fails_its_undo_at_once(kind, monkeypatch, tmp_path):
    graph = Graph(exits_after=4)
    eng = engine(graph, monkeypatch, tmp_path)
    with pytest.raises(adaptation.StepError) as failed:
        eng._undo(respawn(COMMAND_LINES[kind]))
    assert 'exited' in str(failed.value) and 'cannot import aft_ftm.nodes' in str(failed.value), failed.value
    assert graph.asked < 20   # at once: not at the end of the 30 s wait


def test_a_registration_of_another_process_than_the_one_started_again_is_not_taken_for_it(monkeypatch, tmp_path):
    """The name registered anew by a process that is not the one the rollback started (nor under it):
    not taken for the node restored. Here that process never gives way: the undo fails, naming both."""
    graph = Graph()
    graph.registrations[NODE] = (NEW_URI, [NODE + '/rebind'])
    graph.answering[NEW_URI] = NEW_PID + 1
    eng = engine(graph, monkeypatch, tmp_path)
    monkeypatch.setattr(adaptation_engine, 'RESPAWN_TIMEOUT', 0.3)
    with pytest.raises(adaptation.StepError) as failed:
        eng._undo(respawn(COMMAND_LINES['an FTM node']))
    assert 'not set up within 0.3 s' in str(failed.value), failed.value
    assert 'pid %d' % (NEW_PID + 1) in str(failed.value) and NEW_URI in str(failed.value), failed.value
