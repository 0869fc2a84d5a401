"""The car's TJP nodes without a master: commandManager (tjp_sim.ros.tjp_nodes) and the laser voter
(tjp_sim.ros.ftm_nodes), built by their own constructors with their parameters' defaults, their ports
faked and ROS time a fake clock. Inputs are handed to them as their subscribers' threads would."""
import threading
import types

import pytest
import rospy
from aft_msgs.msg import CarCommand, PrimaryBoard
from sensor_msgs.msg import Range

from fakes import FakeClock, FakePorts
from tjp_sim.ros import ftm_nodes, tjp_nodes


def defaults(name, convert, default=None, required=False):
    """aft_ftm.ros.params.param with no parameter set: every node takes its defaults."""
    return default


@pytest.fixture
def clock(monkeypatch):
    """ROS time (the simulator's /clock, as every node reads it), set by the test."""
    clock = FakeClock(10.0)
    monkeypatch.setattr(rospy, 'get_time', lambda: clock.now)
    monkeypatch.setattr(rospy, 'get_rostime', lambda: rospy.Time.from_sec(clock.now))
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time.from_sec(clock.now)))
    return clock


def build(monkeypatch, cls, ports=FakePorts):
    monkeypatch.setattr(tjp_nodes, 'Ports', ports)
    monkeypatch.setattr(tjp_nodes, 'param', defaults)
    monkeypatch.setattr(ftm_nodes, 'param', defaults)
    return cls()


# -- commandManager: controllerPid's command is as old as its stamp ---------------------------------
def pid(accel, stamp):
    """A command of controllerPid computed at ``stamp`` (s of ROS time), as its board's After passes it on."""
    return CarCommand(stamp=rospy.Time.from_sec(stamp), accel=accel, mode=CarCommand.TJP, cycle=1,
                      source='/board_a/controller_pid')


def drive(node, clock, steps):
    """Each step: (ROS time, [commands of controllerPid arriving then]); commandManager's cycle runs
    after them. Returns the accelerations the car got."""
    for now, commands in steps:
        clock.now = now
        for msg in commands:
            node.ports.deliver('pid_command', msg)
        node._send()
    return [msg.accel for port, msg in node.ports.sent if port == 'command']


def test_a_command_computed_long_ago_by_a_resumed_board_never_reaches_the_car(monkeypatch, clock):
    """A board frozen (SIGSTOP) and resumed behind the fence, after the backup took over, publishes the
    commands it computed before it froze. They were applied as they came: 1.5 m/s^2 computed 1 s ago.
    A command older than ``hold`` is refused; the car gets what it gets from a silent controller, its
    last good command held, then braking, and one alarm says so."""
    node = build(monkeypatch, tjp_nodes.CommandManagerNode)
    accels = drive(node, clock, [
        (10.0, [pid(0.4, 10.0)]),
        (10.05, [pid(1.5, 9.0)]),                    # computed 1 s ago: the backlog of a frozen board
        (10.1, [pid(1.5, 9.1), pid(1.5, 9.2)]),
        (10.2, []),                                  # controllerPid late: its last good command held
        (10.35, []),                                 # held for hold (0.3 s): then braking
    ])
    assert accels == [0.4, 0.4, 0.4, 0.4, -3.0], accels
    assert node.ports.alarms() == ['stale_command']   # once for the run of them, not once each
    alarm = [msg for port, msg in node.ports.sent if port == 'alarms'][0]
    assert '9.000' in alarm.detail and alarm.source == node.name


def test_a_command_stamped_ahead_or_before_the_last_one_applied_is_refused(monkeypatch, clock):
    """A command stamped more than 0.5 s after commandManager's clock (a glitched or forged stamp), and
    one stamped at or before the last one applied (reordered, duplicated or replayed), change nothing."""
    node = build(monkeypatch, tjp_nodes.CommandManagerNode)
    accels = drive(node, clock, [
        (10.0, [pid(0.4, 10.0)]),
        (10.1, [pid(-1.0, 11.0),                     # 0.9 s ahead of the clock
                pid(1.0, 9.95),                      # older than the last one applied: reordered
                pid(1.2, 10.0)]),                    # the same instant again: a duplicate
        (10.12, [pid(0.5, 10.1), pid(0.7, 10.05)]),  # a fresh one taken; an older one after it is not
        (10.2, [pid(0.6, 10.6)]),                    # 0.4 s ahead: a clock lagging, taken
    ])
    assert accels == [0.4, 0.4, 0.5, 0.6], accels
    assert node.ports.alarms() == ['future_command', 'reordered_command', 'reordered_command']


def test_refused_commands_raise_one_alarm_per_run_of_them(monkeypatch, clock):
    node = build(monkeypatch, tjp_nodes.CommandManagerNode)
    drive(node, clock, [(10.0, [pid(0.4, 10.0)])])
    drive(node, clock, [(10.05, [pid(1.0, 8.0 + 0.05 * i) for i in range(20)])])   # a backlog of 20
    assert node.ports.alarms() == ['stale_command']
    drive(node, clock, [(10.1, [pid(0.3, 10.1)]), (10.15, [pid(1.0, 9.0)])])   # a good one, then stale again
    assert node.ports.alarms() == ['stale_command', 'stale_command']
    assert node.arbiter.stale == 21


# -- the laser voter: decisions leave in the order they were decided --------------------------------
def laser(stamp, value):
    msg = Range(range=value, min_range=0.1, max_range=40.0)
    msg.header.stamp = rospy.Time.from_sec(stamp)
    return msg


class OvertakingPorts(FakePorts):
    """Ports whose first message on PORT takes its time to go out: it waits until a later one has gone
    out (at most WAIT s). ``first_out`` is set once it waits."""

    PORT = 'out'   # the voter's voted gaps
    WAIT = 0.5

    def __init__(self, specs=(), callbacks=None):
        super(OvertakingPorts, self).__init__(specs, callbacks)
        self.first_out, self.second_out = threading.Event(), threading.Event()

    def publish(self, port, msg):
        if port == self.PORT and not self.first_out.is_set():
            self.first_out.set()
            self.second_out.wait(self.WAIT)
        elif port == self.PORT:
            self.second_out.set()
        super(OvertakingPorts, self).publish(port, msg)


def test_voted_gaps_leave_in_the_order_they_were_decided(monkeypatch, clock):
    """Each laser has its own subscriber thread. The voter decided under its lock but published after
    it: a decision made by one laser's thread could go out after a later one made by another's, and
    distanceSecurityCalculator took the older gap last. Here laser 0 lost its reading of t1: its reading
    of t2 decides t1 (laser 0 skipped it), and laser 1's reading of t2, in another thread, decides t2
    while t1 is still on its way out."""
    node = build(monkeypatch, ftm_nodes.LaserVoteNode, ports=OvertakingPorts)
    t1, t2 = 10.0, 10.04
    for port, msg in (('laser_1', laser(t1, 8.0)), ('laser_2', laser(t1, 8.0)), ('laser_2', laser(t2, 7.9))):
        node.ports.deliver(port, msg)
    assert node.ports.sent == []                     # t1 waits for laser 0
    first = threading.Thread(target=node.ports.deliver, args=('laser_0', laser(t2, 7.9)))
    second = threading.Thread(target=node.ports.deliver, args=('laser_1', laser(t2, 7.9)))
    first.start()
    assert node.ports.first_out.wait(5.0)            # t1 decided, on its way out
    second.start()
    first.join(5.0)
    second.join(5.0)
    out = [(msg.header.stamp.to_sec(), msg.range) for port, msg in node.ports.sent if port == 'out']
    assert out == [(pytest.approx(t1), pytest.approx(8.0)), (pytest.approx(t2), pytest.approx(7.9))], out


class SlowFirstCommand(OvertakingPorts):
    """commandManager's ports, whose first command waits until another has gone out."""

    PORT = 'command'


def test_a_safe_stop_is_the_last_command_the_car_gets_never_overtaken_by_a_cycle_computed_before_it(monkeypatch,
                                                                                                   clock):
    """The timer's cycle computed a driving command and published it after the lock; a safe stop arriving
    meanwhile sent its braking command at once, and the driving command went out after it: the car was
    told to drive after the stop (review of session 49)."""
    node = build(monkeypatch, tjp_nodes.CommandManagerNode, ports=SlowFirstCommand)
    node.ports.deliver('pid_command', pid(1.5, 10.0))
    cycle = threading.Thread(target=node._send)
    cycle.start()
    assert node.ports.first_out.wait(5.0)            # the cycle's driving command, on its way out
    stop = threading.Thread(target=node.ports.deliver, args=('safe_stop', tjp_nodes.String(data='test')))
    stop.start()
    cycle.join(5.0)
    stop.join(5.0)
    sent = [msg for port, msg in node.ports.sent if port == 'command']
    assert [m.accel for m in sent] == [1.5, pytest.approx(-node.arbiter.stop_decel)], [m.accel for m in sent]
    assert [m.cycle for m in sent] == [1, 2]


# -- commandManager: whose commands it takes (the watchdog's word; review of session 51) -------------
A, B, WATCHDOG = '/board_a/cycle_after', '/board_b/cycle_after', '/ftm/watchdog'


def sent_by(msg, sender):
    msg._connection_header = {'callerid': sender}
    return msg


@pytest.fixture
def wall(monkeypatch, clock):
    """commandManager's wall clock (the hold of a command whose sender is not named) the fake clock too."""
    monkeypatch.setattr(tjp_nodes, 'time', types.SimpleNamespace(monotonic=lambda: clock.now))
    return clock


def word(board, node, term, run='w1', sender=WATCHDOG):
    return sent_by(PrimaryBoard(stamp=rospy.Time.from_sec(10.0), board=board, nodes=[node], term=term,
                                incarnation=run), sender)


class BindingPorts(FakePorts):
    """Ports that can be bound: board_a's command comes the moment pid_command is bound (a deposed board
    publishing as the restarted commandManager subscribes)."""

    def __init__(self, specs=(), callbacks=None):
        super(BindingPorts, self).__init__(specs, callbacks)
        self.bound = []

    def bind(self, name, topic=None, **_kwargs):
        self.bound.append(name)
        if name == 'pid_command':
            self.deliver('pid_command', sent_by(pid(1.0, 10.0), A))

    def advertise_service(self):
        pass


def command_manager(monkeypatch, watchdog_runs):
    """commandManager configured as car.launch does with PBR (~sources board_a's After, ~watchdog), set up
    with ``watchdog_runs`` the master's answer on whether the watchdog publishes its word."""
    given = {'sources': [A], 'watchdog': WATCHDOG}
    monkeypatch.setattr(tjp_nodes, 'Ports', BindingPorts)
    monkeypatch.setattr(tjp_nodes, 'param', lambda name, convert, default=None, required=False:
                        given.get(name, default))
    monkeypatch.setattr(tjp_nodes.rospy, 'Timer', lambda *args, **kwargs: None)
    node = tjp_nodes.CommandManagerNode()
    monkeypatch.setattr(node, '_watchdog_runs', lambda: watchdog_runs)
    node.setup(1.0)
    if node.waiter is not None:
        node.waiter.cancel()
    return node


def test_a_restarted_command_manager_takes_no_command_before_the_watchdogs_word(monkeypatch, wall):
    """Bound before the wait for the word began, the deposed board_a's command that came in between was
    taken (review of session 51). Now every command is held from the start; the word names board_b."""
    node = command_manager(monkeypatch, watchdog_runs=True)
    assert node.pending is None and node.arbiter.sources.waiting
    node.ports.deliver('primary', word('board_b', B, 2))
    node.ports.deliver('pid_command', sent_by(pid(-1.0, 10.02), B))
    wall.now = 10.3   # board_a's command held past name_wait (0.25 s): refused
    node._send()
    assert [m.accel for p, m in node.ports.sent if p == 'command'] == [-1.0]
    assert node.driver == B and node.arbiter.foreign == 1


def test_with_no_watchdog_running_the_configured_board_is_taken_at_once(monkeypatch, clock):
    node = command_manager(monkeypatch, watchdog_runs=False)
    assert not node.arbiter.sources.waiting and node.pending == 1.0 and node.pending_sender == A
    assert node.ports.alarms() == []   # nothing to wait for: nothing to say


def test_each_foreign_sender_is_alarmed_not_only_the_last(monkeypatch, wall):
    node = build(monkeypatch, tjp_nodes.CommandManagerNode)
    node.arbiter.sources.nodes = frozenset([A])
    for i, sender in enumerate(('/forger_1', '/forger_2', B)):
        node.ports.deliver('pid_command', sent_by(pid(0.5, 10.0 + 0.001 * i), sender))
    wall.now = 10.3
    node._send()
    alarmed = [m.detail for p, m in node.ports.sent if p == 'alarms' and m.kind == 'foreign_command']
    assert len(alarmed) == 3 and all(any(s in d for d in alarmed) for s in ('/forger_1', '/forger_2', B))


def test_a_refused_word_repeated_is_alarmed_once_per_sender_and_reason(monkeypatch, clock):
    """A forger repeating its word, or a stale word resent, flooded the alarms (one per word)."""
    node = build(monkeypatch, tjp_nodes.CommandManagerNode)
    node.watchdog = WATCHDOG
    node.ports.deliver('primary', word('board_a', A, 3))
    for _ in range(10):
        node.ports.deliver('primary', word('board_b', B, 9, sender='/forger'))
        node.ports.deliver('primary', word('board_b', B, 2))   # a term passed
    assert node.ports.alarms() == ['primary_ignored', 'primary_ignored'] and node.words_refused == 20
    node.ports.deliver('primary', word('board_b', B, 4))       # a new word followed: said again
    node.ports.deliver('primary', word('board_a', A, 3))
    assert node.ports.alarms() == ['primary_ignored'] * 3
    assert '21 words refused' in [m.detail for p, m in node.ports.sent if p == 'alarms'][-1]


def test_a_forger_with_many_names_never_mutes_the_watchdogs_refused_word(monkeypatch, clock):
    node = build(monkeypatch, tjp_nodes.CommandManagerNode)
    node.watchdog = WATCHDOG
    node.ports.deliver('primary', word('board_a', A, 3))
    for i in range(100):
        node.ports.deliver('primary', word('board_b', B, 9, sender='/forger_%d' % i))
    assert len(node.ports.alarms()) == node.WORD_ALARMED_MAX
    node.ports.deliver('primary', word('board_b', B, 1, run='w2'))   # a watchdog started again disputes
    node.ports.deliver('primary', word('board_b', B, 1, run='w3'))   # and again
    assert node.ports.alarms()[-2:] == ['primary_disputed', 'primary_disputed']


def test_unknown_whether_the_watchdog_runs_is_waited_as_if_it_did(monkeypatch, wall):
    node = command_manager(monkeypatch, watchdog_runs=None)
    assert node.arbiter.sources.waiting and node.pending is None and node.waiter is not None
