"""The run's recorder when the car runs under mutual TLS: rosbag record (C++) has no TLS, so this
rospy node (aft_ftm's TLS transport, party recorder) subscribes to the topics and writes each message
as it came, undecoded, into a bag (rosbag's Python API). Like rosbag record it writes <bag>.active
and renames it to <bag> once closed (on SIGINT or SIGTERM)."""
import os
import signal
import threading

import roslib.message
import rosbag
import rospy


class Recorder(object):
    def __init__(self, path, topics):
        self.path = path
        self.bag = rosbag.Bag(path + '.active', 'w')
        self.lock = threading.Lock()
        self.classes = {}
        self.unknown = {}
        self.count = 0
        self.subscribers = [rospy.Subscriber(t, rospy.AnyMsg, self._on_message, callback_args=t, tcp_nodelay=True)
                            for t in topics]

    def _on_message(self, msg, topic):
        header = msg._connection_header
        kind = header['type']
        with self.lock:
            if self.bag is None:
                return
            pytype = self.classes.get(kind)
            if pytype is None:
                pytype = self.classes[kind] = roslib.message.get_message_class(kind)
            if pytype is None:   # a type this machine does not know: said once per type, never silent
                self.unknown[kind] = self.unknown.get(kind, 0) + 1
                if self.unknown[kind] == 1:
                    rospy.logerr('%s: messages of type %s on %s cannot be recorded (type unknown here)',
                                 rospy.get_name(), kind, topic)
                return
            self.bag.write(topic, (kind, msg._buff, header['md5sum'], pytype), rospy.Time.now(), raw=True,
                           connection_header=header)
            self.count += 1

    def close(self):
        with self.lock:
            if self.bag is None:
                return
            self.bag.close()
            self.bag = None
        os.replace(self.path + '.active', self.path)


def main(argv):
    import argparse
    from aft_ftm.ros.params import secure_from_environment
    from aft_ftm.ros.subscription_keeper import keep_subscriptions
    parser = argparse.ArgumentParser(prog='recorder', description=__doc__)
    parser.add_argument('-O', dest='path', required=True, help='the bag to write')
    parser.add_argument('topics', nargs='+')
    options = parser.parse_args(rospy.myargv(argv))
    done = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):   # first: a stop during the set-up still closes the bag
        signal.signal(signum, lambda *_: done.set())
    secure_from_environment()
    keep_subscriptions()   # publishers rospy gave up on are connected again (aft_ftm.ros.subscription_keeper)
    rospy.init_node('tjp_record', disable_signals=True)
    recorder = Recorder(options.path, options.topics)
    try:
        while not done.wait(0.5) and not rospy.is_shutdown():
            pass
    finally:
        recorder.close()
        rospy.signal_shutdown('recorded %d messages' % recorder.count)
    return 0
