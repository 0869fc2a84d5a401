"""The car simulator as a ROS node: the pybullet road (tjp_sim.world) publishing ROS time and the
follower's sensors, driven by the actuator command, with the scenario's sensor faults injected."""
import json
import threading
import time

import rospy
from aft_msgs.msg import CarCommand, CarState
from geometry_msgs.msg import TwistStamped
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Range
from std_msgs.msg import String
from std_srvs.srv import Trigger, TriggerResponse

from aft_ftm import config
from aft_ftm.ros.params import param

from .. import scenario as scenarios
from ..faults import SILENT, SensorFaults
from ..world import LASER_RANGE, ULTRASONIC_RANGE, World


def _bool(name, value):
    if not isinstance(value, bool):
        raise config.ConfigError('parameter %s must be true or false, got %r' % (name, value))
    return value


class CarSimNode(object):
    """Steps the road every ~dt of simulated time, ``rate`` times faster than real time (the
    scenario's), and publishes /clock, so that every node runs on simulated time.

    Before ``~start`` is called it publishes the clock at t = 0 only (the nodes come up without the
    car moving). It stops stepping at the scenario's duration, then keeps publishing its last clock.

    Parameters:
        ~scenario (str, required): a scenario file or shipped name (tjp_sim.scenario)
        ~gui (bool, false): open pybullet's window
        ~dt (float, 0.02 s): the simulation step; the lasers and the ultrasonic sensor read every
            second step (25 Hz), the IMU every step (50 Hz)
        ~rate (float, default the scenario's): how many times faster than real time
    Publishes:
        /clock (rosgraph_msgs/Clock); car/state (aft_msgs/CarState): ground truth, for the record;
        sensors/laser_0 .. laser_2, sensors/ultrasonic (sensor_msgs/Range, +inf: nothing in range);
        sensors/imu (geometry_msgs/TwistStamped, linear.x: the speed); tjp/events (std_msgs/String,
        JSON): faults beginning, the pedestrian, the count of faulty readings injected (each second)
    Subscribes: car/command (aft_msgs/CarCommand): the actuator's command
    Services: ~start (std_srvs/Trigger)
    """

    def __init__(self):
        try:
            self.scenario = scenarios.load(param('scenario', config.non_empty_str, required=True))
        except scenarios.ScenarioError as e:
            raise config.ConfigError(str(e))
        self.gui = param('gui', _bool, False)
        self.dt = param('dt', config.positive_float, 0.02)
        self.rate = param('rate', config.positive_float, self.scenario['rate'])
        self.faults = SensorFaults(self.scenario['faults'], self.scenario['seed'])
        self.started = threading.Event()
        self.accel = 0.0
        self.lock = threading.Lock()
        self.announced = set()
        self.commands = 0

    def setup(self, timeout):
        s = self.scenario
        self.world = World(s['profile'], gap=s['initial_gap'], follower_speed=s['initial_speed'], dt=self.dt,
                           gui=self.gui)
        self.clock = rospy.Publisher('/clock', Clock, queue_size=None, tcp_nodelay=True)
        self.state = rospy.Publisher('car/state', CarState, queue_size=None, tcp_nodelay=True)
        self.lasers = [rospy.Publisher('sensors/laser_%d' % i, Range, queue_size=None, tcp_nodelay=True)
                       for i in range(3)]
        self.ultrasonic = rospy.Publisher('sensors/ultrasonic', Range, queue_size=None, tcp_nodelay=True)
        self.imu = rospy.Publisher('sensors/imu', TwistStamped, queue_size=None, tcp_nodelay=True)
        self.events = rospy.Publisher('tjp/events', String, queue_size=None, tcp_nodelay=True)
        rospy.Subscriber('car/command', CarCommand, self._on_command, tcp_nodelay=True)
        rospy.Service('~start', Trigger, self._on_start)
        rospy.on_shutdown(self.world.close)
        threading.Thread(target=self._run, name='simulation', daemon=True).start()
        return True

    def _on_command(self, msg):
        with self.lock:
            self.accel = msg.accel
            self.commands += 1

    def _on_start(self, _req):
        self.started.set()
        return TriggerResponse(success=True, message='scenario %s started' % self.scenario['name'])

    def _event(self, kind, **fields):
        fields.update(t=round(self.world.t, 4), kind=kind)
        self.events.publish(String(data=json.dumps(fields)))

    def _run(self):
        while not self.started.wait(0.1):
            if rospy.is_shutdown():
                return
            self.clock.publish(Clock(clock=rospy.Time(0)))
        wall0, steps = time.monotonic(), 0
        duration = self.scenario['duration']
        next_report = 1.0
        while not rospy.is_shutdown() and self.world.t < duration - 1e-9:
            steps += 1
            delay = wall0 + steps * self.dt / self.rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            self._scripted_events()
            with self.lock:
                accel = self.accel
            applied = self.world.step(accel)
            now = rospy.Time.from_sec(self.world.t)
            self.clock.publish(Clock(clock=now))
            self._publish_sensors(now, steps)
            pedestrian = self.world.pedestrian_distance()
            obstacle = self.world.gap() if pedestrian is None else min(pedestrian, self.world.gap())
            self.state.publish(CarState(stamp=now, gap=self.world.gap(), follower_speed=self.world.follower_v,
                                        leader_speed=self.world.leader_v, accel=applied,
                                        obstacle=obstacle,
                                        collided=self.world.collided))
            if self.world.t >= next_report:
                next_report += 1.0
                self._event('injected', counts=dict(self.faults.injected))
        self._event('injected', counts=dict(self.faults.injected))
        self._event('end', commands=self.commands)
        rospy.loginfo('%s: scenario %s done (%.1f s simulated)', rospy.get_name(), self.scenario['name'], self.world.t)
        # The simulator is still alive: its clock stands still but keeps being published, so that
        # the end of a scenario is not taken for a simulator crash.
        last = rospy.Time.from_sec(self.world.t)
        while not rospy.is_shutdown():
            self.clock.publish(Clock(clock=last))
            time.sleep(0.1)

    def _scripted_events(self):
        t = self.world.t
        for i, fault in enumerate(self.scenario['faults']):
            if fault['at'] <= t and ('fault', i) not in self.announced and fault['kind'] not in scenarios.PROCESS_FAULTS:
                self.announced.add(('fault', i))
                self._event('fault', fault=fault['kind'], target=fault['sensor'],
                            until=fault.get('until'))
        for i, event in enumerate(self.scenario['events']):
            if event['kind'] != 'pedestrian':
                continue
            if event['at'] <= t and ('in', i) not in self.announced:
                self.announced.add(('in', i))
                self.world.pedestrian_steps_in(event['ahead'])
                self._event('pedestrian', action='in', ahead=event['ahead'])
            if event['leaves'] is not None and event['leaves'] <= t and ('out', i) not in self.announced:
                self.announced.add(('out', i))
                self.world.pedestrian_leaves()
                self._event('pedestrian', action='out')

    def _range(self, sensor, value, radiation, max_range, now):
        reading, _ = self.faults.apply(sensor, self.world.t, value)
        if reading is SILENT:
            return None
        msg = Range(radiation_type=radiation, field_of_view=0.05, min_range=0.02, max_range=max_range,
                    range=float('inf') if reading is None else min(reading, max_range))
        msg.header.stamp, msg.header.frame_id = now, sensor
        return msg

    def _publish_sensors(self, now, steps):
        speed, _ = self.faults.apply('imu', self.world.t, self.world.imu_speed())
        if speed is not SILENT:
            imu = TwistStamped()
            imu.header.stamp, imu.header.frame_id = now, 'imu'
            imu.twist.linear.x = speed
            self.imu.publish(imu)
        if steps % 2:
            return
        for i, value in enumerate(self.world.lasers()):
            msg = self._range('laser_%d' % i, value, Range.INFRARED, LASER_RANGE, now)
            if msg is not None:
                self.lasers[i].publish(msg)
        msg = self._range('ultrasonic', self.world.ultrasonic(), Range.ULTRASOUND, ULTRASONIC_RANGE, now)
        if msg is not None:
            self.ultrasonic.publish(msg)
