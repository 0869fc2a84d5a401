"""A state transfer in parts with back-pressure (aft_ftm.transfer, issue 18): the parts a window lets go,
the backup's assembly in order, and, through any loss, duplicate or reordering of parts drawn from a
printed seed, a backup that holds the exact state or refuses the transfer, never anything else."""
import random
import time

import pytest

from aft_ftm.checkpoint import CheckpointSender, Need
from aft_ftm.protocol import Role
from aft_ftm.transfer import Incoming, Outgoing, TransferError, join, split


def test_a_state_is_cut_into_parts_of_at_most_chunk_bytes_and_put_back_whole():
    state = bytes(range(256)) * 10
    parts = split(state, 1000)
    assert [len(p) for p in parts] == [1000, 1000, 560]
    assert join(parts) == state
    assert split(state, 0) == [state] and split(state, 2560) == [state] and split(b'', 10) == [b'']
    assert join(split(tuple(range(7)), 3)) == tuple(range(7))   # the simulation's states


def test_the_window_bounds_the_parts_in_flight_and_each_acknowledgment_lets_the_next_go():
    out = Outgoing(7, b'x' * 10, 2, window=2)
    assert out.count == 5
    assert out.next_parts() == [0, 1] and out.next_parts() == []   # two unacknowledged: nothing more
    assert out.acknowledged(0) and out.next_parts() == [2]
    assert not out.acknowledged(0)                                   # a duplicate is no progress
    assert out.acknowledged(2) and out.next_parts() == [3, 4]        # cumulative: 1 and 2 held
    assert out.all_sent()
    with pytest.raises(TransferError, match='only 5 of 5 were sent|acknowledged'):
        out.acknowledged(5)
    with pytest.raises(ValueError):
        Outgoing(1, b'x', 1, window=0)


def test_the_backup_assembles_in_order_acknowledges_a_duplicate_again_and_refuses_a_gap():
    inc = Incoming()
    assert inc.receive('/a/after', 9, 0, 3, b'ab') is None
    assert inc.receive('/a/after', 9, 0, 3, b'ab') is None           # again: changes nothing
    with pytest.raises(TransferError, match='came after part 0: one is missing'):
        inc.receive('/a/after', 9, 2, 3, b'ef')
    assert not inc.holding()                                          # refused whole
    assert inc.receive('/a/after', 10, 0, 3, b'ab') is None
    assert inc.receive('/a/after', 10, 1, 3, b'cd') is None
    with pytest.raises(TransferError, match='transfer 10 of /a/after in 3 parts is being received'):
        inc.receive('/b/after', 11, 2, 3, b'ef')                      # another sender's part, mid-transfer
    assert inc.receive('/a/after', 12, 0, 2, b'ab') is None           # a new transfer replaces an unfinished one
    assert inc.receive('/a/after', 12, 1, 2, b'cd') == b'abcd'
    with pytest.raises(TransferError):
        inc.receive('/a/after', 13, 3, 3, b'')                        # not a part of anything


def test_whatever_the_link_does_to_the_parts_the_backup_holds_the_exact_state_or_refuses():
    seed = int(time.time())
    rng = random.Random(seed)
    whole = refused = 0
    for _ in range(500):
        state = bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 400)))
        out = Outgoing(1, state, rng.randint(1, 64), rng.randint(1, 4))
        inc = Incoming()
        link, got, outcome = [], None, None
        for _ in range(10 * out.count + 20):        # bounded: a transfer that stalls is given up
            link += [(p, out.parts[p]) for p in out.next_parts()]
            if not link:
                break
            roll = rng.random()
            if roll < 0.05:
                link.pop(rng.randrange(len(link)))                  # lost
                continue
            if roll < 0.1:
                link.append(link[rng.randrange(len(link))])         # duplicated
            if roll < 0.15 and len(link) > 1:
                i = rng.randrange(len(link) - 1)
                link[i], link[i + 1] = link[i + 1], link[i]         # reordered
            part, data = link.pop(0)
            try:
                got = inc.receive('/a/after', 1, part, out.count, data) if out.count > 1 else data
            except TransferError:
                outcome = 'refused'
                break
            if got is not None:
                outcome = 'whole'
                break
            out.acknowledged(part)
        if outcome == 'whole':
            assert got == state, 'seed %d: the assembled state differs from the one sent' % seed
            whole += 1
        refused += outcome == 'refused'
    assert whole > 200 and refused > 10, 'seed %d: %d whole, %d refused' % (seed, whole, refused)


def test_each_part_acknowledged_restarts_the_ack_timeout_of_the_transfer_and_of_the_checkpoints_behind_it():
    sender = CheckpointSender(Role.ALONE, first_seq=1)
    seq = sender.join('/b/after', now=0.0)
    queued = sender.hold('reply', now=0.1)       # made while the parts are sent, sent after the last
    assert sender.overdue(1.5, 1.0)
    assert not sender.progress(seq + 1, 1.4)      # not the transfer under way: nothing changes
    assert sender.progress(seq, 1.4)
    assert not sender.overdue(2.3, 1.0) and sender.overdue(2.5, 1.0)
    assert sender.on_ack(seq, True) == ([], Need.ADMIT)
    assert sender.on_ack(queued, True) == (['reply'], Need.NOTHING)
    sender.depose('another primary')
    assert not sender.progress(seq, 3.0)


def test_a_joiner_catching_up_costs_clients_no_wait_and_is_admitted_only_once_it_holds_everything_released():
    sender = CheckpointSender(Role.ALONE, first_seq=1)
    seq = sender.join('/b/after', now=0.0, catch_up=True)
    during = sender.hold('r1', now=0.1)
    assert sender.releases_at_once(during) and not sender.held      # the client has it now, as ALONE
    assert sender.on_ack(seq, True) == ([], Need.NOTHING)             # the transfer held, r1 not yet
    assert not sender.ready_to_admit()
    after = sender.hold('r2', now=0.2)
    assert not sender.releases_at_once(after)                          # from the transfer's ack on, held
    assert sender.overdue(1.2, 1.0)                                    # the joiner must acknowledge r1 in time
    assert sender.on_ack(during, True) == ([], Need.ADMIT)             # it holds all that was released
    assert sender.on_ack(after, True) == (['r2'], Need.NOTHING)
    sender.admit(3)
    assert not sender.ready_to_admit() and not sender.releases_at_once(sender.hold('r3', now=0.3))


def test_a_checkpoint_the_catching_up_joiner_refuses_excludes_it():
    sender = CheckpointSender(Role.ALONE, first_seq=1)
    seq = sender.join('/b/after', now=0.0, catch_up=True)
    during = sender.hold('r1', now=0.1)
    assert sender.on_ack(during, False) == ([], Need.EXCLUDE)
    assert sender.excluded(2) == [] and not sender.catchup and sender.role == Role.ALONE
    assert sender.on_ack(seq, True) == ([], Need.NOTHING)              # a late answer changes nothing


def test_a_joiner_acknowledging_its_catch_up_steadily_is_never_taken_for_silent():
    """Review of stop 39: only a part's ack was progress; once the last part was acknowledged, every
    catch-up checkpoint had to be acknowledged within the ack timeout of it. A joiner acknowledging one
    every 10 ms was excluded at 1.0 s, and each new attempt built the same backlog: it never joined."""
    sender = CheckpointSender(Role.ALONE, first_seq=1)
    seq = sender.join('/b/after', now=0.0, catch_up=True)
    queued = [sender.hold('r%d' % i, now=0.001 * i) for i in range(120)]   # sent while the transfer went
    assert sender.on_ack(seq, True, 0.1) == ([], Need.NOTHING)
    now = 0.1
    for i, cp in enumerate(queued):
        now += 0.01
        assert not sender.overdue(now, 1.0), 'excluded after %d of %d catch-up acks at %.2f s' % (i, len(queued), now)
        assert sender.on_ack(cp, True, now)[1] == (Need.ADMIT if i == len(queued) - 1 else Need.NOTHING)
    # A joiner that stops acknowledging is still found silent, one timeout after its last ack.
    sender = CheckpointSender(Role.ALONE, first_seq=1)
    seq = sender.join('/b/after', now=0.0, catch_up=True)
    first = sender.hold('r1', now=0.01)
    sender.hold('r2', now=0.02)   # (outstanding: the joiner never acknowledges it)
    sender.on_ack(seq, True, 0.1)
    sender.on_ack(first, True, 0.5)
    assert not sender.overdue(1.4, 1.0) and sender.overdue(1.6, 1.0)


def test_a_joiner_acknowledging_more_slowly_than_checkpoints_are_made_is_excluded_in_the_end():
    sender = CheckpointSender(Role.ALONE, first_seq=1)
    seq = sender.join('/b/after', now=0.0, catch_up=True)
    sender.on_ack(seq, True, 0.0)
    now, sent = 0.0, []
    while not sender.overdue(now, 1.0):
        now += 0.01
        sent.append(sender.hold('r', now))       # 100 checkpoints a second
        if len(sent) % 2 == 0:
            sender.on_ack(sent[len(sent) // 2 - 1], True, now)   # acknowledged at half that rate
        assert now < 20.0, 'never excluded: the catch-up grows for ever'
    assert now <= 10.0 + 0.02


def test_a_long_transfer_acknowledged_part_by_part_does_not_run_out_its_catch_up_bound():
    """Review of group commit (session 33): the catch-up checkpoints made while the parts are sent
    (queued behind them) counted their CATCHUP_TIMEOUTS bound from when they were made, so a transfer of
    20 parts acknowledged every 0.6 s excluded its joiner at 10 s, every attempt alike."""
    sender = CheckpointSender(Role.ALONE, first_seq=1)
    seq = sender.join('/b/after', now=0.0, catch_up=True)
    queued = [sender.hold('r%d' % i, now=0.05 * i) for i in range(1, 6)]
    now = 0.0
    for part in range(20):
        now += 0.6
        assert not sender.overdue(now, 1.0), 'excluded at part %d (%.1f s), every part acknowledged in time' % (part, now)
        assert sender.progress(seq, now)
    assert sender.on_ack(seq, True, now)[1] == Need.NOTHING
    for cp in queued:
        now += 0.05
        assert not sender.overdue(now, 1.0)
        sender.on_ack(cp, True, now)
    assert sender.ready_to_admit()
