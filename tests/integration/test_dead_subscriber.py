"""A subscriber's host loses power: a synchronous publisher must not block for good (emulated hosts).

A host that loses power sends no FIN or RST. A rospy publisher without a queue writes to each
subscriber in the publishing thread; once about 20 small messages fill the socket's buffers towards
the dead host, that write blocks until the kernel gives the connection up: about 15 minutes of
retransmissions, during which the publisher's other subscribers hear nothing and the thread holds
whatever it holds. Every FTM node (run_node) sets a limit on unacknowledged data on its inbound
connections (TCP_USER_TIMEOUT, AFT_TCP_USER_TIMEOUT, 10 s by default; aft_ftm.ros.handshake.
unacknowledged_limit): the kernel then aborts the dead connection, rospy drops that subscriber, and
the publisher goes on.

Here two synchronous publishers run in host a, one with a 2 s limit and one without (the control),
each heard by a subscriber in host a and by one in host b; host b is powered off (link down first).
With the limit, the local subscriber hears again within a few seconds; without it, it hears nothing
for the rest of the run. Needs root; skipped (with the reason) where namespaces cannot be made.
Everything is removed at the end, pass or fail (the hosts' processes with them).
"""
import os
import subprocess
import sys
import threading
import time

import pytest

from aft_ftm import hosts_exec
from aft_ftm.hosts_exec import Hosts, PlatformError
from reporting import report

PUBLISHER = r'''
import sys, time, rospy
from std_msgs.msg import String
from aft_ftm.ros.handshake import bound_handshakes, unacknowledged_limit
bound_handshakes()
unacknowledged_limit(float(sys.argv[2]))
rospy.init_node('publisher', anonymous=True, disable_signals=True)
pub = rospy.Publisher(sys.argv[1], String, queue_size=None, tcp_nodelay=True)   # synchronous
end = time.monotonic() + 120
while time.monotonic() < end and not rospy.is_shutdown():
    pub.publish(String('x' * 200))
    time.sleep(0.002)
'''
SUBSCRIBER = r'''
import sys, time, rospy
from std_msgs.msg import String
rospy.init_node('subscriber', anonymous=True, disable_signals=True)
counts = {t: 0 for t in sys.argv[1:]}
def heard(_msg, topic):
    counts[topic] += 1
for topic in counts:
    rospy.Subscriber(topic, String, heard, callback_args=topic, tcp_nodelay=True)
while True:
    time.sleep(0.1)
    print(' '.join('%s=%d' % kv for kv in sorted(counts.items())), flush=True)
'''
TOPICS = ('/limited', '/unlimited')


class Counts(object):
    """The latest counts a subscriber process printed, read in a thread: {topic: count}."""

    def __init__(self, popen):
        self.latest = {}
        threading.Thread(target=self._read, args=(popen,), daemon=True).start()

    def _read(self, popen):
        for line in popen.stdout:
            try:
                self.latest = {k: int(v) for k, v in (kv.split('=') for kv in line.decode().split())}
            except ValueError:
                pass

    def of(self, topic):
        return self.latest.get(topic, 0)


def wait(predicate, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def test_a_publisher_to_a_dead_host_goes_on_after_the_limit_and_without_it_stays_blocked():
    try:
        hosts_exec.check_platform()
    except PlatformError as e:
        pytest.skip(str(e))
    with Hosts(['m', 'a', 'b']) as hosts:
        env = dict(os.environ, ROS_MASTER_URI='http://%s:11311' % hosts.ip('m'))
        hosts.run_in('m', ['rosmaster', '--core', '-p', '11311'], env=env, stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL)
        for topic, limit in zip(TOPICS, ('2', '0')):
            hosts.run_in('a', [sys.executable, '-c', PUBLISHER, topic, limit], env=env, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL)
        local = Counts(hosts.run_in('a', [sys.executable, '-c', SUBSCRIBER] + list(TOPICS), env=env,
                                    stdout=subprocess.PIPE, stderr=subprocess.DEVNULL))
        remote = Counts(hosts.run_in('b', [sys.executable, '-c', SUBSCRIBER] + list(TOPICS), env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL))
        assert wait(lambda: all(c.of(t) > 100 for c in (local, remote) for t in TOPICS), 60), \
            'not every subscriber heard its publishers: local %s, remote %s' % (local.latest, remote.latest)
        hosts.power_off('b')
        off = time.monotonic()
        time.sleep(2.0)   # both publishers have filled their buffers towards b by now
        since = {t: local.of(t) for t in TOPICS}
        resumed = wait(lambda: local.of('/limited') > since['/limited'] + 200, 8.0)
        resumed_after = time.monotonic() - off
        time.sleep(max(0.0, 8.0 - (time.monotonic() - off)))
        control = local.of('/unlimited') - since['/unlimited']
        report('dead subscriber host: a synchronous publisher with a 2 s unacknowledged-data limit heard again '
               '%.1f s after the power loss; without it, %d messages in the %.0f s after' % (
                   resumed_after, control, time.monotonic() - off - 2.0))
        assert resumed, 'the publisher with the limit did not go on: local counts %s (from %s)' % (local.latest, since)
        assert control == 0, 'the control publisher (no limit) was not blocked: %d messages' % control
