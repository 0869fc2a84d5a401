"""The pybullet road without a master: sensors see what is there, a collision is a collision, and the
TJP's control logic keeps the follower safe behind a stop-and-go leader."""
import pytest

from tjp_sim.control import CommandArbiter, EmergencyBraking, PidController, SafetyDistance
from tjp_sim.errors import TjpConfigError
from tjp_sim.filters import vote
from tjp_sim.world import World, check_profile, profile_speed

STOP_AND_GO = [[0, 8.0], [10, 8.0], [14, 0.0], [20, 0.0], [28, 9.0], [40, 9.0]]


@pytest.mark.parametrize('t,speed', [(0, 8.0), (12, 4.0), (14, 0.0), (24, 4.5), (100, 9.0)])
def test_a_driving_profile_is_linear_between_its_points(t, speed):
    assert profile_speed(check_profile(STOP_AND_GO), t) == pytest.approx(speed)


@pytest.mark.parametrize('profile,message', [
    ([], 'non-empty list'),
    ([[0, 5], [0, 6]], 'does not come after'),
    ([[0, 12.0]], 'outside 0 .. 9.72 m/s'),
    ([[0, 'fast']], 'must be \\[time, speed\\]'),
])
def test_a_bad_profile_is_refused_naming_the_point(profile, message):
    with pytest.raises(TjpConfigError, match=message):
        check_profile(profile)


def test_the_lasers_measure_the_gap_and_the_imu_the_speed():
    with World([[0, 5.0]], gap=12.0, follower_speed=5.0) as world:
        for _ in range(50):
            world.step(0.0)
        assert world.lasers() == pytest.approx([12.0] * 3, abs=0.05)
        assert world.imu_speed() == pytest.approx(5.0) and world.gap() == pytest.approx(12.0)
        assert world.ultrasonic() is None and not world.collided


def test_the_ultrasonic_sensor_sees_a_pedestrian_stepping_in():
    with World([[0, 5.0]], gap=20.0, follower_speed=5.0) as world:
        world.pedestrian_steps_in(ahead=3.0)
        assert world.ultrasonic() == pytest.approx(3.0, abs=0.05)
        world.pedestrian_leaves()
        assert world.ultrasonic() is None


def test_driving_into_the_leader_is_a_collision():
    with World([[0, 0.0]], gap=5.0, follower_speed=5.0) as world:
        for _ in range(100):
            world.step(0.0)
        assert world.collided


def drive(world, seconds, pid=None, pedestrian_at=None, emergency_braking=True):
    """The TJP loop on the true sensors: lasers voted, controllerPid, commandManager, Emergency Braking."""
    pid, safety, arbiter, braking = pid or PidController(), SafetyDistance(), CommandArbiter(), EmergencyBraking()
    worst = float('inf')
    while world.t < seconds:
        if pedestrian_at is not None and world.t >= pedestrian_at[0]:
            world.pedestrian_steps_in(ahead=pedestrian_at[1])
            pedestrian_at = None
        if emergency_braking:
            arbiter.emergency(braking.update(world.ultrasonic(), world.t, world.imu_speed()))
        gap = vote(world.lasers()).value
        command = pid.update(gap, safety(world.imu_speed()), world.t) if gap is not None else None
        world.step(arbiter.command(command, world.t))
        worst = min(worst, world.gap() / safety(world.imu_speed()))
    return worst


def test_the_tjp_follows_a_stop_and_go_leader_without_collision():
    with World(STOP_AND_GO, gap=SafetyDistance()(8.0), follower_speed=8.0) as world:
        worst = drive(world, 40.0)
        assert not world.collided and worst > 0.9
        assert world.imu_speed() == pytest.approx(9.0, abs=0.3)


def test_emergency_braking_stops_the_car_before_a_pedestrian_and_waits_for_them_to_leave():
    # At 5 m/s the car stops within 3.6 m (braking_distance): inside the ultrasonic's 5 m range.
    with World([[0, 5.0]], gap=SafetyDistance()(5.0), follower_speed=5.0) as world:
        drive(world, 20.0, pedestrian_at=(5.0, 4.8))
        assert not world.collided and world.imu_speed() == 0.0
        world.pedestrian_leaves()
        drive(world, 30.0)
        assert not world.collided and world.imu_speed() > 3.0   # the TJP drives on


def test_without_emergency_braking_the_same_pedestrian_is_hit():
    """The control experiment: the TJP alone follows the leader and does not see the pedestrian."""
    with World([[0, 5.0]], gap=SafetyDistance()(5.0), follower_speed=5.0) as world:
        drive(world, 20.0, pedestrian_at=(5.0, 4.8), emergency_braking=False)
        assert world.collided
