"""PBR checkpoint logic: replies held until acknowledged, ordering, gaps and fencing. No ROS."""
import pytest

from aft_ftm.checkpoint import CheckpointReceiver, CheckpointSender, Decision
from aft_ftm.errors import RoleError
from aft_ftm.protocol import Role
from fakes import reply


def test_reply_is_released_only_when_the_backup_acknowledges_it():
    sender = CheckpointSender(Role.PRIMARY)
    seq = sender.hold(reply(rid=1), now=0)
    assert seq == 1 and sender.held
    released, lost = sender.on_ack(seq, ok=True)
    assert [r.id for r in released] == [1] and not lost and not sender.held


def test_duplicate_ack_releases_nothing_more():
    sender = CheckpointSender(Role.PRIMARY)
    seq = sender.hold(reply(rid=1), now=0)
    sender.on_ack(seq, ok=True)
    assert sender.on_ack(seq, ok=True) == ([], False)


def test_refused_checkpoint_releases_the_reply_and_goes_alone():
    sender = CheckpointSender(Role.PRIMARY)
    sender.hold(reply(rid=1), now=0)
    sender.hold(reply(rid=2), now=0)
    released, lost = sender.on_ack(1, ok=False)
    assert lost and sorted(r.id for r in released) == [1, 2]
    assert sender.role == Role.ALONE and not sender.needs_checkpoint()


def test_backup_lost_releases_held_replies_in_order():
    sender = CheckpointSender(Role.PRIMARY)
    for rid in (7, 8, 9):
        sender.hold(reply(rid=rid), now=0)
    assert [r.id for r in sender.go_alone()] == [7, 8, 9]
    assert sender.role == Role.ALONE and not sender.held


def test_overdue_ack_is_detected_after_timeout():
    sender = CheckpointSender(Role.PRIMARY)
    sender.hold(reply(rid=1), now=5.0)
    assert not sender.overdue(5.5, timeout=1.0)
    assert sender.overdue(6.5, timeout=1.0)


def test_sender_refuses_backup_role():
    with pytest.raises(RoleError):
        CheckpointSender(Role.BACKUP)


@pytest.mark.parametrize('last_seq,seq,sender,expected', [
    (0, 1, '/master/after', Decision.APPLY),
    (4, 5, '/master/after', Decision.APPLY),
    (4, 4, '/master/after', Decision.REACK),     # re-sent: acknowledged again, not re-applied
    (4, 2, '/master/after', Decision.REACK),
    (4, 6, '/master/after', Decision.GAP),       # 5 missing: the backup would diverge
    (0, 3, '/master/after', Decision.GAP),
    (4, 5, '/intruder/after', Decision.FENCED),  # another sender than the one we follow
])
def test_receiver_decisions(last_seq, seq, sender, expected):
    receiver = CheckpointReceiver()
    if last_seq:
        receiver.accept(last_seq, '/master/after')
    assert receiver.decide(seq, sender) == expected


def test_promoted_backup_is_fenced_against_the_old_primary():
    receiver = CheckpointReceiver()
    receiver.accept(1, '/master/after')
    assert receiver.promote() == 1
    assert receiver.decide(2, '/master/after') == Decision.FENCED


def test_backup_that_failed_to_apply_a_checkpoint_refuses_the_next_and_cannot_take_over():
    receiver = CheckpointReceiver()
    receiver.accept(1, '/master/after')
    receiver.failed(2, 'the server refused the state')
    assert receiver.decide(2, '/master/after') == Decision.FENCED
    assert receiver.decide(3, '/master/after') == Decision.FENCED
    with pytest.raises(RoleError, match='cannot take over: checkpoint 2 could not be applied'):
        receiver.promote()
    assert receiver.role == Role.BACKUP


def test_late_refusal_of_an_acknowledged_checkpoint_makes_the_primary_go_alone():
    sender = CheckpointSender(Role.PRIMARY)
    sender.on_ack(sender.hold(reply(rid=1), now=0), ok=True)
    sender.hold(reply(rid=2), now=0)
    released, lost = sender.on_ack(1, ok=False)
    assert lost and [r.id for r in released] == [2] and sender.role == Role.ALONE


# -- an adaptation replaces an After: the backup follows the new one from its first checkpoint -------

@pytest.mark.parametrize('seq,sender,first_seq,replaces,expected', [
    (1000, '/master/after_v2', 1000, '/master/after', Decision.APPLY),     # declared replacement, from its start
    (1001, '/master/after_v2', 1000, '/master/after', Decision.FENCED),    # not from its first checkpoint
    (1000, '/master/after_v2', 1000, '/master/other', Decision.FENCED),    # replaces someone else
    (1000, '/master/after_v2', 1000, '', Decision.FENCED),                 # declares nothing
    (3, '/master/after_v2', 3, '/master/after', Decision.FENCED),          # numbers below what we hold
    (1000, '/master/after', 1000, '', Decision.APPLY),                     # the same After started again
    (1001, '/master/after', 1000, '', Decision.GAP),                       # ... but not from its start
])
def test_a_replacement_after_is_followed_only_from_its_first_checkpoint(seq, sender, first_seq, replaces,
                                                                          expected):
    receiver = CheckpointReceiver()
    receiver.accept(1, '/master/after')
    receiver.accept(4, '/master/after')
    assert receiver.decide(seq, sender, first_seq, replaces) == expected


def test_a_fresh_backup_starts_at_the_senders_first_checkpoint_never_in_the_middle():
    assert CheckpointReceiver().decide(1000, '/master/after', 1000) == Decision.APPLY
    assert CheckpointReceiver().decide(1001, '/master/after', 1000) == Decision.GAP


def test_a_replacement_sender_numbers_above_the_one_it_replaces():
    old = CheckpointSender(Role.PRIMARY, first_seq=1000)
    for i in range(5):
        old.hold(reply(rid=i), now=0)
    new = CheckpointSender(Role.PRIMARY, first_seq=2000)
    assert new.hold(reply(rid=9), now=0) == 2000 > old.seq
