"""The car's After (aft_ftm.ros.cycle_nodes.CycleAfterNode) hears its own site's last heartbeat: a
backup then stops for good (it refuses checkpoints, so its primary goes on alone at once). That
heartbeat says the site fail-stops; any node on the graph can publish one. Only its own crash
detector's (from ~site_detector, with this node's launcher as the beat's pid) may stop it: a forged
or misrouted one must change nothing. Session 38 checked this by reading the code only; here it
runs, with the node's handler and a real CycleReplica, no master."""
import os
import threading

import pytest
import rospy
from aft_msgs.msg import Heartbeat

from aft_ftm.cycle_replica import CycleReplica
from aft_ftm.protocol import Role
from aft_ftm.ros import cycle_nodes
from fakes import FakePorts

DETECTOR = '/board_b/crash_detector'


@pytest.fixture
def backup(monkeypatch):
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))
    node = cycle_nodes.CycleAfterNode.__new__(cycle_nodes.CycleAfterNode)
    node.name, node.site, node.site_detector = '/board_b/cycle_after', 'board_b', DETECTOR
    node.lock, node.ports = threading.Lock(), FakePorts()
    node.replica = CycleReplica(node.name, Role.BACKUP, 1000, expect='/board_a/')
    return node


def beat(site='board_b', pid=None, stopping='the After hung', sender=DETECTOR):
    msg = Heartbeat(site=site, pid=os.getppid() if pid is None else pid, stopping=stopping)
    msg._connection_header = {'callerid': sender} if sender is not None else {}
    return msg


@pytest.mark.parametrize('forged', [
    dict(sender='/intruder'),                       # another node, naming our launcher's pid
    dict(sender=None),                              # a message without a caller id
    dict(pid=1),                                    # our detector's name, another launcher's pid
    dict(pid=os.getpid()),                          # this process, not its launcher
    dict(site='board_a'),                           # the peer site's last beat, misrouted here
    dict(stopping=''),                              # an ordinary beat: the site lives
], ids=['other sender', 'no caller id', 'other launcher', 'not the launcher', 'other site', 'not stopping'])
def test_a_heartbeat_not_our_own_detectors_last_one_changes_nothing(backup, forged):
    backup._on_site_beat(beat(**forged))
    assert backup.replica.stopped is None and backup.ports.alarms() == []
    backup._on_site_beat(beat())   # the genuine one still stops it: the forgery left nothing behind
    assert backup.replica.stopped is not None and backup.ports.alarms() == ['site_stopped']


def test_any_sender_of_our_launcher_may_stop_it_when_no_detector_is_named(backup):
    """~site_detector '' (the default): any node of this launcher, as a launcher runs one site."""
    backup.site_detector = ''
    backup._on_site_beat(beat(pid=1, sender='/board_b/crash_detector'))   # still another launcher: ignored
    assert backup.replica.stopped is None
    backup._on_site_beat(beat(sender='/board_b/anything'))
    assert backup.replica.stopped is not None and backup.ports.alarms() == ['site_stopped']
