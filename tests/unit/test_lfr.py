"""LFR logic: replies held until the follower computed them, exclusion, joins by one state transfer,
late Joins, refusals, role changes, stray senders. No ROS."""
import random
import types

import pytest

from aft_ftm.errors import RoleError
from aft_ftm.lfr import (EDGES, ROLE_OF, Ack, ConfChange, JoinDecision, JoinStep, LfrAfter, LfrForwarder, Out,
                         State)
from aft_ftm.protocol import ROLE_EDGES, Role

LEADER, FOLLOWER = '/master/after', '/slave/after'


def reply(rid=1, origin='/proxy', oldest_pending=0):
    """A stand-in for aft_msgs/Reply (the LFR After stamps its epoch on it)."""
    return types.SimpleNamespace(origin=origin, id=rid, oldest_pending=oldest_pending, epoch=0)


def join(site='slave', after=FOLLOWER, incarnation='i1', last_seq=0):
    return types.SimpleNamespace(site=site, after=after, incarnation=incarnation, last_seq=last_seq)


def conf(epoch, primary, backup='', reason='test'):
    return types.SimpleNamespace(epoch=epoch, primary=primary, backup=backup, reason=reason)


def leader(state=State.LEADING, **kwargs):
    role = {State.LEADING: Role.PRIMARY, State.ALONE: Role.ALONE}[state]
    return LfrAfter(LEADER, role, site='master', peer='slave', **kwargs)


def follower(joined=True, **kwargs):
    return LfrAfter(FOLLOWER, Role.BACKUP, joined=joined, site='slave', peer='master', **kwargs)


# -- replies ------------------------------------------------------------------------------
def test_a_leaders_reply_is_released_only_once_the_follower_computed_it():
    core = leader()
    r = reply(1)
    assert core.on_reply(r, now=0.0) == Out.HOLD and core.held
    assert core.on_ack('/proxy', 2, now=0.1, sender=FOLLOWER) == (Ack.EARLY, None)   # another request
    assert core.held
    assert core.on_ack('/proxy', 1, now=0.2, sender=FOLLOWER) == (Ack.RELEASE, r)
    assert not core.held


def test_an_ack_before_the_leaders_own_result_releases_the_reply_at_once():
    core = leader()
    assert core.on_ack('/proxy', 1, now=0.0, sender=FOLLOWER) == (Ack.EARLY, None)
    assert core.on_reply(reply(1), now=0.1) == Out.RELEASE_NOTIFY
    assert not core.held and not core.acked


def test_a_duplicate_ack_releases_nothing_twice():
    core = leader()
    core.on_reply(reply(1), now=0.0)
    assert core.on_ack('/proxy', 1, now=0.1, sender=FOLLOWER)[0] == Ack.RELEASE
    answer, released = core.on_ack('/proxy', 1, now=0.2, sender=FOLLOWER)
    assert released is None and answer != Ack.RELEASE


def test_alone_a_leader_replies_at_once_and_a_follower_stores_and_acknowledges():
    assert leader(State.ALONE).on_reply(reply(1), now=0.0) == Out.RELEASE
    core = follower()
    assert core.on_reply(reply(1), now=0.0) == Out.STORE and core.computed == 1
    assert core.on_reply(reply(2), now=0.0, refused=True) == Out.DROP and core.computed == 1


def test_released_replies_carry_the_leaders_epoch():
    core = leader()
    core.epoch = 4
    r = reply(1)
    core.on_reply(r, now=0.0)
    assert r.epoch == 4
    assert [x.epoch for x in core.go_alone(epoch=6)] == [6]


def test_a_refusal_is_sent_to_the_follower_and_held_until_it_acknowledges():
    core = leader()
    r = reply(1)
    assert core.on_reply(r, now=0.0, refused=True) == Out.HOLD_REFUSAL
    assert core.held
    assert core.on_ack('/proxy', 1, now=0.1, sender=FOLLOWER) == (Ack.RELEASE, r)


def test_a_follower_stores_the_leaders_refusals_only_while_it_follows():
    assert follower().on_peer_refusal(reply(1))
    assert not follower(joined=False).on_peer_refusal(reply(1))
    assert not leader().on_peer_refusal(reply(1))


# -- losing the follower ----------------------------------------------------------------------
def test_ack_timeout_means_exclusion_and_the_held_replies_go_out_in_order_only_then():
    core = leader(ack_timeout=1.0)
    for rid, t in ((3, 0.0), (1, 0.2), (2, 0.4)):
        core.on_reply(reply(rid), now=t)
    assert not core.overdue(0.9)
    assert core.overdue(1.1)          # the adapter asks the witness to exclude the follower
    assert core.held and core.state == State.LEADING   # nothing released before the witness answered
    assert [r.id for r in core.go_alone(epoch=5)] == [3, 1, 2]
    assert core.state == State.ALONE and core.role == Role.ALONE and core.epoch == 5
    assert not core.held and core.follower is None and not core.overdue(10.0)


def test_a_deposed_leader_withholds_its_replies_and_answers_nothing_more():
    core = leader()
    core.on_reply(reply(1), now=0.0)
    assert core.depose('slave is the primary of epoch 3') == 1
    assert core.state == State.DEPOSED and core.role == Role.PRIMARY
    assert core.on_reply(reply(2), now=0.1) == Out.DROP
    assert core.on_ack('/proxy', 1, now=0.2, sender=FOLLOWER) == (Ack.IGNORED, None)
    assert not core.overdue(100.0)
    assert core.on_join(join()) == JoinDecision.IGNORE


def test_a_configuration_naming_another_primary_deposes_the_leader():
    core = leader()
    assert core.on_configuration(conf(2, 'master', 'slave')) == ConfChange.NOTHING and core.epoch == 2
    assert core.on_configuration(conf(3, 'slave')) == ConfChange.DEPOSED
    assert core.on_configuration(conf(1, 'slave')) == ConfChange.NOTHING   # older: changes nothing


def test_an_excluded_follower_joins_again_and_cannot_take_over():
    core = follower()
    assert core.on_configuration(conf(3, 'master')) == ConfChange.EXCLUDED
    assert core.state == State.JOINING and core.join_step(0.0) == JoinStep.JOIN
    with pytest.raises(RoleError, match='never joined'):
        core.set_role(Role.ALONE, epoch=4)


# -- joins ---------------------------------------------------------------------------------
def test_join_by_one_state_transfer_then_admission():
    lead, foll = leader(State.ALONE, join_seq=100), follower(joined=False)
    assert foll.join_step(now=0.0) == JoinStep.JOIN
    j = join(last_seq=foll.accepted)
    assert lead.on_join(j) == JoinDecision.TRANSFER
    lead.remember(reply(7))
    transfer = lead.start_transfer('slave', now=1.0)
    assert transfer.seq == 101 and [r.id for r in transfer.cache] == [7]
    assert lead.on_reply(reply(8), now=1.1) == Out.RELEASE   # not admitted yet: nothing held
    assert foll.check_transfer(transfer.seq, LEADER, epoch=0, full=True) is None
    foll.transferred(transfer.seq, epoch=0, cache=transfer.cache, now=2.0)
    assert foll.state == State.FOLLOWING and foll.accepted == 101 and (7, ) == tuple(r.id for r in foll.recent.replies())
    assert foll.check_transfer(transfer.seq, LEADER, epoch=0, full=True) == '%s is not joining' % FOLLOWER
    assert lead.on_ack('', 101, now=1.5, sender=FOLLOWER) == (Ack.TRANSFER, None)
    assert transfer.acknowledged_s == pytest.approx(0.5)
    assert lead.on_ack('', 101, now=1.6, sender=FOLLOWER) == (Ack.IGNORED, None)   # duplicate
    assert lead.end_transfer() is transfer
    lead.admitted(j.after, j.incarnation, transfer.seq, epoch=2)
    assert lead.state == State.LEADING and lead.role == Role.PRIMARY and lead.epoch == 2
    assert lead.on_reply(reply(9), now=3.0) == Out.HOLD


def test_a_late_join_is_ignored_by_last_seq_and_a_join_after_the_transfer_means_a_restart():
    lead = leader(State.ALONE, join_seq=100)
    transfer = lead.start_transfer('slave', now=0.0)
    lead.end_transfer()
    lead.admitted(FOLLOWER, 'i1', transfer.seq, epoch=2)
    assert lead.on_join(join(last_seq=0)) == JoinDecision.IGNORE             # sent before it accepted
    assert lead.on_join(join(last_seq=transfer.seq)) == JoinDecision.EXCLUDE   # it lost the state
    assert lead.on_join(join(incarnation='i2', last_seq=0)) == JoinDecision.EXCLUDE   # restarted site


@pytest.mark.parametrize('core,j', [
    (leader(State.ALONE), join(site='master')),      # our own site's Join
    (follower(), join(site='master')),               # a follower transfers nothing
    (follower(joined=False), join(site='master')),
])
def test_joins_that_are_ignored(core, j):
    assert core.on_join(j) == JoinDecision.IGNORE


def test_no_transfer_unless_leading_alone():
    assert leader().start_transfer('slave', now=0.0) is None
    assert follower().start_transfer('slave', now=0.0) is None


def test_an_ack_of_an_older_transfer_is_ignored():
    lead = leader(State.ALONE, join_seq=10)
    lead.start_transfer('slave', now=0.0)
    assert lead.on_ack('', 9, now=0.1, sender=FOLLOWER) == (Ack.IGNORED, None)
    assert lead.transfer.acknowledged_s is None


def test_a_follower_never_admitted_asks_the_witness_then_joins_again():
    core = follower(joined=False, ack_timeout=1.0, join_period=0.5)
    core.transferred(5, epoch=1, cache=[], now=10.0)
    core.on_configuration(conf(1, 'master'))      # our own epoch: nothing changes
    assert core.join_step(11.0) == JoinStep.NOTHING   # not long enough
    assert core.join_step(12.5) == JoinStep.STATUS
    assert core.not_admitted(epoch=2) and core.state == State.JOINING
    assert not core.not_admitted(epoch=2)
    core.on_configuration(conf(2, 'master', 'slave'))
    assert core.join_step(100.0) == JoinStep.JOIN


# -- stray senders ---------------------------------------------------------------------------
@pytest.mark.parametrize('seq,sender,epoch,full,problem', [
    (1, '/intruder/after', 0, True, 'does not follow /intruder/after'),
    (1, LEADER, 0, False, 'does not follow'),                  # not a state transfer
    (1, LEADER, 2, True, 'state transfer of epoch 2, older than epoch 3'),
    (1, '/masterx/after', 3, True, 'does not follow'),
])
def test_a_stray_or_stale_transfer_is_refused_and_changes_nothing(seq, sender, epoch, full, problem):
    core = follower(joined=False)
    core.epoch = 3
    assert problem in core.check_transfer(seq, sender, epoch, full)
    assert core.state == State.JOINING and core.accepted == 0 and core.epoch == 3


def test_a_forged_ack_releases_nothing_and_is_reported():
    core = leader()
    core.on_reply(reply(1), now=0.0)
    assert core.on_ack('/proxy', 1, now=0.1, sender='/intruder/after') == (Ack.STRAY, None)
    assert core.held and not core.acked
    transfer_leader = leader(State.ALONE, join_seq=1)
    transfer_leader.start_transfer('slave', now=0.0)
    assert transfer_leader.on_ack('', 2, now=0.1, sender='/intruder/x') == (Ack.STRAY, None)
    assert transfer_leader.transfer.acknowledged_s is None


def test_without_a_peer_no_sender_is_checked():
    core = LfrAfter(LEADER, Role.PRIMARY)
    core.on_reply(reply(1), now=0.0)
    assert core.on_ack('/proxy', 1, now=0.1, sender='/anyone')[0] == Ack.RELEASE


# -- role changes ---------------------------------------------------------------------------
@pytest.mark.parametrize('core,role', [
    (follower(), Role.PRIMARY),
    (leader(), Role.BACKUP),
    (leader(State.ALONE), Role.BACKUP),
])
def test_illegal_role_changes_are_refused_with_a_clear_error_and_change_nothing(core, role):
    before = (core.state, core.role, core.epoch)
    with pytest.raises(RoleError, match='role change %s -> %s is not allowed' % (core.role.name, role.name)):
        core.set_role(role, epoch=9)
    assert (core.state, core.role, core.epoch) == before


def test_a_joining_follower_takes_over_only_as_the_witnesses_first_primary():
    core = follower(joined=False)
    with pytest.raises(RoleError, match='%s holds no state: it never joined' % FOLLOWER):
        core.set_role(Role.ALONE, epoch=1)
    assert core.set_role(Role.ALONE, epoch=1, initial=True) == ([], None)
    assert core.state == State.ALONE and core.epoch == 1


def test_recovery_promotes_a_follower_and_makes_a_leader_alone():
    core = follower()
    assert core.set_role(Role.ALONE, epoch=3) == ([], None) and core.role == Role.ALONE
    lead = leader()
    lead.on_reply(reply(1), now=0.0)
    released, kept = lead.set_role(Role.ALONE, epoch=3)
    assert [r.id for r in released] == [1] and kept is None and lead.state == State.ALONE


def test_a_late_order_of_an_older_epoch_keeps_the_leader_leading():
    lead = leader()
    lead.epoch = 5
    lead.on_reply(reply(1), now=0.0)
    assert lead.set_role(Role.ALONE, epoch=4) == ([], 'role PRIMARY kept: epoch 5 is newer than 4')
    assert lead.state == State.LEADING and lead.held


def test_only_a_join_makes_a_leader_lead():
    lead = leader(State.ALONE)
    assert lead.set_role(Role.PRIMARY) == ([], None)
    assert lead.state == State.ALONE
    with pytest.raises(RoleError, match='JOINING -> LEADING is not allowed'):
        follower(joined=False).admitted(FOLLOWER, 'i1', 1, epoch=1)


def test_every_edge_has_a_reason_and_agrees_with_the_role_edges():
    for (old, new), why in EDGES.items():
        assert why
        if new != State.DEPOSED and ROLE_OF[old] != ROLE_OF[new]:
            assert (ROLE_OF[old], ROLE_OF[new]) in ROLE_EDGES


@pytest.mark.parametrize('role,order,epoch,expected_role,message', [
    (Role.PRIMARY, Role.ALONE, 3, Role.ALONE, None),
    (Role.BACKUP, Role.ALONE, 3, Role.ALONE, None),
    (Role.ALONE, Role.PRIMARY, 3, Role.PRIMARY, None),
])
def test_the_befores_role_changes(role, order, epoch, expected_role, message):
    forwarder = LfrForwarder(role)
    assert forwarder.set_role(order, epoch) == message
    assert forwarder.role == expected_role and forwarder.epoch == epoch


def test_the_before_refuses_illegal_changes_and_keeps_primary_on_a_late_order():
    forwarder = LfrForwarder(Role.PRIMARY)
    with pytest.raises(RoleError, match='PRIMARY -> BACKUP'):
        forwarder.set_role(Role.BACKUP)
    forwarder.set_role(Role.PRIMARY, 5)
    assert forwarder.set_role(Role.ALONE, 4) == 'role PRIMARY kept: epoch 5 is newer than 4'
    assert forwarder.forwards()


def test_a_promoted_before_refuses_forwarded_requests():
    forwarder = LfrForwarder(Role.BACKUP)
    assert forwarder.on_forwarded() and forwarder.passed == 1
    forwarder.set_role(Role.ALONE, 2)
    assert not forwarder.on_forwarded() and (forwarder.passed, forwarder.refused) == (1, 1)


# -- random orders ----------------------------------------------------------------------------
@pytest.mark.parametrize('seed', range(40))
def test_in_any_order_of_results_and_acks_every_reply_goes_out_exactly_once_after_both_computed(seed):
    """The leader's results and the follower's acks (some duplicated, some forged) arrive in a random
    order; at a random point the follower may be excluded. Every reply is released exactly once, and
    before the exclusion only once both replicas computed it."""
    rng = random.Random(seed)
    core = leader()
    n = rng.randint(1, 12)
    events = [('reply', i) for i in range(n)] + [('ack', i) for i in range(n)]
    events += [('ack', rng.randrange(n)) for _ in range(rng.randint(0, 3))]          # duplicates
    events += [('forged', rng.randrange(n)) for _ in range(rng.randint(0, 3))]
    rng.shuffle(events)
    exclude_at = rng.randint(0, len(events)) if rng.random() < 0.3 else None
    computed, acked, released = set(), set(), []
    for t, (kind, i) in enumerate(events):
        if t == exclude_at:
            released += [r.id for r in core.go_alone(epoch=2)]
        excluded = exclude_at is not None and t >= exclude_at
        if kind == 'reply':
            computed.add(i)
            out = core.on_reply(reply(i), now=t)
            if out in (Out.RELEASE, Out.RELEASE_NOTIFY):
                released.append(i)
        else:
            answer, r = core.on_ack('/proxy', i, now=t, sender=FOLLOWER if kind == 'ack' else '/intruder/after')
            if kind == 'ack':
                acked.add(i)
            if r is not None:
                released.append(r.id)
        if not excluded:
            assert set(released) <= computed & acked, 'seed %d: released before both computed' % seed
    assert sorted(released) == list(range(n)), 'seed %d: %s' % (seed, released)
    assert not core.held, 'seed %d' % seed
