"""Protocol logic: duplicate detection, one request at a time, backup and promotion. No ROS."""
import random

import pytest

from aft_ftm.errors import RoleError
from aft_ftm.protocol import DuplicateCache, Forward, ProtocolCore, Refuse, Role, check_role_change
from fakes import reply, request


def kinds(actions):
    return [(type(a).__name__, (a.request if isinstance(a, Forward) else a.reply).id) for a in actions]


def test_new_request_is_forwarded_and_its_result_answered_and_cached():
    core = ProtocolCore(Role.PRIMARY)
    assert kinds(core.on_request(request(rid=1), 0)) == [('Forward', 1)]
    actions = core.on_result(reply(rid=1, value='r1'), 0)
    assert kinds(actions) == [('Answer', 1)] and actions[0].reply.value == 'r1'
    assert core.stats.executed == 1


def test_duplicate_after_execution_is_answered_from_cache_without_executing_again():
    core = ProtocolCore(Role.PRIMARY)
    core.on_request(request(rid=1), 0)
    core.on_result(reply(rid=1, value='r1'), 0)
    actions = core.on_request(request(rid=1), 1)
    assert kinds(actions) == [('Answer', 1)]
    assert actions[0].cached and actions[0].reply.value == 'r1'
    assert core.stats.executed == 1 and core.stats.cached_answers == 1


def test_duplicate_of_executing_or_queued_request_is_joined_not_executed_twice():
    core = ProtocolCore(Role.PRIMARY)
    core.on_request(request(rid=1), 0)
    core.on_request(request(rid=2), 0)
    assert core.on_request(request(rid=1), 0) == []     # executing
    assert core.on_request(request(rid=2), 0) == []     # queued
    assert kinds(core.on_result(reply(rid=1), 0)) == [('Answer', 1), ('Forward', 2)]
    assert kinds(core.on_result(reply(rid=2), 0)) == [('Answer', 2)]
    assert core.stats.executed == 2 and core.stats.joined == 2


def test_requests_execute_one_at_a_time_in_arrival_order():
    core = ProtocolCore(Role.PRIMARY)
    forwarded = []
    for rid in (5, 3, 9):
        forwarded += kinds(core.on_request(request(rid=rid), 0))
    assert forwarded == [('Forward', 5)]
    assert kinds(core.on_result(reply(rid=5), 0)) == [('Answer', 5), ('Forward', 3)]
    assert kinds(core.on_result(reply(rid=3), 0)) == [('Answer', 3), ('Forward', 9)]


def test_same_id_from_two_origins_are_two_requests():
    core = ProtocolCore(Role.PRIMARY)
    core.on_request(request(origin='/a', rid=1), 0)
    core.on_result(reply(origin='/a', rid=1, value='a'), 0)
    assert kinds(core.on_request(request(origin='/b', rid=1), 0)) == [('Forward', 1)]


def test_stray_result_is_counted_and_changes_nothing():
    core = ProtocolCore(Role.PRIMARY)
    core.on_request(request(rid=1), 0)
    assert core.on_result(reply(rid=7), 0) == []
    assert core.stats.stray_results == 1
    assert core.current.id == 1 and core.cache.lookup(('/proxy', 7, 0)) is None


def test_watermark_forgets_replies_the_proxy_can_no_longer_ask_for():
    core = ProtocolCore(Role.PRIMARY)
    for rid in (1, 2, 3):
        core.on_request(request(rid=rid), 0)
        core.on_result(reply(rid=rid), 0)
    core.on_request(request(rid=4, oldest_pending=3), 0)
    assert core.cache.lookup(('/proxy', 1, 0)) is None and core.cache.lookup(('/proxy', 2, 0)) is None
    assert core.cache.lookup(('/proxy', 3, 0)) is not None


def test_backup_executes_nothing_and_stores_checkpointed_replies():
    core = ProtocolCore(Role.BACKUP)
    assert core.on_request(request(rid=1), 0) == []
    core.on_stored(reply(rid=1, value='from primary'), seq=1)
    assert core.last_stored_seq == 1 and core.stats.executed == 0


def test_promoted_backup_answers_executed_requests_from_cache_and_executes_the_rest():
    core = ProtocolCore(Role.BACKUP)
    core.on_stored(reply(rid=1, value='done by primary'), seq=1)
    core.on_stored(reply(rid=2, value='done by primary'), seq=2)
    assert not core.can_take_over(3) and core.can_take_over(2)
    assert core.set_role(Role.ALONE, 0) == []
    # The proxy re-sends its two pending requests: 2 was executed by the old primary, 3 was not.
    answer = core.on_request(request(rid=2), 0)
    assert kinds(answer) == [('Answer', 2)] and answer[0].reply.value == 'done by primary'
    assert kinds(core.on_request(request(rid=3), 0)) == [('Forward', 3)]


def test_a_backup_answers_no_client_even_from_its_cache():
    """One replica answers the clients: a backup queues a request whose reply it stored, and answers it
    from the cache only once promoted."""
    core = ProtocolCore(Role.BACKUP)
    core.on_stored(reply(rid=1, value='by the primary'), seq=1)
    assert core.on_request(request(rid=1), 0) == [] and core.stats.cached_answers == 0
    answers = core.set_role(Role.ALONE, 0)
    assert kinds(answers) == [('Answer', 1)] and answers[0].cached and core.stats.executed == 0


def test_a_backup_taking_over_drops_a_queued_request_its_primary_dealt_with_but_whose_reply_was_lost():
    """Found by the simulation (loss within a site, seed 90 of loss,local): the message storing 6's reply
    was lost, 7's arrived. The Proxy sent 6 before 7 to both replicas, so the primary executed 6 first:
    taking over, the backup must not execute it again. A re-send of 6 (the Proxy still waiting) executes."""
    core = ProtocolCore(Role.BACKUP)
    core.on_request(request(rid=6, oldest_pending=6), 0)
    core.on_request(request(rid=7, oldest_pending=6), 0)
    core.on_stored(reply(rid=7, oldest_pending=6), seq=2, sender='/master/after')   # seq 1 (reply 6) lost
    assert kinds(core.set_role(Role.ALONE, 0)) == [('Answer', 7)]
    assert core.stats.executed == 0 and core.stats.dropped == 1
    assert kinds(core.on_request(request(rid=6, oldest_pending=6), 0)) == [('Forward', 6)]


def test_requests_queued_while_backup_are_deduplicated_at_promotion():
    core = ProtocolCore(Role.BACKUP)
    core.on_request(request(rid=1), 0)
    core.on_request(request(rid=2), 0)
    core.on_stored(reply(rid=1, value='old primary'), seq=1)
    assert kinds(core.set_role(Role.ALONE, 0)) == [('Answer', 1), ('Forward', 2)]


def test_overdue_request_is_reported_after_timeout_only():
    core = ProtocolCore(Role.PRIMARY)
    core.on_request(request(rid=1), now=10.0)
    assert core.overdue(10.5, timeout=1.0) is None
    assert core.overdue(11.5, timeout=1.0).id == 1


@pytest.mark.parametrize('current,new,allowed', [
    (Role.BACKUP, Role.ALONE, True),
    (Role.PRIMARY, Role.ALONE, True),
    (Role.ALONE, Role.ALONE, True),
    (Role.ALONE, Role.PRIMARY, True),      # a backup joined
    (Role.ALONE, Role.BACKUP, False),
    (Role.PRIMARY, Role.BACKUP, False),
    (Role.BACKUP, Role.PRIMARY, False),
])
def test_role_edges(current, new, allowed):
    if allowed:
        check_role_change(current, new)
    else:
        with pytest.raises(RoleError, match='%s -> %s' % (current.name, new.name)):
            check_role_change(current, new)


def test_refused_role_change_leaves_the_protocol_unchanged():
    core = ProtocolCore(Role.ALONE)
    with pytest.raises(RoleError):
        core.set_role(Role.BACKUP, 0)
    assert core.role == Role.ALONE


def test_a_cache_at_its_capacity_is_full_and_forgets_no_reply():
    cache = DuplicateCache(capacity=2)
    cache.store(reply(rid=1))
    assert not cache.full()
    cache.store(reply(rid=2))
    assert cache.full() and '2 replies (bound 2)' in cache.why_full()
    cache.store(reply(rid=3))   # one in flight when it filled: kept too
    assert cache.evicted == 0 and len(cache) == 3 and cache.lookup(('/proxy', 1, 0)) is not None
    cache.forget_below('/proxy', 3)   # its Proxy confirmed them: room again
    assert not cache.full() and len(cache) == 1


def test_a_flood_of_origins_never_makes_a_captured_request_run_twice():
    """Review of SEC (session 33): past 100 000 entries the Protocol evicted its oldest reply, one still
    at or above its origin's watermark. An insider sending from many origins (each keeping its
    oldest_pending) evicted a victim's last reply in 1.7 s; the captured request then ran again,
    with no alarm. A cache at its bound now refuses new requests instead."""
    core = ProtocolCore(Role.ALONE, cache_capacity=50)
    victim = request(rid=7, origin='/victim')
    assert [type(a).__name__ for a in core.on_request(victim, 0.0)] == ['Forward']
    core.on_result(reply(rid=7, origin='/victim'), 0.0)
    refused = 0
    for i in range(200):   # the insider's flood, from origins of its own
        actions = core.on_request(request(rid=1, origin='/insider%d' % i), 0.0)
        for a in actions:
            if isinstance(a, Forward):
                core.on_result(reply(rid=1, origin='/insider%d' % i), 0.0)
            refused += isinstance(a, Refuse)
    assert refused == 200 - 49 and core.cache.full()
    replay = core.on_request(request(rid=7, origin='/victim'), 0.0)
    assert [type(a).__name__ for a in replay] == ['Answer'], replay   # from the cache: never executed again


def test_a_repeated_execution_is_not_taken_for_a_resend():
    """TR numbers the executions of one request: a nested Protocol executes each of them."""
    core = ProtocolCore(Role.ALONE)
    first, again = request(rid=1), request(rid=1)
    again.attempt = 1
    assert kinds(core.on_request(first, 0)) == [('Forward', 1)]
    core.on_result(reply(rid=1), 0)
    assert kinds(core.on_request(again, 0)) == [('Forward', 1)]
    assert core.stats.executed == 2


def test_stored_checkpoint_numbers_are_counted_per_sending_after():
    """An adaptation replaced the primary's After: take-over waits for the new one's numbers."""
    core = ProtocolCore(Role.BACKUP)
    core.on_stored(reply(rid=1), seq=5000, sender='/master/after')
    core.on_stored(reply(rid=2), seq=5001, sender='/master/after')
    core.on_stored(reply(rid=3), seq=40, sender='/master/after_lfr')
    assert core.last_stored_seq == 40
    assert core.can_take_over(40) and not core.can_take_over(41)


def test_a_suspended_protocol_promoted_meanwhile_executes_nothing_until_resumed():
    """Found by the simulation (loss,local, group commit, seed 39848): the After suspended its Protocol, a
    quiescent backup, to capture a join's state transfer; Recovery promoted the Protocol meanwhile, which
    executed its queue under the capture: the state held a request whose reply the transfer lacked."""
    core = ProtocolCore(Role.BACKUP, max_batch=4)
    core.on_request(request(rid=1), 0)
    core.on_request(request(rid=2), 0)
    core.hold()
    assert core.set_role(Role.ALONE, 0) == [] and core.current is None
    assert core.on_request(request(rid=3), 0) == []
    assert kinds(core.release(0)) == [('Forward', 1), ('Forward', 2), ('Forward', 3)]
    assert core.release(0) == []   # resumed twice (a rollback resumes every node): nothing more


def test_stored_checkpoints_are_counted_without_a_gap_and_a_state_transfer_closes_one():
    """Found by the simulation (loss,local, seed 13403): the message storing checkpoint 2's reply was lost
    and 3's came; comparing the highest number, the backup took over and executed request 2 again."""
    core = ProtocolCore(Role.BACKUP)
    core.on_stored(reply(rid=1), seq=1, sender='/master/after', first_seq=1)
    core.on_stored(reply(rid=3, oldest_pending=1), seq=3, sender='/master/after', first_seq=1)   # 2 lost
    assert core.stored_gap == 2 and core.last_stored_seq == 1
    assert not core.can_take_over(3)
    # the After, promoted, sends every reply it holds
    core.on_state_transfer([reply(rid=1), reply(rid=2, oldest_pending=1), reply(rid=3, oldest_pending=1)], 3,
                           '/master/after')
    assert core.stored_gap is None and core.can_take_over(3)
    core.on_request(request(rid=2, oldest_pending=1), 0)
    answers = core.set_role(Role.ALONE, 0)
    assert kinds(answers) == [('Answer', 2)] and core.stats.executed == 0


def test_checkpoints_stored_out_of_order_close_their_gap_and_a_sender_heard_late_has_one():
    core = ProtocolCore(Role.BACKUP)
    for seq in (1, 3, 4, 2):
        core.on_stored(reply(rid=seq), seq=seq, sender='/master/after', first_seq=1)
    assert core.stored_gap is None and core.can_take_over(4)
    # a replacement After numbered from 10, whose first checkpoint's message was lost
    core.on_stored(reply(rid=12), seq=11, sender='/master/after_2', first_seq=10)
    assert core.stored_gap == 10 and not core.can_take_over(11)
    # without first_seq (an older sender), the first number heard counts as its first
    core.on_stored(reply(rid=13), seq=20, sender='/master/after_3')
    assert core.stored_gap is None and core.can_take_over(20)
    # a group commit's replies come one by one with one number
    for rid in (14, 15, 16):
        core.on_stored(reply(rid=rid), seq=21, sender='/master/after_3')
    assert core.last_stored_seq == 21


def test_an_after_started_again_under_its_name_numbers_anew_and_leaves_no_false_gap():
    core = ProtocolCore(Role.BACKUP)
    for seq in (1, 2):
        core.on_stored(reply(rid=seq), seq=seq, sender='/master/after', first_seq=1)
    core.on_stored(reply(rid=3), seq=900, sender='/master/after', first_seq=900)   # a rollback restarted it
    assert core.stored_gap is None and core.can_take_over(900)
    core.on_stored(reply(rid=4), seq=902, sender='/master/after', first_seq=900)   # 901 lost
    assert core.stored_gap == 901


def test_numbers_kept_beyond_a_gap_are_bounded_and_the_gap_stays():
    from aft_ftm.protocol import MAX_AHEAD
    core = ProtocolCore(Role.BACKUP)
    core.on_stored(reply(rid=1), seq=1, sender='/a', first_seq=1)
    for seq in range(3, 3 + MAX_AHEAD + 50):
        core.on_stored(reply(rid=seq), seq=seq, sender='/a', first_seq=1)
    assert len(core._ahead) == MAX_AHEAD and core.stored_gap == 2
    core.on_stored(reply(rid=2), seq=2, sender='/a', first_seq=1)
    assert core.stored_gap == MAX_AHEAD + 3 and not core.can_take_over(MAX_AHEAD + 10)   # never too early
    core.on_state_transfer([], MAX_AHEAD + 60, '/a')
    assert core.stored_gap is None and core.can_take_over(MAX_AHEAD + 60)


def test_a_state_transfer_heard_after_the_take_over_brings_back_no_reply_its_proxy_confirmed():
    core = ProtocolCore(Role.BACKUP)
    core.on_stored(reply(rid=1), seq=1, sender='/a', first_seq=1)
    core.set_role(Role.ALONE, 0)
    core.on_request(request(rid=5, oldest_pending=5), 0)   # the Proxy has every answer below 5
    core.on_state_transfer([reply(rid=1), reply(rid=2)], 1, '/a')
    assert core.cache.lookup(('/proxy', 1, 0)) is None and core.cache.lookup(('/proxy', 2, 0)) is None


def test_a_request_queued_while_backup_and_answered_meanwhile_is_not_executed_at_promotion():
    """Found by the simulation (tests/unit/test_replication_sim.py): a backup being promoted queues the
    re-sent request 7, then stores its reply from the primary's last checkpoint (it answered a re-send
    of 7 from it then; a backup answers nothing now). The Proxy's next request says it has 7's answer:
    the stored reply is forgotten, and the queued 7 must go with it, or the promoted backup applies it
    a second time."""
    core = ProtocolCore(Role.BACKUP)
    core.on_request(request(rid=7, oldest_pending=7), 0)
    core.on_stored(reply(rid=7, oldest_pending=7), seq=1, sender='/master/after')
    assert core.on_request(request(rid=7, oldest_pending=7), 0) == []   # a backup answers nothing
    core.on_request(request(rid=8, oldest_pending=8), 0)
    assert kinds(core.set_role(Role.ALONE, 0)) == [('Forward', 8)]
    assert core.stats.executed == 1 and core.stats.dropped == 1


def test_a_copy_of_a_refused_request_is_refused_again_never_executed():
    """Found by the simulation: 'not executed' is a definite answer only if no copy of the request sent
    before the Proxy had it (a re-send) is executed later, once the reply cache has room again."""
    core = ProtocolCore(Role.ALONE, cache_bytes=64)
    core.on_request(request(rid=1, oldest_pending=1), 0)
    core.on_result(reply(rid=1), 0)
    refused = core.on_request(request(rid=2, oldest_pending=1), 0)
    assert [type(a).__name__ for a in refused] == ['Refuse'] and refused[0].reason.startswith('not executed')
    again = core.on_request(request(rid=2, oldest_pending=2), 0)     # 1 confirmed: the cache has room now
    assert [type(a).__name__ for a in again] == ['Refuse'] and again[0].reason == refused[0].reason
    assert kinds(core.on_request(request(rid=3, oldest_pending=3), 0)) == [('Forward', 3)]   # 2's refusal had
    assert core.stats.executed == 2 and not core.refused


def test_a_refusal_replicated_through_after_is_kept_and_answers_every_later_copy():
    """A replica's refusal comes back from After once its backup holds it: the Protocol keeps it in the
    reply cache (so does the backup, from the checkpoint), and a copy answered later gets it again."""
    backup = ProtocolCore(Role.BACKUP)
    refusal = reply(rid=2, value='not executed')
    backup.on_stored(refusal, 1, '/master/after')
    backup.set_role(Role.ALONE, 0)
    answers = backup.on_request(request(rid=2, oldest_pending=2), 0)   # the cache has room: no refusal of its own
    assert kinds(answers) == [('Answer', 2)] and answers[0].reply.value == 'not executed'
    assert backup.stats.executed == 0
    primary = ProtocolCore(Role.PRIMARY)
    answered = primary.on_refusal(reply(rid=5), 0)
    assert kinds(answered) == [('Answer', 5)] and primary.cache.lookup(('/proxy', 5, 0)) is not None


def test_an_inner_mechanisms_refusal_of_the_executing_request_is_its_result():
    core = ProtocolCore(Role.ALONE)
    core.on_request(request(rid=1), 0)
    core.on_request(request(rid=2), 0)
    actions = core.on_refusal(reply(rid=1), 0)
    assert kinds(actions) == [('Answer', 1), ('Forward', 2)] and core.current.id == 2


def test_a_backup_with_a_full_cache_queues_and_refuses_only_once_promoted():
    """A backup cannot say "not executed" (its primary may run the request): it queues the request. Once
    promoted, a request is refused if the cache is still full, and executed once it has room."""
    core = ProtocolCore(Role.BACKUP, cache_bytes=64)
    core.on_stored(reply(rid=1, oldest_pending=1), seq=1, sender='/master/after')
    assert core.cache.full()
    assert core.on_request(request(rid=2, oldest_pending=1), 0) == [] and core.stats.refused == 0
    actions = core.set_role(Role.ALONE, 0)
    assert [type(a).__name__ for a in actions] == ['Refuse'] and actions[0].request.id == 2
    assert core.stats.executed == 0
    assert kinds(core.on_request(request(rid=3, oldest_pending=3), 0)) == [('Forward', 3)]   # 1, 2 confirmed


@pytest.mark.parametrize('seed', range(60))
def test_a_backup_listening_from_set_up_keeps_a_bounded_queue_and_takes_over_exactly_once(seed):
    """The backup's Protocol hears every client request from set-up (so that a failover needs no new
    subscription). A Proxy with up to `window` calls pending, a primary that releases a reply once its
    checkpoint is acknowledged, FIFO links delivered in a random order, and at a random point the
    primary crashes (checkpoints in flight lost) and the backup is promoted. Then: the backup's queue
    never holds more than the Proxy's window, it never answers, refuses nor executes as a backup, every answered
    request is in the final state exactly once, and a refused one is not in it."""
    rng = random.Random(seed)
    total, window = rng.randint(1, 30), rng.randint(1, 4)
    primary = ProtocolCore(Role.PRIMARY)
    backup = ProtocolCore(Role.BACKUP, cache_bytes=rng.choice([0, 64 * rng.randint(1, 4)]))
    links = {name: [] for name in ('to_primary', 'to_backup', 'checkpoints', 'acks', 'replies')}
    state_primary, state_backup, held = [], [], {}
    pending, answered, refused, next_id, crashed = set(), {}, set(), 0, False
    crash_at = rng.randint(0, 6 * total) if rng.random() < 0.8 else None

    def send(rid):
        oldest = min(pending) if pending else next_id
        for link in (['to_backup'] if crashed else ['to_primary', 'to_backup']):
            links[link].append(request(rid=rid, oldest_pending=oldest))

    def backup_acts(actions):
        for a in actions:
            if isinstance(a, Forward):
                assert crashed, 'seed %d: a backup executed %d' % (seed, a.request.id)
                state_backup.append(a.request.id)
                backup_acts(backup.on_result(reply(rid=a.request.id, oldest_pending=a.request.oldest_pending), 0))
            elif type(a).__name__ == 'Refuse':
                assert crashed, 'seed %d: a backup refused %d' % (seed, a.request.id)
                links['replies'].append(('refused', a.request.id))
            else:
                assert crashed, 'seed %d: a backup answered %d' % (seed, a.reply.id)
                links['replies'].append(('ok', a.reply.id))

    def primary_acts(actions):
        for a in actions:
            if isinstance(a, Forward):
                state_primary.append(a.request.id)
                seq = len(state_primary)
                held[seq] = reply(rid=a.request.id, oldest_pending=a.request.oldest_pending)
                links['checkpoints'].append((seq, held[seq], list(state_primary)))
            else:
                links['replies'].append(('ok', a.reply.id))

    for step in range(100 * total + 100):
        if step == crash_at:
            crashed = True
            for name in ('to_primary', 'checkpoints', 'acks'):
                links[name] = []
            backup_acts(backup.set_role(Role.ALONE, 0))
            for rid in sorted(pending):   # the Proxy's re-send
                send(rid)
        if len(answered) == total:
            break
        choices = [name for name, link in links.items() if link]
        if next_id < total and len(pending) < window:
            choices.append('call')
        if not choices:   # only re-sends are left
            assert pending, 'seed %d: nothing left to do' % seed
            for rid in sorted(pending):
                send(rid)
            continue
        choice = rng.choice(choices)
        if choice == 'call':
            pending.add(next_id)
            send(next_id)
            next_id += 1
            continue
        message = links[choice].pop(0)
        if choice == 'to_primary':
            primary_acts(primary.on_request(message, 0))
        elif choice == 'to_backup':
            backup_acts(backup.on_request(message, 0))
            assert len(backup.queue) <= window, 'seed %d: backup queue %d > window %d' % (
                seed, len(backup.queue), window)
        elif choice == 'checkpoints':
            seq, stored, state = message
            backup.on_stored(stored, seq, '/master/after')
            state_backup[:] = state
            links['acks'].append(seq)
        elif choice == 'acks':
            primary_acts(primary.on_result(held.pop(message), 0))
        else:
            outcome, rid = message
            if rid in pending:
                pending.discard(rid)
                answered[rid] = outcome
                if outcome == 'refused':
                    refused.add(rid)
    assert len(answered) == total, 'seed %d: %d of %d answered' % (seed, len(answered), total)
    final = state_backup if crashed else state_primary
    assert len(final) == len(set(final)), 'seed %d: executed twice: %s' % (seed, final)
    assert set(final) == set(answered) - refused, 'seed %d: state %s, answered %s' % (seed, final, answered)


@pytest.mark.parametrize('seed', range(40))
def test_a_site_that_joined_by_state_transfer_never_executes_an_answered_request_again(seed):
    """Replay protection across a re-join (issue 16): a request answered before a state transfer,
    re-sent or replayed whole (its signed oldest_pending unchanged) to the site that joined and then
    took over, is answered from the cache or dropped, never executed, for every origin, including
    one whose Proxy has since moved past all its requests (its replies pruned). The transfer carries
    the After's recent replies (pbr_nodes/lfr: forget below each reply's oldest_pending, then store)."""
    rng = random.Random(seed)
    primary = ProtocolCore(Role.ALONE)
    recent = DuplicateCache()
    answered = []
    proxies = {'/p%d' % i: {'next': 1, 'pending': []} for i in range(rng.randint(1, 5))}
    for _ in range(rng.randint(5, 80)):
        origin = rng.choice(sorted(proxies))
        proxy = proxies[origin]
        if proxy['pending'] and (len(proxy['pending']) >= 3 or rng.random() < 0.5):
            sent = proxy['pending'].pop(rng.randrange(len(proxy['pending'])))   # its answer comes back
            answered.append(sent)
            continue
        sent = request(origin=origin, rid=proxy['next'], oldest_pending=min([p.id for p in proxy['pending']] +
                                                                            [proxy['next']]))
        proxy['next'] += 1
        proxy['pending'].append(sent)
        actions = primary.on_request(sent, 0)
        for action in actions:   # executed at once: one request at a time, no queue here
            assert isinstance(action, Forward)
            done = reply(origin=origin, rid=sent.id, oldest_pending=sent.oldest_pending)
            primary.on_result(done, 0)
            recent.forget_below(done.origin, done.oldest_pending)
            recent.store(done)
    joined = ProtocolCore(Role.BACKUP)
    joined.on_state_transfer(recent.replies(), 1, '/master/after')
    joined.set_role(Role.ALONE, 0)
    for old in answered + [p for proxy in proxies.values() for p in proxy['pending']]:   # every one executed
        again = joined.on_request(request(origin=old.origin, rid=old.id, oldest_pending=old.oldest_pending), 1)
        assert not any(isinstance(a, Forward) for a in again), (seed, old.origin, old.id, kinds(again))


# -- group commit (max_batch > 1) ---------------------------------------------------------------------

def test_requests_queued_while_a_batch_executes_go_as_the_next_batch_each_numbered_left_and_size():
    core = ProtocolCore(Role.PRIMARY, max_batch=3)
    first = core.on_request(request(rid=1), 0)
    assert kinds(first) == [('Forward', 1)] and first[0].request.batch == (1, 1)
    for rid in (2, 3, 4, 5):
        assert core.on_request(request(rid=rid), 0) == []       # a batch executes: they queue
    # The batch's result releases the next batch, at most max_batch, in arrival order.
    actions = core.on_result(reply(rid=1), 0)
    assert kinds(actions) == [('Answer', 1), ('Forward', 2), ('Forward', 3), ('Forward', 4)]
    assert [a.request.batch for a in actions[1:]] == [(3, 3), (2, 3), (1, 3)]
    # Nothing more is forwarded until every result of the batch came back, whatever their order.
    assert kinds(core.on_result(reply(rid=3), 0)) == [('Answer', 3)]
    assert kinds(core.on_result(reply(rid=2), 0)) == [('Answer', 2)]
    actions = core.on_result(reply(rid=4), 0)
    assert kinds(actions) == [('Answer', 4), ('Forward', 5)] and actions[1].request.batch == (1, 1)
    assert core.stats.executed == 5 and core.batches == 3


def test_a_copy_of_a_request_of_the_executing_batch_is_joined_and_a_stray_result_changes_nothing():
    core = ProtocolCore(Role.PRIMARY, max_batch=4)
    core.on_request(request(rid=1), 0)
    core.on_request(request(rid=2), 0)
    core.on_request(request(rid=3), 0)
    core.on_result(reply(rid=1), 0)                      # 2 and 3 execute as one batch
    assert core.on_request(request(rid=3), 1) == [] and core.stats.joined == 1
    assert core.on_result(reply(rid=9), 1) == [] and core.stats.stray_results == 1
    assert core.current.id == 2 and core.overdue(61, 30).id == 2 and core.overdue(60, 30) is None   # 2 executing


def test_one_at_a_time_requests_carry_no_batch_number():
    core = ProtocolCore(Role.PRIMARY)
    actions = core.on_request(request(rid=1), 0)
    assert not hasattr(actions[0].request, 'batch')      # aft_msgs/Request.batch stays [0, 0]


def test_max_batch_below_1_is_refused():
    with pytest.raises(ValueError):
        ProtocolCore(Role.PRIMARY, max_batch=0)


def test_a_batch_is_overdue_after_the_timeout_per_request_still_executing_counted_from_its_last_result():
    # A batch's results come together, after its checkpoint: 4 requests of 2 s each within a 5 s bound
    # must not look hung at 5 s (review: a healthy primary was fail-stopped by the 30 s backstop).
    core = ProtocolCore(Role.ALONE, max_batch=4)
    core.on_request(request(rid=0), 0)
    for rid in (1, 2, 3, 4):
        core.on_request(request(rid=rid), 0)
    core.on_result(reply(rid=0), 0)                      # 1-4 execute as one batch from t=0
    assert core.overdue(19.9, 5) is None and core.overdue(20.1, 5).id == 1
    core.on_result(reply(rid=1), 12)                     # progress: 3 left, 15 s from t=12
    assert core.overdue(26.9, 5) is None and core.overdue(27.1, 5).id == 2


# -- a Proxy started again with its clock behind (ids below its predecessor's) -------------------------

def test_a_request_below_the_watermark_is_not_executed_and_the_primary_says_the_ids_to_use():
    """Review, stop 38: a Proxy started again under its name numbers its ids from the wall clock; after
    a backward step they fell below its predecessor's, and every call was dropped in silence (hung)."""
    core = ProtocolCore(Role.PRIMARY)
    for rid in (5000, 5001, 5002):
        core.on_request(request(rid=rid, oldest_pending=5000), 0)
        core.on_result(reply(rid=rid, oldest_pending=5000), 0)
    core.on_request(request(rid=5003, oldest_pending=5002), 0)        # 5002 answered, 5003 executing
    actions = core.on_request(request(rid=40, oldest_pending=40), 1)   # started again, clock behind
    assert [type(a).__name__ for a in actions] == ['Renumber'] and actions[0].first_id == 5004
    assert core.stats.executed == 4 and core.stats.stale_ids == 1
    # A re-send built as its reply came (its oldest_pending above it already): a late copy, no renumber.
    assert core.on_request(request(rid=5001, oldest_pending=5003), 1) == [] and core.stats.stale_ids == 1
    backup = ProtocolCore(Role.BACKUP)
    backup.on_request(request(rid=5003, oldest_pending=5002), 0)
    assert backup.on_request(request(rid=40, oldest_pending=40), 1) == []   # a backup tells nothing


@pytest.mark.parametrize('seed', range(60))
def test_a_proxy_started_again_with_its_clock_behind_has_each_call_executed_once_and_answered(seed):
    """Property over drawn histories: the old Proxy's calls (some answered, some in flight when it
    stopped), then a Proxy of the same name numbering from a drawn id below the old ones. Each new call
    executes once and gets its own result; no old call executes again."""
    from aft_ftm.proxy import PendingTable
    rng = random.Random(seed)
    core = ProtocolCore(Role.PRIMARY)
    executed = []

    def deliver(table, entry):
        for _ in range(10):   # bounded: a renumber, then the execution
            actions = core.on_request(request(rid=entry.id, oldest_pending=table.oldest_pending()), 0)
            for action in actions:
                kind = type(action).__name__
                if kind == 'Forward':
                    executed.append(entry.payload)
                    for answer in core.on_result(reply(rid=action.request.id, value=entry.payload,
                                                       oldest_pending=action.request.oldest_pending), 0):
                        table.close(answer.reply.id, answer.reply)
                elif kind == 'Renumber':
                    assert table.renumber(action.request.id, action.first_id) is entry
                elif kind == 'Answer':
                    table.close(action.reply.id, action.reply)
            if entry.done.is_set():
                return
        raise AssertionError('seed %d: call %r not answered' % (seed, entry.payload))

    start = rng.randint(10 ** 6, 10 ** 9)
    old = PendingTable(first_id=start)
    for n in range(rng.randint(1, 30)):
        entry = old.open('/c', ('old', n), 0)
        if rng.random() < 0.8:
            deliver(old, entry)
        elif rng.random() < 0.5:   # in flight when the Proxy stopped: executed, its answer lost
            for action in core.on_request(request(rid=entry.id, oldest_pending=old.oldest_pending()), 0):
                executed.append(entry.payload)
                core.on_result(reply(rid=entry.id, value=entry.payload, oldest_pending=old.oldest_pending()), 0)
    new = PendingTable(first_id=rng.randint(1, start - 1))
    for n in range(rng.randint(1, 20)):
        entry = new.open('/c', ('new', n), 0)
        deliver(new, entry)
        assert entry.reply.value == ('new', n), 'seed %d: another call\'s result: %r' % (seed, entry.reply.value)
    news = [p for p in executed if p[0] == 'new']
    assert len(news) == len(set(news)), 'seed %d: executed twice: %s' % (seed, news)


def test_the_replies_a_state_transfer_carries_are_never_evicted_by_count():
    """Review, stop 38: the After's cache of replies for a state transfer evicted silently at 100 000
    entries (small replies: long before its byte bound); the transfer then lacked a reply, and a re-sent
    copy executed again on the joiner once it took over. The Afters keep them with no count bound."""
    from aft_ftm.lfr import LfrAfter
    cache = LfrAfter('/master/after', Role.ALONE, cache_bytes=64 << 20).recent
    for rid in range(100001):
        cache.store(reply(origin='/p%d' % (rid % 7), rid=rid + 1))
    assert len(cache) == 100001 and cache.evicted == 0


def test_a_state_transfer_from_an_after_started_again_under_its_name_is_no_gap():
    """Review of stop 39: the Protocol was told the transfer without its sender's first number; the
    next checkpoint, carrying the new first number, reset the count below the transfer: a gap at the
    transfer itself, and no take-over without asking the After for every reply."""
    core = ProtocolCore(Role.BACKUP)
    for seq in range(1000, 1005):                       # the first incarnation of /a/after
        core.on_stored(reply(rid=seq), seq, '/a/after', first_seq=1000)
    core.on_state_transfer([reply(rid=5000)], 5000, '/a/after', first_seq=4990)   # started again, joined
    core.on_stored(reply(rid=5001), 5001, '/a/after', first_seq=4990)
    assert core.stored_gap is None and core.last_stored_seq == 5001
