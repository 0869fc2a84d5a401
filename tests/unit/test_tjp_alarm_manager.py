"""The car's alarm manager (tjp_sim.ros.ftm_nodes.AlarmManagerNode) without a master: its watch loop on
a fake ROS clock, its ports faked."""
import threading
import time

from tjp_sim.ros import ftm_nodes


class Ports(object):
    def __init__(self):
        self.sent = []

    def publish(self, port, msg):
        self.sent.append((port, msg))

    def topic(self, port):
        return '/sensors/' + port


def manager(monkeypatch, clock):
    node = ftm_nodes.AlarmManagerNode.__new__(ftm_nodes.AlarmManagerNode)
    node.name, node.ports, node.lock = '/alarm_manager', Ports(), threading.Lock()
    node.watch = {'imu': 0.3, 'ultrasonic': 0.3, 'gap': 0.5}
    node.clock_timeout, node.master_down, node.stopped, node.last_heard = 0.5, None, None, {}
    node.last_clock_wall = time.monotonic()
    monkeypatch.setattr(ftm_nodes.rospy, 'get_time', lambda: clock[0])
    monkeypatch.setattr(ftm_nodes.rospy, 'logerr', lambda *a, **k: None)
    monkeypatch.setattr(ftm_nodes.rospy.Time, 'now', staticmethod(lambda: ftm_nodes.rospy.Time(0)))
    return node


def one_round(node, monkeypatch):
    """One pass of the watch loop: the loop's sleep ends it."""
    rounds = iter([False, True])
    monkeypatch.setattr(ftm_nodes.rospy, 'is_shutdown', lambda: next(rounds))
    monkeypatch.setattr(ftm_nodes.time, 'sleep', lambda s: None)
    node._loop()


def test_a_sensor_silent_after_the_clock_went_back_is_still_seen(monkeypatch):
    """Review of session 48: the watch compared the clock with when each input was last heard; after a
    /clock reset that was in the future, so a sensor silent from then on went unseen until the clock
    caught up (50 s of ROS time without an alarm). Watched afresh from the reset now."""
    clock = [100.0]
    node = manager(monkeypatch, clock)
    for port in node.watch:
        node._heard(port)
    for step in range(5):                           # the clock restarts at 1 s; the ultrasonic is silent
        clock[0] = 1.0 + 0.1 * step
        node._heard('imu')
        node._heard('gap')
        node.last_clock_wall = time.monotonic()
        one_round(node, monkeypatch)
        if node.stopped:
            break
    assert node.stopped == 'ultrasonic_silent', node.stopped
    assert [(port, getattr(m, 'kind', None)) for port, m in node.ports.sent][0] == ('alarms', 'ultrasonic_silent')
