"""Recovery when the failed site comes back (review of stop 39): the real RecoveryNode methods and the
real witness record, with the ROS calls, the power switch and the timers faked.

- a promotion held for the power switch, then the peer re-joined as this site's backup: the re-arm
  forgot the promotion and the Protocol stayed a backup for good, the witness naming this site primary;
- a verdict on the re-joined peer that reached Recovery before the configuration re-arming it: dropped,
  the backup never took over;
- a recovery retried after the witness was unreachable, firing after the peer re-joined: it excluded and
  fenced the new, healthy backup.
"""
import threading
import time
import types

import pytest
import rospy
from aft_msgs.msg import Configuration, Failure

from aft_ftm.master_watch import MasterWatch
from aft_ftm.power_switch import Fencing, Outcome, SwitchSpec
from aft_ftm.protocol import Role
from aft_ftm.realtime import RealtimeBurst
from aft_ftm.ros import recovery_node
from aft_ftm.ros.witness_client import WitnessUnreachable
from aft_ftm.witness import Op, Witness


class World(object):
    def __init__(self):
        self.alarms = []
        self.timers = []
        self.switch_confirms = False


@pytest.fixture
def world(monkeypatch):
    world = World()
    monkeypatch.setattr(recovery_node, 'alarm', lambda ports, mechanism, kind, detail: world.alarms.append(kind))

    class Timer(object):   # run by the test, when it says so
        def __init__(self, delay, function, args=()):
            self.function, self.args, self.daemon = function, args, False

        def start(self):
            world.timers.append(self)

    monkeypatch.setattr(recovery_node, 'threading', types.SimpleNamespace(Timer=Timer, Thread=threading.Thread,
                                                                          Lock=threading.Lock))
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(1000)))
    monkeypatch.setattr(recovery_node.rospy, 'is_shutdown', lambda: False)
    monkeypatch.setattr(recovery_node, 'call_switch', lambda spec, host, timeout: Outcome(
        world.switch_confirms, 'the switch says %s' % ('off' if world.switch_confirms else 'nothing')))
    return world


class WitnessAt(object):
    """A site's witness client on the real record."""

    def __init__(self, witness, site, incarnation):
        self.witness, self.site, self.incarnation = witness, site, incarnation
        self.down = False

    def request(self, op, **kw):
        if self.down:
            raise WitnessUnreachable('timed out')
        return self.witness.request(op, self.site, self.incarnation, kw.get('peer', ''),
                                    kw.get('peer_incarnation', ''), kw.get('claim', False), kw.get('epoch', 0))


class Roles(object):
    def __init__(self, name, calls):
        self.name, self.calls = name, calls

    def __call__(self, **request):
        self.calls.append((self.name, Role(request['role'])))
        return types.SimpleNamespace(success=True, message='ok', last_seq=7)


def recovery(site, witness, role=Role.BACKUP, switch=True):
    node = recovery_node.RecoveryNode.__new__(recovery_node.RecoveryNode)
    node.site, node.peer_ns, node.role = site, '/' + ('b' if site == 'a' else 'a'), role
    node.calls = []
    node.promote = ['/%s/after' % site]
    node.set_role_nodes = [Roles('after', node.calls)]
    node.set_role_protocol = Roles('protocol', node.calls)
    node.witness = WitnessAt(witness, site, site + '@1')
    node.fencing = Fencing(SwitchSpec('command', argv=['/bin/false']) if switch else None, 'host_b', 1.0)
    node.fence_timeout, node.timeout, node.retry = 10.0, 2.0, 0.5
    node.burst = RealtimeBurst(0)
    node.lock = threading.Lock()
    node.stopped = node.last_recovery = node.unasked = node.last_seq = node.deferred = node.retrying = None
    node.recovered = node.promotion_waits = False
    node.epoch, node.granted, node.primary_seen = witness.epoch, 0, ''
    node.fence = types.SimpleNamespace(processes=lambda: {}, shut_down_the_rest=lambda: 0, lock=threading.Lock())
    node.master = MasterWatch(60.0)
    node.events, node.ports = types.SimpleNamespace(publish=lambda msg: None), None
    node._clean_master = lambda: None
    node._start = 0
    return node


def eventually(predicate, timeout=5.0):
    """Whether predicate() holds within timeout (what a node's own thread does, waited for)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def paired(primary, backup):
    """The witness's record at epoch 2: ``primary`` registered first, ``backup`` admitted."""
    witness = Witness()
    witness.request(Op.REGISTER, primary, primary + '@1', claim=True)
    witness.request(Op.ADMIT, primary, primary + '@1', backup, backup + '@1')
    return witness


def retry_pending(world, witness):
    """Primary a, whose recovery from b's failure met an unreachable witness: retried later (a timer)."""
    world.switch_confirms = True
    a = recovery('a', witness, role=Role.PRIMARY)
    a.witness.down = True
    a._on_failure(failure())
    return a


def configuration(witness):
    return Configuration(epoch=witness.epoch, primary=witness.primary, backup=witness.backup, reason=witness.reason)


def failure(site='b', epoch=0):
    return Failure(site=site, host='host_b', pid=0, reason='no heartbeat', silence=0.03,
                   detected=rospy.Time(1000), epoch=epoch)


def test_a_promotion_waiting_for_the_switch_is_completed_when_the_peer_rejoins_as_its_backup(world):
    witness = paired('b', 'a')   # epoch 2: b primary, a backup
    a = recovery('a', witness)
    a._on_failure(failure())                                      # b hangs; the switch never confirms
    assert a.promotion_waits and ('protocol', Role.ALONE) not in a.calls and 'fence_failed' in world.alarms
    a._on_configuration(configuration(witness))                  # epoch 3: a alone
    assert a.promotion_waits
    # b is started again and re-joins: a's After, alone, transfers its state; the witness admits b@2.
    assert witness.request(Op.ADMIT, 'a', 'a@1', 'b', 'b@2', False, witness.epoch).granted
    a._on_configuration(configuration(witness))                  # epoch 4: a primary, b backup: re-armed
    assert eventually(lambda: 'promotion_unfenced' in world.alarms), world.alarms
    assert ('protocol', Role.ALONE) in a.calls, a.calls       # before: still a backup, queuing every request
    assert not a.promotion_waits


def test_a_verdict_before_the_configuration_that_rearms_recovery_is_kept_and_run(world):
    witness = paired('b', 'a')   # epoch 2 (b, a)
    a = recovery('a', witness, switch=False)
    witness.request(Op.EXCLUDE, 'b', 'b@1')                      # a partition: b excludes a first (epoch 3)
    a._on_failure(failure())                                      # a's take-over is refused
    a._on_configuration(configuration(witness))
    assert a.recovered and a.role is None
    witness.request(Op.ADMIT, 'b', 'b@1', 'a', 'a@1', False, witness.epoch)   # healed, a re-joins: epoch 4
    # b powers off at once; a's detector (re-armed by epoch 4) reports before a's Recovery sees epoch 4.
    calls = len(a.calls)
    a._on_failure(failure(epoch=witness.epoch))
    assert a.deferred is not None and len(a.calls) == calls
    a._on_configuration(configuration(witness))
    assert eventually(lambda: witness.primary == 'a'), 'dropped: nobody served again'
    assert eventually(lambda: ('after', Role.ALONE) in a.calls[calls:]), a.calls
    assert eventually(lambda: ('protocol', Role.ALONE) in a.calls[calls:]), a.calls   # the plan's last step
    assert eventually(lambda: not a.lock.locked())
    # A stale verdict (of an epoch already seen) is still dropped as before.
    b_again = len(a.calls)
    a._on_failure(failure(epoch=2))
    assert len(a.calls) == b_again and a.deferred is None


def test_a_recovery_retried_after_the_peer_rejoined_leaves_the_new_backup_alone(world):
    witness = paired('a', 'b')   # epoch 2 (a, b)
    a = retry_pending(world, witness)   # witness unreachable: retried later
    assert len(world.timers) == 1
    a.witness.down = False
    # Meanwhile the After excluded b (ack timeout), b re-joined and was admitted as b@2 (epoch 4).
    witness.request(Op.EXCLUDE, 'a', 'a@1')
    a._on_configuration(configuration(witness))
    witness.request(Op.ADMIT, 'a', 'a@1', 'b', 'b@2', False, witness.epoch)
    a._on_configuration(configuration(witness))
    epoch = witness.epoch
    timer = world.timers.pop(0)
    timer.function(*timer.args)                                   # the old retry fires now
    assert (witness.epoch, witness.primary, witness.backup) == (epoch, 'a', 'b'), 'the new backup was excluded'
    assert a.fencing.attempts == 0, 'the new backup was powered off'
    assert not a.recovered                                        # its detector's next verdict is acted on


def test_a_kept_verdict_whose_configuration_was_skipped_is_dropped(world):
    witness = paired('b', 'a')   # epoch 2 (b, a)
    a = recovery('a', witness, switch=False)
    a.recovered = True                                            # a recovery under way
    a._on_failure(failure(epoch=3))                               # judged for epoch 3, not seen here yet
    assert a.deferred is not None
    witness.request(Op.EXCLUDE, 'b', 'b@1')                      # epoch 3, then 4: only 4 is delivered
    witness.request(Op.ADMIT, 'b', 'b@1', 'a', 'a@1', False, witness.epoch)
    calls = len(a.calls)
    a._on_configuration(configuration(witness))
    assert a.deferred is None and len(a.calls) == calls          # not run against the incarnation of epoch 4


def test_a_recovery_retried_after_the_peer_registered_again_leaves_it_alone(world):
    witness = paired('a', 'b')   # epoch 2 (a, b)
    a = retry_pending(world, witness)
    a.witness.down = False
    witness.request(Op.EXCLUDE, 'a', 'a@1')                      # epoch 3: a alone; b, restarted, joins
    a._on_configuration(configuration(witness))
    timer = world.timers.pop(0)
    timer.function(*timer.args)                                   # before b's admission
    assert a.fencing.attempts == 0, 'the re-joining backup was powered off'


def test_a_grant_that_came_after_its_call_timed_out_fences_the_launcher_the_failure_report_named(world):
    """a's PROMOTE timed out (the witness was frozen) and its retry is due; the witness, resumed, grants
    the PROMOTE it had queued and publishes the configuration, which a takes as a late promotion. Its
    fail-silence must use the report that named b's launcher: before, the take-over carried pid 0, and
    only the nodes learned by pid were killed (review of session 36)."""
    from aft_ftm.sites import this_host
    witness = paired('b', 'a')                                     # epoch 2: b primary, a backup
    a = recovery('a', witness, switch=False)
    fenced = []
    a._launcher = lambda f: (fenced.append((f.pid, f.host)), ([], 'the launcher (pid %d)' % f.pid))[1]
    a.witness.down = True
    report = Failure(site='b', host=this_host(), pid=4321, reason='no heartbeat', silence=0.03,
                     detected=rospy.Time(1000))
    a._on_failure(report)                                          # unreachable: a retry is due
    assert 'witness_unreachable' in world.alarms and len(world.timers) == 1 and fenced == []
    a.witness.down = False
    assert witness.request(Op.PROMOTE, 'a', 'a@1').granted        # the queued PROMOTE, granted late
    a._on_configuration(configuration(witness))                    # epoch 3: a primary, b deposed
    assert eventually(lambda: ('protocol', Role.ALONE) in a.calls), a.calls
    assert 'late_promotion' in world.alarms and fenced == [(4321, this_host())]
    world.timers[0].function(*world.timers[0].args)               # the retry, now due: dropped
    assert fenced == [(4321, this_host())] and a.retrying is None
