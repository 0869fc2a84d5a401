"""PBR's After for a pub/sub node (the car's controllerPid), with a fake clock and no ROS: a backup
follows from whichever checkpoint it gets first, a replica running alone takes a backup that asks to
join, a backup that holds no state never takes over, and the controller's state survives two
failovers with a re-join in between."""
import pytest

from aft_ftm.checkpoint import Decision, Follow
from aft_ftm.cycle_replica import STALE_STATE, CycleReplica
from aft_ftm.errors import RoleError
from aft_ftm.protocol import Role
from fakes import FakeClock

A, B = '/board_a/cycle_after', '/board_b/cycle_after'


def replica(name, role, first_seq=1000, expect='', **kw):
    return CycleReplica(name, role, first_seq, expect=expect, **kw)


def alarms(notes):
    return [n.kind for n in notes if n.alarm]


def deliver(backup, out, sender, now, node_accepts=True):
    """A checkpoint reaches the backup; returns (ok, notes) as its acknowledgment says."""
    decision, notes = backup.on_checkpoint(out.seq, sender, out.first_seq, True)
    if decision in (Decision.APPLY, Decision.APPLY_FULL):
        notes += backup.applied(out.seq, sender, node_accepts, '' if node_accepts else 'state refused', now,
                                out.first_seq)
        return node_accepts, notes
    return decision == Decision.REACK, notes


def test_every_checkpoint_is_a_state_transfer_so_a_late_backup_follows_from_the_next_one():
    primary, backup = replica(A, Role.PRIMARY), replica(B, Role.BACKUP, expect='/board_a/')
    for cycle in range(5):
        out, _ = primary.cycle_end(b'state %d' % cycle, now=cycle * 0.1)   # nobody listens yet
    ok, notes = deliver(backup, out, A, now=0.5)
    assert ok and backup.following and [n.kind for n in notes] == ['following']
    assert backup.receiver.last_seq == out.seq
    # A lost checkpoint costs nothing: the next one carries the whole state.
    primary.cycle_end(b'lost', now=0.6)
    out, _ = primary.cycle_end(b'state 7', now=0.7)
    assert deliver(backup, out, A, now=0.7)[0] and backup.receiver.last_seq == out.seq


def test_a_backup_follows_only_the_after_it_expects():
    backup = replica(B, Role.BACKUP, expect='/board_a/')
    stranger = replica('/elsewhere/cycle_after', Role.PRIMARY)
    out, _ = stranger.cycle_end(b'x', now=0)
    assert deliver(backup, out, '/elsewhere/cycle_after', now=0) == (False, [])
    assert backup.receiver.state == Follow.JOINING


def test_a_joining_backup_asks_every_join_period_until_it_follows_and_cannot_take_over_meanwhile():
    backup = replica(B, Role.BACKUP, join_period=0.25)
    asks = [t for t in (0.0, 0.1, 0.2, 0.25, 0.3, 0.5) if backup.check(t)[0]]
    assert asks == [0.0, 0.25, 0.5]
    with pytest.raises(RoleError, match='cannot take over'):
        backup.set_role(Role.ALONE, first_seq=1)
    assert backup.role == Role.BACKUP and not backup.passes_outputs()
    primary = replica(A, Role.PRIMARY)
    deliver(backup, primary.cycle_end(b's', now=0.6)[0], A, now=0.6)
    assert backup.check(1.0) == (False, [])


def test_a_replica_running_alone_takes_a_backup_that_asks_to_join_at_the_next_cycle_end():
    alone = replica(A, Role.ALONE)
    assert alone.cycle_end(b'no backup', now=0)[0] is None
    assert alone.on_join(B) == []
    out, notes = alone.cycle_end(b'state 1', now=0.1)
    assert out is not None and out.state == b'state 1' and [n.kind for n in notes] == ['join']
    assert alone.role == Role.PRIMARY
    assert [n.kind for n in alone.on_ack(out.seq, True, '', A)] == ['joined']
    assert alone.sender.admitted and alone.sender.joiner is None
    out2, _ = alone.cycle_end(b'state 2', now=0.2)
    assert out2.seq == out.seq + 1 and alone.on_ack(out2.seq, True, '', A) == []


def test_a_primary_asked_to_join_by_its_own_backup_transfers_again_without_counting_the_old_stream():
    primary = replica(A, Role.PRIMARY, ack_timeout=0.5)
    primary.cycle_end(b'never answered', now=0.0)   # its backup died with this one
    primary.on_join(B)                              # ... and came back
    out, _ = primary.cycle_end(b'state', now=0.1)
    primary.on_ack(out.seq, True, '', A)
    assert primary.check(now=1.0) == (False, [])    # the unanswered checkpoint no longer counts
    assert primary.role == Role.PRIMARY


def test_an_unacknowledged_or_refused_checkpoint_means_the_backup_is_lost_and_says_so():
    primary = replica(A, Role.PRIMARY, ack_timeout=0.5)
    primary.cycle_end(b's', now=0.0)
    assert primary.check(now=0.4) == (False, [])
    ask, notes = primary.check(now=0.6)
    assert alarms(notes) == ['backup_lost'] and primary.role == Role.ALONE
    assert primary.cycle_end(b's', now=0.7)[0] is None
    other = replica(A, Role.PRIMARY)
    out, _ = other.cycle_end(b's', now=0)
    assert alarms(other.on_ack(out.seq, False, 'state refused', A)) == ['backup_lost'] and other.role == Role.ALONE


def test_acknowledgments_addressed_to_another_after_are_ignored():
    primary = replica(A, Role.PRIMARY)
    out, _ = primary.cycle_end(b's', now=0)
    assert primary.on_ack(out.seq, False, 'not for you', '/elsewhere/cycle_after') == []
    assert primary.role == Role.PRIMARY and out.seq in primary.sender.held


@pytest.mark.parametrize('cycles,seconds,stale', [(2, 5.0, False), (10, 0.5, False), (3, 1.0, True)])
def test_a_backup_whose_primary_stopped_checkpointing_joins_again_but_only_when_its_own_node_ran(cycles, seconds,
                                                                                                 stale):
    primary, backup = replica(A, Role.PRIMARY), replica(B, Role.BACKUP, stale_after=1.0, stale_cycles=3)
    deliver(backup, primary.cycle_end(b's', now=0)[0], A, now=0)
    notes = []
    for i in range(cycles):
        notes += backup.cycle_end(b'own', now=seconds * (i + 1) / cycles)[1]
    assert (alarms(notes) == ['backup_invalid']) == stale
    assert backup.following != stale
    if stale:
        assert backup.check(now=seconds)[0]   # it asks to join at once
        with pytest.raises(RoleError):
            backup.set_role(Role.ALONE, first_seq=1)


def test_a_backup_whose_node_refuses_a_state_joins_again():
    primary, backup = replica(A, Role.PRIMARY), replica(B, Role.BACKUP)
    deliver(backup, primary.cycle_end(b'good', now=0)[0], A, now=0)
    ok, notes = deliver(backup, primary.cycle_end(b'bad', now=0.1)[0], A, now=0.1, node_accepts=False)
    assert not ok and alarms(notes) == ['backup_invalid'] and backup.receiver.state == Follow.JOINING


def test_role_changes_from_outside():
    primary = replica(A, Role.PRIMARY)
    with pytest.raises(RoleError):
        replica(A, Role.ALONE).set_role(Role.PRIMARY, first_seq=1)
    with pytest.raises(RoleError):
        primary.set_role(Role.BACKUP, first_seq=1)
    assert primary.set_role(Role.PRIMARY, first_seq=1) == 0   # no change
    assert primary.set_role(Role.ALONE, first_seq=1) == 0 and primary.role == Role.ALONE
    backup = replica(B, Role.BACKUP)
    assert backup.set_role(Role.BACKUP, first_seq=1) == 0     # the watchdog's connection check


# -- the car's pair, end to end ------------------------------------------------------------------------
class Board(object):
    """A board: controllerPid (its state: the integral of the error, one step a cycle) and its After."""

    def __init__(self, name, role, now, peer):
        self.name = name
        self.after = CycleReplica('/%s/cycle_after' % name, role, int(now * 1e6) + 1, expect='/%s/' % peer)
        self.integral = 0          # a board that starts holds no state of the controller's
        self.on = True


class Pair(object):
    def __init__(self):
        self.clock = FakeClock(0.0)
        self.boards = {'board_a': Board('board_a', Role.PRIMARY, 0.0, 'board_b'),
                       'board_b': Board('board_b', Role.BACKUP, 0.0, 'board_a')}
        self.commands = []         # (t, board, integral): what the car got
        self.notes = []

    def cycle(self):
        now = self.clock.advance(0.1)
        live = [b for b in self.boards.values() if b.on]
        for board in live:   # the join requests of backups holding no state
            ask, notes = board.after.check(now)
            self.notes += notes
            if ask:
                for other in live:
                    if other is not board:
                        self.notes += other.after.on_join(board.after.name)
        for board in live:
            board.integral += 1   # every node computes the cycle on the same inputs
            if board.after.passes_outputs():
                self.commands.append((now, board.name, board.integral))
        for board in live:       # then the cycle ends are checkpointed
            out, notes = board.after.cycle_end(board.integral, now)
            self.notes += notes
            for other in live:
                if out is not None and other is not board:
                    decision, notes = other.after.on_checkpoint(out.seq, board.after.name, out.first_seq, True)
                    if decision in (Decision.APPLY, Decision.APPLY_FULL):
                        other.integral = out.state
                        notes += other.after.applied(out.seq, board.after.name, True, '', now)
                    self.notes += notes
                    self.notes += board.after.on_ack(out.seq, decision != Decision.JOINING, '', board.after.name)

    def run(self, seconds):
        for _ in range(int(round(seconds / 0.1))):
            self.cycle()

    def power_off(self, name):
        self.boards[name].on = False

    def start_again(self, name, peer):
        self.boards[name] = Board(name, Role.BACKUP, self.clock.now, peer)

    def promote(self, name):
        return self.boards[name].after.set_role(Role.ALONE, int(self.clock.now * 1e6) + 1)


def test_the_controller_state_survives_two_failovers_with_a_rejoin_in_between():
    pair = Pair()
    pair.run(2.0)
    pair.power_off('board_a')
    pair.promote('board_b')
    pair.run(1.0)
    pair.start_again('board_a', 'board_b')
    with pytest.raises(RoleError):   # back, but holding nothing: it must not take over
        pair.promote('board_a')
    pair.run(1.0)
    assert pair.boards['board_a'].after.following
    assert pair.boards['board_b'].after.role == Role.PRIMARY
    pair.power_off('board_b')
    pair.promote('board_a')
    pair.run(1.0)
    # One command per cycle, from exactly one board at a time, and the integral never jumps.
    integrals = [c[2] for c in pair.commands]
    assert integrals == list(range(1, 51))
    assert [c[1] for c in pair.commands] == ['board_a'] * 20 + ['board_b'] * 20 + ['board_a'] * 10
    assert not [n for n in pair.notes if n.alarm]


def test_a_primary_started_again_behind_the_clock_is_a_gap_for_its_backup_not_copies():
    """Review of stop 38: the primary's cycle After respawned under its name, numbering from a clock
    stepped back below the checkpoints its backup held; each was acknowledged as a re-sent copy and
    never applied. It is a gap now: the backup says it cannot follow and joins again."""
    primary, backup = replica(A, Role.PRIMARY, first_seq=5000), replica(B, Role.BACKUP, expect='/board_a/')
    out, _ = primary.cycle_end(b'state 1', now=0.0)
    assert deliver(backup, out, A, now=0.0)[0]
    again, _ = replica(A, Role.PRIMARY, first_seq=40).cycle_end(b'state 2', now=0.1)
    ok, notes = deliver(backup, again, A, now=0.1)
    assert not ok and alarms(notes) and not backup.following


# -- a node that hangs (its process lives, its board heartbeats on) -----------------------------------
def cycling(after, until, start=0.0, period=0.1, rate=1.0, backup=None):
    """The node ends a cycle every ``period`` of its clock from ``start`` to ``until`` (wall = clock / rate);
    after each the After checkpoints (to ``backup``, which acknowledges) and the watch looks. Returns the
    clock at the last cycle end, and what the watch said."""
    said, t = [], start
    while t <= until + 1e-9:
        said += after.node_cycled(t, t / rate)
        out, _ = after.cycle_end(b'state', now=t / rate)
        if backup is not None:   # its node runs on the same inputs, a little behind
            backup.node_cycled(t - period / 10, t / rate)
            assert backup.cycle_end(b'own', now=t / rate) == (None, [])
        if out is not None and backup is not None:
            ok, _ = deliver(backup, out, after.name, now=t / rate)
            after.on_ack(out.seq, ok, '', after.name)
        said.append(after.check_node(t, t / rate))
        t += period
    return t - period, said


def pair(cycle_timeout=0.5, **kw):
    """A PRIMARY with a following backup."""
    primary = replica(A, Role.PRIMARY, cycle_timeout=cycle_timeout, **kw)
    backup = replica(B, Role.BACKUP, cycle_timeout=cycle_timeout)   # (board.launch gives both boards the same)
    out, _ = primary.cycle_end(b's0', now=0.0)
    ok, _ = deliver(backup, out, A, now=0.0)
    primary.on_ack(out.seq, ok, '', A)
    return primary, backup


def test_a_primary_whose_node_hangs_fail_stops_once_and_passes_nothing_on_from_then_on():
    primary, backup = pair()
    last, said = cycling(primary, 3.0, backup=backup)
    assert all(s == (None, []) for s in said if isinstance(s, tuple)) and not primary.sender.held
    assert primary.check_node(last + 0.5, last + 0.5) == (None, [])        # at the timeout: not yet
    stop, notes = primary.check_node(last + 0.51, last + 0.51)
    assert 'ended no cycle for 0.51 s' in stop and 'backup takes over' in stop and alarms(notes) == ['node_hung']
    assert primary.check_node(last + 5.0, last + 5.0) == (None, [])        # said once
    assert not primary.passes_outputs()                                     # a node resumed now is not the system's
    assert primary.cycle_end(b'late', now=9.0) == (None, [])                # nor are its checkpoints
    primary.node_cycled(last + 5.1, last + 5.1)
    assert not primary.passes_outputs() and primary.check_node(last + 9.0, last + 9.0) == (None, [])


def test_a_primary_whose_backup_did_not_acknowledge_its_last_checkpoint_says_the_hang_and_does_not_stop():
    """The backup's board lost power just before the node hung: a fail-stop would leave nobody. The hang is
    said; the fail-stop comes only if the acknowledgment does (a slow backup), never without it."""
    primary, backup = pair()
    last, _ = cycling(primary, 2.0, backup=backup)
    out, _ = primary.cycle_end(b'last', now=last + 0.1)      # its last cycle: the backup never answers
    primary.node_cycled(last + 0.1, last + 0.1)
    stop, notes = primary.check_node(last + 0.7, last + 0.7)
    assert stop is None and alarms(notes) == ['node_hung'] and 'not acknowledged' in notes[0].detail
    assert primary.check_node(last + 0.8, last + 0.8) == (None, []) and primary.passes_outputs()
    primary.on_ack(out.seq, True, '', A)                     # the backup was only slow
    stop, notes = primary.check_node(last + 0.9, last + 0.9)
    assert stop and alarms(notes) == ['node_hung'] and not primary.passes_outputs()


@pytest.mark.parametrize('rate', [20.0, 2.0, 1.0, 0.5, 0.1])
def test_at_any_rate_the_backup_is_still_valid_when_the_hung_primary_is_failed_over(rate):
    """The primary sees the hang after cycle_timeout on the node's clock (and 0.1 s of wall clock at
    least); the watchdog's failover takes a few tens of ms of wall clock more. The backup's own
    staleness must not come first: before, at rate 0.5, it went invalid 1 s of wall clock after its
    last checkpoint, when the primary's detection alone took 1 s, and the failover failed."""
    primary, backup = pair()
    last, _ = cycling(primary, 2.0, rate=rate, backup=backup)
    t, stopped_at = last, None
    while stopped_at is None:                # the backup's node runs on; the primary's is hung
        t += 0.1
        backup.node_cycled(t, t / rate)
        assert backup.cycle_end(b'own', now=t / rate) == (None, [])
        stop, _ = primary.check_node(t, t / rate)
        stopped_at = t if stop else None
        assert t < last + 5.0
    assert stopped_at - last <= 0.5 + 0.1 + 1e-9 or (stopped_at - last) / rate <= 0.1 + 0.1 / rate + 1e-9
    wall_failover = 0.2                      # the watchdog's timeout, the fencing and the promotion, generously
    t_promoted = stopped_at + wall_failover * rate
    while t < t_promoted:
        t += 0.1
        backup.node_cycled(t, t / rate)
        backup.cycle_end(b'own', now=t / rate)
    assert backup.following, 'rate %g: the backup went stale before the failover' % rate
    assert backup.set_role(Role.ALONE, first_seq=7) > 0


@pytest.mark.parametrize('seed', range(30))
def test_a_stopped_clock_a_clock_gone_back_a_suspension_or_late_cycles_are_never_a_hang(seed):
    """Drawn from a seed: cycles late by up to just under the timeout, the node's clock stopped for any
    wall time (a crashed simulator), set back (restarted), the After's inputs held by a suspension for
    any time, a replica that reads no clock yet (0); none fail-stops a primary nor invalidates a
    backup. Then a real silence does, once."""
    import random
    rng = random.Random(seed)
    timeout = rng.choice([0.3, 0.5, 1.0])
    role = rng.choice([Role.PRIMARY, Role.BACKUP])
    if role == Role.PRIMARY:
        after, _ = pair(timeout)
    else:
        primary, after = replica(A, Role.PRIMARY), replica(B, Role.BACKUP, cycle_timeout=timeout)
        deliver(after, primary.cycle_end(b's0', now=0.0)[0], A, now=0.0)
    t = rng.uniform(1, 100)
    wall = 0.0

    def ok():
        return after.passes_outputs() if role == Role.PRIMARY else after.following
    after.node_cycled(t, wall)
    for _ in range(200):
        event = rng.random()
        if event < 0.55:                     # a cycle, late by up to just under the timeout
            step = rng.uniform(0.0, timeout * 0.98)
            t, wall = t + step, wall + step
            said = after.node_cycled(t, wall)
        elif event < 0.65:                   # the clock stops: any number of looks, any wall time
            said = []
            for _ in range(rng.randint(1, 50)):
                wall += rng.uniform(0, 1.0)
                said.append(after.check_node(t, wall))
        elif event < 0.7:                    # this replica reads no clock yet
            wall += rng.uniform(0, 5.0)
            said = [after.check_node(0.0, wall)]
        elif event < 0.8:                    # set back, then a look before the next cycle
            t -= rng.uniform(0.1, t - 0.05)
            said = [after.check_node(t, wall), after.check_node(t + timeout * 0.9, wall + timeout * 0.9)]
            t, wall = t + timeout * 0.95, wall + timeout * 0.95
            after.node_cycled(t, wall)
        else:                                # held for any time, the node's clock running on
            said = []
            for _ in range(rng.randint(1, 20)):
                step = rng.uniform(0.0, 5.0)
                t, wall = t + step, wall + step
                said.append(after.check_node(t, wall, held=True))
            said.append(after.check_node(t + timeout * 0.9, wall + timeout * 0.9))
            t, wall = t + timeout * 0.95, wall + timeout * 0.95
            after.node_cycled(t, wall)
        assert ok(), 'seed %d (%s): a false hang: %r' % (seed, role.name, said)
        assert after.check_node(t, wall) == (None, [])
    stop, notes = after.check_node(t + timeout * 1.01, wall + timeout * 1.01)
    if role == Role.PRIMARY:
        assert stop and alarms(notes) == ['node_hung'], 'seed %d' % seed
    else:
        assert stop is None and alarms(notes) == ['backup_invalid'] and not after.following, 'seed %d' % seed


def test_a_short_silence_on_the_wall_clock_is_not_a_hang_however_fast_the_simulation():
    primary, backup = pair()
    last, _ = cycling(primary, 40.0, rate=20.0, backup=backup)
    assert primary.check_node(last + 0.9, last / 20.0 + 0.05) == (None, [])   # 0.9 s of its clock, 45 ms of wall
    stop, _ = primary.check_node(last + 2.1, last / 20.0 + 0.105)
    assert stop


def test_a_replica_alone_whose_node_hangs_raises_an_alarm_each_time_and_does_not_stop():
    alone = replica(A, Role.ALONE, cycle_timeout=0.5)
    assert alone.check_node(10.0, 10.0) == (None, [])   # no cycle yet: not watched (the node waits for inputs)
    last, _ = cycling(alone, 2.0)
    stop, notes = alone.check_node(last + 0.6, last + 0.6)
    assert stop is None and alarms(notes) == ['node_hung'] and 'no backup can take over' in notes[0].detail
    assert [n.kind for n in alone.node_cycled(last + 2.0, last + 2.0)] == ['node_resumed'] and alone.passes_outputs()
    stop, notes = alone.check_node(last + 2.6, last + 2.6)
    assert stop is None and alarms(notes) == ['node_hung']   # a second hang is told again


def test_a_following_backup_whose_node_hangs_can_no_longer_take_over_nor_asks_to_join_until_it_resumes():
    primary, backup = replica(A, Role.PRIMARY), replica(B, Role.BACKUP, cycle_timeout=0.5)
    deliver(backup, primary.cycle_end(b's1', now=0.0)[0], A, now=0.0)
    last, _ = cycling(backup, 1.0)
    assert backup.following
    stop, notes = backup.check_node(last + 0.6, last + 0.6)
    assert stop is None and alarms(notes) == ['backup_invalid'] and 'hangs' in notes[0].detail
    with pytest.raises(RoleError):
        backup.set_role(Role.ALONE, first_seq=1)     # the watchdog cannot promote it
    assert backup.check(now=5.0) == (False, [])     # it could not take a state transfer: it does not ask
    backup.node_cycled(last + 3.0, last + 3.0)
    assert backup.check(now=6.0) == (True, [])      # resumed: it asks to join again


def test_a_state_its_hung_node_takes_once_resumed_does_not_make_the_backup_follow_again():
    """The backup's After was in the node's set_state when the node hung; the watch invalidated it. The
    call returns once the node resumes, seconds later: that old state must be refused (acknowledged as
    such), not followed from."""
    primary, backup = replica(A, Role.PRIMARY), replica(B, Role.BACKUP, cycle_timeout=0.5)
    deliver(backup, primary.cycle_end(b's1', now=0.0)[0], A, now=0.0)
    last, _ = cycling(backup, 1.0)
    out, _ = primary.cycle_end(b's2', now=last)
    decision, _ = backup.on_checkpoint(out.seq, A, out.first_seq, True)
    assert decision in (Decision.APPLY, Decision.APPLY_FULL) and backup.refusal(out.seq) is None
    assert alarms(backup.check_node(last + 0.6, last + 0.6)[1]) == ['backup_invalid']   # meanwhile, hung
    assert backup.refusal(out.seq)                  # the caller acknowledges it as refused
    backup.node_cycled(last + 3.0, last + 3.0)      # resumed: its set_state answers, it cycles again
    assert backup.refusal(out.seq) == STALE_STATE
    notes = backup.applied(out.seq, A, True, '', now=last + 3.0, first_seq=out.first_seq)
    assert not backup.following and [n.kind for n in notes] == ['join_failed'] and 'hung' in notes[0].detail


def test_a_node_that_hangs_just_after_its_clock_went_back_is_still_seen():
    primary, _ = pair()
    primary.node_cycled(50.0, 50.0)
    assert primary.check_node(1.0, 50.05) == (None, [])   # the simulation started again at 0: counted from here
    stop, _ = primary.check_node(1.6, 50.65)
    assert stop and 'ended no cycle for 0.60 s' in stop


def test_without_a_cycle_timeout_a_silent_node_is_not_watched():
    primary = replica(A, Role.PRIMARY)
    last, _ = cycling(primary, 1.0)
    assert primary.check_node(last + 1000.0, last + 1000.0) == (None, []) and primary.passes_outputs()
    with pytest.raises(ValueError, match='cycle_timeout'):
        replica(A, Role.PRIMARY, cycle_timeout=-1)


def test_a_backup_whose_node_still_hangs_takes_no_state_transfer_and_so_never_follows_again():
    """Review of session 37: the node's set_state may answer while its cycle is stuck. A JOINING backup
    takes any state transfer: it followed again, acknowledged, and stayed promotable with a node that
    runs nothing."""
    primary, backup = replica(A, Role.PRIMARY), replica(B, Role.BACKUP, cycle_timeout=0.5)
    deliver(backup, primary.cycle_end(b's1', now=0.0)[0], A, now=0.0)
    last, _ = cycling(backup, 1.0)
    assert alarms(backup.check_node(last + 0.6, last + 0.6)[1]) == ['backup_invalid']
    primary.on_join(B)
    out, _ = primary.cycle_end(b'transfer', now=last + 0.7)
    assert backup.refusal(out.seq) is not None      # the caller acknowledges it as refused
    _, notes = deliver(backup, out, A, now=last + 0.7)
    assert not backup.following and 'hangs' in notes[0].detail
    with pytest.raises(RoleError):
        backup.set_role(Role.ALONE, first_seq=1)


def test_a_primary_whose_joiner_has_not_acknowledged_its_state_transfer_does_not_fail_stop():
    """Review of session 37: a restarted backup asked to join; the transfer went out and the primary's node
    hung at once. Fail-stopped then, the watchdog fenced it and could promote nobody."""
    primary, backup = pair()
    last, _ = cycling(primary, 2.0, backup=backup)
    primary.on_join('/board_b/cycle_after_again')
    primary.node_cycled(last + 0.1, last + 0.1)
    out, _ = primary.cycle_end(b'transfer', now=last + 0.1)
    assert out is not None and primary.sender.join_seq == out.seq and not primary.sender.held
    stop, notes = primary.check_node(last + 0.7, last + 0.7)
    assert stop is None and alarms(notes) == ['node_hung'] and primary.passes_outputs()


def test_a_cycle_end_stamped_0_is_no_time_to_count_a_hang_from():
    primary, backup = pair()
    primary.node_cycled(0.0, 5.0)            # the node read no clock yet
    assert primary.check_node(30.0, 5.2) == (None, [])
    last, _ = cycling(primary, 32.0, start=31.0, backup=backup)
    assert primary.check_node(last + 0.6, last + 0.6)[0]


# -- session 38: a hung After, told by its crash detector ----------------------------------------
def test_only_a_primary_whose_backup_is_admitted_and_answers_says_a_backup_could_take_over_from_it():
    """Its signs of life say it (``alive``): its crash detector fail-stops the board on their silence
    only then. A backup, a primary alone, or one whose backup let a checkpoint wait past ack_timeout
    is not replaceable: a hung After there is alarmed, and it serves again once it resumes. A
    checkpoint in flight (a round trip at every cycle) does not make it unreplaceable: a sign taken
    then said no, and a hang right after it was never failed over (review of session 38)."""
    primary, backup = pair()
    assert primary.replaceable(0.1) and not backup.replaceable(0.1)
    out, _ = primary.cycle_end(b'in flight', now=1.0)
    assert primary.replaceable(1.01) and primary.replaceable(1.5)        # (ack_timeout 0.5 s)
    assert not primary.replaceable(1.51)                                  # its backup may be gone
    primary.on_ack(out.seq, True, '', A)
    assert primary.replaceable(1.6)
    primary.on_join(B)                                                    # a state transfer asked for
    assert not primary.replaceable(1.6)
    primary, _ = pair()
    primary.set_role(Role.ALONE, first_seq=0)
    assert not primary.replaceable(2.0) and not replica(A, Role.ALONE).replaceable(2.0)


def test_a_backup_whose_site_fail_stopped_refuses_checkpoints_and_never_asks_to_join():
    """Its board's crash detector fail-stopped the board (its After gave no sign of life, say) and
    beats no more: the watchdog will never promote it. Before, its After, resumed, went on
    acknowledging, and the primary counted on a backup that could not take over. Now the primary
    hears a refusal at its next checkpoint and goes on alone, said."""
    primary, backup = pair()
    notes = backup.site_stopped('no sign of life on /board_b/after_alive: it hangs')
    assert alarms(notes) == ['site_stopped'] and backup.site_stopped('again') == []   # said once
    out, _ = primary.cycle_end(b's1', now=1.0)
    ok, _ = deliver(backup, out, A, now=1.0)
    assert not ok and backup.on_checkpoint(out.seq, A, out.first_seq, True)[0] == Decision.FENCED
    assert alarms(primary.on_ack(out.seq, ok, 'site fail-stopped', A)) == ['backup_lost']
    assert not primary.replaceable(1.1)
    assert not any(backup.check(t)[0] for t in (2.0, 5.0, 60.0))   # never asks to join again
    assert 'fail-stopped' in backup.refusal(out.seq) and not backup.passes_outputs()


def test_a_primary_whose_site_fail_stopped_serves_on_until_it_is_fenced():
    """A primary's site fail-stops so that its backup takes over, and the watchdog then fences it.
    If no backup can (it failed meanwhile), the watchdog leaves the silent primary running: made
    inert, nobody would drive (review of session 38). It says so and serves on."""
    primary, backup = pair()
    notes = primary.site_stopped('the After hung')
    assert alarms(notes) == ['site_stopped'] and 'serves on' in notes[0].detail
    assert primary.passes_outputs() and primary.cycle_end(b's1', now=2.0)[0] is not None


def test_a_primary_the_watchdog_deposed_while_it_could_not_hear_stops_and_fails_its_site():
    """board_a froze past its failover on a host nobody could power off: on resuming it hears the
    watchdog name board_b the primary (term 2). Before session 51 it passed its outputs on for good."""
    primary = replica(A, Role.PRIMARY)
    assert primary.primary_named('board_a', 'board_a', 1, 'w1') == (None, [])   # itself, at the start
    assert primary.passes_outputs()
    stop, notes = primary.primary_named('board_a', 'board_b', 2, 'w1')
    assert 'board board_b' in stop and alarms(notes) == ['deposed']
    assert not primary.passes_outputs()
    assert primary.cycle_end(b'state', 1.0)[0] is None      # no checkpoint either
    assert primary.primary_named('board_a', 'board_b', 2, 'w1') == (None, [])   # said once


@pytest.mark.parametrize('role', [Role.BACKUP, Role.ALONE])
def test_the_word_naming_another_board_changes_nothing_for_a_backup_nor_for_the_board_named(role):
    r = replica(B, role)
    assert r.primary_named('board_b', 'board_a' if role == Role.BACKUP else 'board_b', 5, 'w1') == (None, [])
    assert r.stopped is None


def test_an_earlier_term_or_another_watchdog_run_deposes_nobody():
    """A replayed or reordered word of a passed term, and a watchdog started again (which starts from its
    configured primary whatever board drives) naming another board: said, not obeyed. The word in force
    heard again (a latched word re-sent on a reconnect) is silent. Another run naming the board in
    force is followed from then on."""
    alone = replica(B, Role.ALONE)
    assert alone.primary_named('board_b', 'board_b', 2, 'w1') == (None, [])
    assert alone.primary_named('board_b', 'board_b', 2, 'w1') == (None, [])   # the same again: silent
    stop, notes = alone.primary_named('board_b', 'board_a', 1, 'w1')         # reordered, or replayed
    assert stop is None and alarms(notes) == ['primary_ignored']
    stop, notes = alone.primary_named('board_b', 'board_a', 1, 'w2')         # a watchdog started again
    assert stop is None and alarms(notes) == ['primary_disputed'] and alone.passes_outputs()
    assert alone.primary_named('board_b', 'board_b', 1, 'w2') == (None, [])   # w2 names board_b: adopted
    stop, notes = alone.primary_named('board_b', 'board_a', 2, 'w2')
    assert stop and alarms(notes) == ['deposed'] and not alone.passes_outputs()


def test_a_board_started_again_and_promoted_before_it_heard_the_latched_word_is_not_deposed_by_it():
    """board_a failed (term 2 named board_b), was started again, joined, and board_b failed in turn: the
    watchdog made board_a ALONE before board_a's After handled the latched word of term 2. Taken as news,
    it deposed the board that just took over (review of session 51). A later word is news."""
    _, alone = pair()                # (the board started again, joined: it holds a checkpoint)
    alone.set_role(Role.ALONE, 1)
    assert alone.primary_named('board_a', 'board_b', 2, 'w1') == (None, []) and alone.passes_outputs()
    assert alone.primary_named('board_a', 'board_a', 3, 'w1') == (None, []) and alone.passes_outputs()
    stop, notes = alone.primary_named('board_a', 'board_b', 4, 'w1')
    assert stop and alarms(notes) == ['deposed']


def test_a_primary_whose_first_word_names_another_board_steps_down():
    """Frozen before its subscription to the word connected, the primary hears the take-over's latched
    word first: exempt as a first word, it ran on as a second primary (review of session 52)."""
    primary = replica(A, Role.PRIMARY)
    stop, notes = primary.primary_named('board_a', 'board_b', 2, 'w1')
    assert stop and alarms(notes) == ['deposed'] and not primary.passes_outputs()


def test_a_watchdog_run_left_is_never_followed_again():
    """Run w2 adopted (it named the board in force), then a late word of w1 naming that board too: it
    re-adopted w1, and w2's next take-over was disputed for good (review of session 51)."""
    alone = replica(B, Role.ALONE)
    assert alone.primary_named('board_b', 'board_b', 2, 'w1') == (None, [])
    assert alone.primary_named('board_b', 'board_b', 1, 'w2') == (None, [])   # adopted
    stop, notes = alone.primary_named('board_b', 'board_b', 2, 'w1')         # late, from the run left
    assert stop is None and alarms(notes) == ['primary_ignored'] and 'left' in notes[0].detail
    stop, notes = alone.primary_named('board_b', 'board_a', 2, 'w2')         # w2's take-over: obeyed
    assert stop and alarms(notes) == ['deposed']


def test_a_word_naming_no_node_deposes_nobody():
    primary = replica(A, Role.PRIMARY)
    stop, notes = primary.primary_named('board_a', 'board_b', 2, 'w1', names_nodes=False)
    assert stop is None and alarms(notes) == ['primary_ignored'] and primary.passes_outputs()
