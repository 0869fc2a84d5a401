"""The road of the Traffic Jam Pilot in pybullet, headless by default, without rospy.

Two cars on a straight road along x: a leader that follows a driving profile, and a follower
driven only by acceleration commands. pybullet holds the geometry: the follower's three forward
lasers and its ultrasonic sensor are ray casts, a collision is a contact between bodies, and a
pedestrian can step onto the road between the cars. The cars' longitudinal motion is integrated
here (speed from the commanded acceleration, within the car's own limits), and the bodies are
moved to their new positions each step: a traffic jam at under 35 km/h needs no tyre model, and
a fixed step makes every run with the same seed the same.

Units: metres, seconds. Time advances only by :meth:`World.step`: a scenario runs as fast as the
machine allows, or in step with a clock.
"""
import bisect

import pybullet

from .errors import TjpConfigError

CAR_LENGTH, CAR_WIDTH, CAR_HEIGHT = 4.0, 1.8, 1.4
LASER_RANGE, ULTRASONIC_RANGE = 100.0, 5.0
LASER_OFFSETS = (-0.5, 0.0, 0.5)      # lateral offsets of the three lasers on the follower's bumper (m)


def profile_speed(profile, t):
    """Speed of a driving profile [(time, speed), ...] at t: linear between points, held after."""
    times = [p[0] for p in profile]
    i = bisect.bisect_right(times, t)
    if i == 0:
        return profile[0][1]
    if i == len(profile):
        return profile[-1][1]
    (t0, v0), (t1, v1) = profile[i - 1], profile[i]
    return v0 + (v1 - v0) * (t - t0) / (t1 - t0)


def check_profile(profile, limit=35 / 3.6):
    """A profile is a list of (time, speed) with increasing times and speeds from 0 to limit."""
    if not isinstance(profile, (list, tuple)) or not profile:
        raise TjpConfigError('a driving profile is a non-empty list of [time, speed] points, got %r' % (profile,))
    last = None
    for i, point in enumerate(profile):
        if not isinstance(point, (list, tuple)) or len(point) != 2 or \
                not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in point):
            raise TjpConfigError('profile point %d must be [time, speed], got %r' % (i, point))
        t, v = point
        if last is not None and t <= last:
            raise TjpConfigError('profile point %d: time %g does not come after %g' % (i, t, last))
        if not 0 <= v <= limit + 1e-9:
            raise TjpConfigError('profile point %d: speed %g m/s outside 0 .. %.2f m/s (35 km/h)' % (i, v, limit))
        last = t
    return [tuple(float(x) for x in p) for p in profile]


class World(object):
    """A pybullet world with the two cars. Call :meth:`close` (or use ``with``) to release it."""

    def __init__(self, profile, gap=15.0, follower_speed=0.0, dt=0.02, gui=False,
                 max_accel=3.0, max_decel=8.0):
        self.profile = check_profile(profile)
        if isinstance(gap, bool) or not isinstance(gap, (int, float)) or not gap > 0:
            raise TjpConfigError('initial gap must be > 0, got %r' % (gap,))
        self.dt, self.max_accel, self.max_decel = float(dt), float(max_accel), float(max_decel)
        self.client = pybullet.connect(pybullet.GUI if gui else pybullet.DIRECT)
        shape = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=[CAR_LENGTH / 2, CAR_WIDTH / 2,
                                                                              CAR_HEIGHT / 2],
                                              physicsClientId=self.client)
        self.t = 0.0
        self.follower_x, self.follower_v = 0.0, float(follower_speed)
        self.leader_x, self.leader_v = CAR_LENGTH + gap, profile_speed(self.profile, 0.0)
        self.follower = self._body(shape, self.follower_x)
        self.leader = self._body(shape, self.leader_x)
        self.pedestrian = None
        self.collided = False

    def _body(self, shape, x, y=0.0):
        return pybullet.createMultiBody(baseMass=0, baseCollisionShapeIndex=shape,
                                        basePosition=[x, y, CAR_HEIGHT / 2], physicsClientId=self.client)

    def _move(self, body, x):
        pybullet.resetBasePositionAndOrientation(body, [x, 0.0, CAR_HEIGHT / 2], [0, 0, 0, 1],
                                                 physicsClientId=self.client)

    # -- time --------------------------------------------------------------------------------------
    def step(self, accel):
        """Advance one step with the follower's commanded acceleration (clamped to the car's limits)."""
        accel = min(self.max_accel, max(-self.max_decel, accel))
        self.t += self.dt
        if self.collided:
            accel = -self.follower_v / self.dt   # a crash stops the car where it is
        self.follower_v = max(0.0, self.follower_v + accel * self.dt)
        self.follower_x += self.follower_v * self.dt
        self.leader_v = profile_speed(self.profile, self.t)
        self.leader_x += self.leader_v * self.dt
        self._move(self.follower, self.follower_x)
        self._move(self.leader, self.leader_x)
        others = [self.leader] + ([self.pedestrian] if self.pedestrian is not None else [])
        # The bodies are placed, not simulated: pybullet reports no contact between two of them,
        # but their closest points at distance 0 are a touch.
        if any(pybullet.getClosestPoints(self.follower, other, 0.0, physicsClientId=self.client)
               for other in others):
            self.collided = True
        return accel

    # -- sensors -----------------------------------------------------------------------------------
    def _rays(self, offsets, length):
        front = self.follower_x + CAR_LENGTH / 2 + 0.01
        starts = [[front, y, CAR_HEIGHT / 2] for y in offsets]
        ends = [[front + length, y, CAR_HEIGHT / 2] for y in offsets]
        hits = pybullet.rayTestBatch(starts, ends, physicsClientId=self.client)
        return [None if hit[0] < 0 else hit[2] * length for hit in hits]

    def lasers(self):
        """The three lasers' distances to what is ahead (m), None when nothing is in range."""
        return self._rays(LASER_OFFSETS, LASER_RANGE)

    def ultrasonic(self):
        """Distance to a close obstacle ahead (m), None when nothing is within 5 m."""
        return self._rays((0.0,), ULTRASONIC_RANGE)[0]

    def imu_speed(self):
        """The follower's speed (m/s), as its IMU integrates it."""
        return self.follower_v

    def gap(self):
        """The true gap between the cars (bumper to bumper, m), for the summary."""
        return self.leader_x - self.follower_x - CAR_LENGTH

    # -- scripted events -----------------------------------------------------------------------------
    def pedestrian_steps_in(self, ahead=3.0):
        """A pedestrian steps onto the road this far ahead of the follower's bumper."""
        if self.pedestrian is None:
            shape = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=[0.2, 0.3, 0.9],
                                                  physicsClientId=self.client)
            x = self.follower_x + CAR_LENGTH / 2 + ahead + 0.2
            self.pedestrian = pybullet.createMultiBody(baseMass=0, baseCollisionShapeIndex=shape,
                                                       basePosition=[x, 0.0, 0.9], physicsClientId=self.client)

    def pedestrian_distance(self):
        """The true distance from the follower's bumper to the pedestrian (m), None when none."""
        if self.pedestrian is None:
            return None
        position, _ = pybullet.getBasePositionAndOrientation(self.pedestrian, physicsClientId=self.client)
        return position[0] - 0.2 - (self.follower_x + CAR_LENGTH / 2)

    def pedestrian_leaves(self):
        if self.pedestrian is not None:
            pybullet.removeBody(self.pedestrian, physicsClientId=self.client)
            self.pedestrian = None

    def close(self):
        if self.client is not None:
            pybullet.disconnect(self.client)
            self.client = None

    def __enter__(self):
        return self

    def __exit__(self, *_):
        self.close()
