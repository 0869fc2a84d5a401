"""The engine's kill of a node whose process ends without unregistering: the real Engine._kill, a real
process signalled, the master and the nodes' XML-RPC APIs faked (no master).

A node that ends on its SIGINT unregisters itself. One that does not (SIGKILLed by the engine 5 s
after a SIGINT it ignored, or killed by a fault between its record and its signal) never does: its
name stays with the master until a process registers under it anew, and the engine waited 5 s for it
to leave, inside the pause the clients see. Its registrations are removed at once now, but only those
of the dead process: a name registered anew by another process keeps it.
"""
import subprocess
import sys
import types

import psutil
import pytest
import rosgraph

from aft_ftm.ros import adaptation_engine

NODE = '/master/tr/a'
OLD_URI, NEW_URI = 'http://localhost:40011/', 'http://localhost:40012/'


class Master(object):
    """The master's registrations of NODE (uri, services), and what answers at each URI: uri -> pid."""

    def __init__(self, uri):
        self.registered = {NODE: (uri, [NODE + '/rebind', NODE + '/suspend'])}
        self.answering = {}
        self.removed = []       # (node, uri) of each unregister asked
        self.first_check = None   # whether the engine's wait found the node gone at its first look

    def getSystemState(self):
        pubs = [('/rosout', sorted(self.registered))]
        srvs = [(s, [n]) for n, (_, services) in self.registered.items() for s in services]
        return pubs, [], srvs

    def lookupNode(self, node):
        if node not in self.registered:
            raise rosgraph.MasterError('unknown node')
        return self.registered[node][0]

    def visible_pid(self, uri, caller_id, node, timeout=1.0):
        if uri not in self.answering:
            raise ConnectionRefusedError(111, 'Connection refused')
        return self.answering[uri]

    def unregister(self, master, dead, uris):
        for node in dead:
            self.removed.append((node, uris[node]))
            if node in self.registered and self.registered[node][0] == uris[node]:
                del self.registered[node]
        return len(dead)

    def wait_until(self, predicate, timeout, interval=0.02):
        value = predicate()
        if self.first_check is None:
            self.first_check = bool(value)
        return value


@pytest.fixture
def victim():
    """A process that ends on SIGINT (Python's KeyboardInterrupt) and unregisters nothing. (Its handler
    set explicitly: started from a background shell, SIGINT is ignored on entry and Python keeps it so.)"""
    proc = subprocess.Popen([sys.executable, '-c', 'import signal, time; '
                             'signal.signal(signal.SIGINT, signal.default_int_handler); print("ready", flush=True); '
                             'time.sleep(60)'], stdout=subprocess.PIPE)
    assert proc.stdout.readline().strip() == b'ready'
    yield proc
    if proc.poll() is None:
        proc.kill()
    proc.wait()


def kill(master, victim, monkeypatch, while_signalled=None):
    monkeypatch.setattr(adaptation_engine.Engine, 'master', property(lambda self: master))
    for name in ('visible_pid', 'unregister', 'wait_until'):
        monkeypatch.setattr(adaptation_engine, name, getattr(master, name))
    monkeypatch.setattr(adaptation_engine, 'mark_retired', lambda pid: None)
    monkeypatch.setattr(adaptation_engine, 'disarm_guard_of', lambda pid: None)
    said = []
    eng = adaptation_engine.Engine(log=said.append)
    eng._keeper = types.SimpleNamespace(release=lambda node: None)
    record = adaptation_engine.Killed(victim.pid, [], '/', {}, [])
    if while_signalled is not None:   # what happens between the signal and the end of the process
        real = adaptation_engine.wait_dead

        def wait_dead(procs, timeout):
            alive = real(procs, timeout)
            while_signalled()
            return alive
        monkeypatch.setattr(adaptation_engine, 'wait_dead', wait_dead)
    assert eng._kill(NODE, (psutil.Process(victim.pid), record)) is record
    assert victim.wait(5.0) is not None
    return said


def test_a_killed_node_that_never_unregisters_is_removed_from_the_master_at_once(victim, monkeypatch):
    master = Master(OLD_URI)
    master.answering[OLD_URI] = victim.pid   # its API answered while it ran
    said = kill(master, victim, monkeypatch, while_signalled=lambda: master.answering.pop(OLD_URI))
    assert master.removed == [(NODE, OLD_URI)], 'the dead node\'s registrations were left with the master'
    assert master.first_check is True, 'the engine waited for a dead node to leave the master by itself'
    assert any('ended without unregistering' in line for line in said), said


def test_a_name_registered_anew_by_another_process_is_not_removed(victim, monkeypatch):
    master = Master(OLD_URI)

    def registered_anew():   # the node started again elsewhere (a respawn): its new URI answers
        master.registered[NODE] = (NEW_URI, [NODE + '/rebind'])
        master.answering[NEW_URI] = victim.pid + 1
    kill(master, victim, monkeypatch, while_signalled=registered_anew)
    assert master.removed == [] and master.registered[NODE][0] == NEW_URI


def test_a_process_answering_as_the_node_at_its_uri_keeps_the_name(victim, monkeypatch):
    """The same URI answered by another live process as the node (the port taken by its successor)."""
    master = Master(OLD_URI)
    kill(master, victim, monkeypatch, while_signalled=lambda: master.answering.update({OLD_URI: victim.pid + 1}))
    assert master.removed == [] and NODE in master.registered


@pytest.mark.parametrize('answer', [TimeoutError('timed out'), OSError(113, 'No route to host')])
def test_a_registration_whose_uri_does_not_refuse_is_kept(answer, victim, monkeypatch):
    """Only a refused connection (nothing listens) proves the registration dead: a slow or frozen node's
    API, or an unreachable one, may belong to a live process registered anew."""
    master = Master(OLD_URI)
    refused = master.visible_pid

    def slow(uri, caller_id, node, timeout=1.0):
        if uri == OLD_URI:
            raise answer
        return refused(uri, caller_id, node, timeout)
    master.visible_pid = slow
    kill(master, victim, monkeypatch)
    assert master.removed == [] and NODE in master.registered


def test_a_node_that_was_not_registered_leaves_nothing_to_remove(victim, monkeypatch):
    master = Master(OLD_URI)
    del master.registered[NODE]
    kill(master, victim, monkeypatch)
    assert master.removed == []
