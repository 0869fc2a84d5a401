"""The watchdog's promotion of the backup board, without a master (aft_ftm.ros.watchdog_node): its
SetRole calls faked, ROS time a fake clock.

A backup node that does not answer SetRole ALONE within ~service_timeout (a load peak, a pause) took
the role a moment later, but the watchdog gave up at the first call: it never said which board is the
primary, and the car's commandManager refused the promoted board's commands for good (review of
session 51). It is now waited for on the same call (asked again through the master, the second call
failed at once with the master gone; review of session 52), each node PROMOTE_TRIES periods, and the
word is said once every node took its role; a node that never answers leaves the word unsaid (a board
nobody fenced may still drive) and failover_failed raised; a refusal is not waited on."""
import json
import threading
import time

import pytest
import rospy
from aft_msgs.srv import SetRoleResponse

from aft_ftm.board_watch import Failover
from aft_ftm.detector import Verdict
from aft_ftm.ros import watchdog_node
from fakes import FakeClock, FakePorts

A, B = '/board_a/cycle_after', '/board_b/cycle_after'


class Watch(object):
    """BoardWatch's face to the failover: what promoted() was told."""

    def __init__(self):
        self.told = []

    def promoted(self, name, problems, now):
        self.told.append((name, list(problems)))
        return []


class Node(object):
    """A backup board's node behind SetRole, on its one persistent connection: it answers ``pause`` s
    after the call (a node stalled; None: never), ``success`` as given."""

    def __init__(self, pause, success=True):
        self.pause, self.success, self.calls = pause, success, 0

    def __call__(self, role, last_seq):
        self.calls += 1
        time.sleep(3600 if self.pause is None else self.pause)
        return SetRoleResponse(success=self.success, message='' if self.success else 'holds no state', last_seq=0)


def no_master(name, cls):
    raise AssertionError('the promotion looked a service up at the master (it may be gone)')


@pytest.fixture
def watchdog(monkeypatch):
    clock = FakeClock(10.0)
    monkeypatch.setattr(rospy, 'get_time', lambda: clock.now)
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time.from_sec(clock.now)))
    monkeypatch.setattr(rospy, 'get_name', lambda: '/ftm/watchdog')
    node = watchdog_node.WatchdogNode.__new__(watchdog_node.WatchdogNode)
    node.boards = {'board_a': [A], 'board_b': [B]}
    node.service_timeout = 0.2
    node.lock, node.announce_lock = threading.Lock(), threading.Lock()
    node.term, node.incarnation, node.host = 1, 'w1', 'this-host'
    node.watch, node.ports = Watch(), FakePorts()
    return node


def fail_over(monkeypatch, node, backups):
    """board_a silent on another host (nobody can power it off); board_b's nodes are ``backups``
    {name: Node}, reached on their persistent connections only. Returns the failover record."""
    node.boards['board_b'] = sorted(backups)
    node.proxies = {'board_b': dict(backups)}
    monkeypatch.setattr(watchdog_node.rospy, 'ServiceProxy', no_master)
    node._failover(Failover('board_a', Verdict('silent for 0.10 s', 0.1, None), 'board_b', sorted(backups)))
    return [json.loads(m.data) for port, m in node.ports.sent if port == 'events'][-1]


def words(node):
    return [(m.board, m.term) for port, m in node.ports.sent if port == 'primary']


def test_a_backup_node_that_answers_late_is_waited_for_and_the_new_primary_is_named(monkeypatch, watchdog):
    backup = Node(pause=0.3)   # past one service_timeout (0.2 s), within two
    record = fail_over(monkeypatch, watchdog, {B: backup})
    assert record['ok'] and record['retried'] == 1 and record['term'] == 2 and backup.calls == 1, record
    assert words(watchdog) == [('board_b', 2)]
    assert watchdog.watch.told == [('board_b', [])]


def test_each_node_of_the_backup_gets_its_own_wait(monkeypatch, watchdog):
    """Two nodes each late by more than one period: a budget shared by the board failed the second."""
    first, second = Node(pause=0.3), Node(pause=0.3)
    record = fail_over(monkeypatch, watchdog, {B: first, '/board_b/other': second})
    assert record['ok'] and record['retried'] == 2 and words(watchdog) == [('board_b', 2)], record


def test_a_backup_node_that_never_answers_is_given_up_and_no_word_is_said(monkeypatch, watchdog):
    backup = Node(pause=None)
    started = time.monotonic()
    record = fail_over(monkeypatch, watchdog, {B: backup})
    assert time.monotonic() - started < 1.5   # PROMOTE_TRIES periods of 0.2 s, bounded
    assert not record['ok'] and record['retried'] == watchdog.PROMOTE_TRIES - 1 and backup.calls == 1
    assert 'no answer within 0.6 s' in record['problems'][0]
    assert words(watchdog) == [] and watchdog.term == 1
    assert 'failover_failed' in watchdog.ports.alarms()


def test_a_refusal_is_not_waited_on_and_names_no_primary(monkeypatch, watchdog):
    backup = Node(pause=0.0, success=False)
    record = fail_over(monkeypatch, watchdog, {B: backup})
    assert not record['ok'] and record['retried'] == 0 and 'holds no state' in record['problems'][0]
    assert words(watchdog) == []


def test_a_backup_node_that_answers_at_once_is_asked_once(monkeypatch, watchdog):
    backup = Node(pause=0.0)
    record = fail_over(monkeypatch, watchdog, {B: backup})
    assert record['ok'] and record['retried'] == 0 and backup.calls == 1 and words(watchdog) == [('board_b', 2)]
