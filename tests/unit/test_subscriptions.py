"""When a subscription that lacks a registered publisher is connected again (aft_ftm.subscriptions;
aft_ftm.ros.subscription_keeper's period). No ROS master."""
import os
import random

import pytest

from aft_ftm.errors import ConfigError
from aft_ftm.subscriptions import Keeper

A, B = 'http://10.0.0.2:4101/', 'http://10.0.0.3:4102/'


def test_a_publisher_missing_for_the_grace_is_connected_again_then_after_a_doubling_backoff():
    keeper = Keeper(grace=5.0, backoff_first=4.0, backoff_max=20.0)
    wanted, deaf = {'/gap': {A}}, {}
    due = {t: keeper.step(t, wanted, deaf) for t in range(0, 80)}
    attempts = [(t, d[0][3]) for t, d in sorted(due.items()) if d]
    # first at the grace, then 4, 8, 16 s apart, then the cap of 20 s
    assert attempts == [(5, 1), (9, 2), (17, 3), (33, 4), (53, 5), (73, 6)]
    assert due[5] == [('/gap', A, 5.0, 1)]


def test_hurried_a_cut_publisher_is_connected_again_at_the_first_look_then_the_grace_is_back():
    """Issue 16, a key rotation: the TLS layer knows the connections it sees cut were cut on purpose
    (a revoked certificate) and that rospy will not make them again; waiting the grace was each
    subscription's 5.5 s pause. Hurried, a missing publisher is due at once, one already missing
    within its grace too; one already tried keeps its backoff; after the window the grace is back."""
    keeper = Keeper(grace=5.0, backoff_first=4.0)
    assert keeper.step(10.0, {'/a': {A}}, {}) == []           # missing since 10, in its grace
    keeper.hurry(until=20.0)
    assert keeper.hurrying(10.5) and not keeper.hurrying(20.0)
    assert keeper.step(10.5, {'/a': {A}, '/b': {B}}, {}) == [('/a', A, 0.5, 1), ('/b', B, 0.0, 1)]
    assert keeper.step(11.0, {'/a': {A}, '/b': {B}}, {}) == []   # tried: its backoff still holds
    assert keeper.step(14.6, {'/a': {A}, '/b': {B}}, {}) == [('/a', A, 4.6, 2), ('/b', B, 4.1, 2)]
    keeper.hurry(until=15.0)                                   # a shorter window does not shorten it
    assert keeper.hurry_until == 20.0
    assert keeper.step(21.0, {'/c': {A}}, {}) == [] and keeper.step(25.9, {'/c': {A}}, {}) == []
    assert keeper.step(26.0, {'/c': {A}}, {}) == [('/c', A, 5.0, 1)]   # past the window: the grace again


def test_a_publisher_connected_within_the_grace_is_left_to_rospy():
    keeper = Keeper(grace=5.0)
    assert keeper.step(0.0, {'/gap': {A}}, {}) == []
    assert keeper.step(4.9, {'/gap': {A}}, {}) == []
    assert keeper.step(5.5, {'/gap': {A}}, {'/gap': {A}}) == []   # rospy connected it meanwhile
    assert keeper.missing == {}


def test_a_publisher_found_again_is_forgotten_and_a_later_loss_gets_a_fresh_grace():
    keeper = Keeper(grace=5.0, backoff_first=4.0)
    for t in range(0, 30):
        keeper.step(t, {'/gap': {A}}, {})
    assert keeper.step(30, {'/gap': {A}}, {'/gap': {A}}) == []
    assert keeper.step(31, {'/gap': {A}}, {}) == []    # lost again: waits the grace, not the old backoff
    assert keeper.step(35.9, {'/gap': {A}}, {}) == []
    assert keeper.step(36, {'/gap': {A}}, {}) == [('/gap', A, 5.0, 1)]


def test_a_publisher_the_master_no_longer_knows_is_forgotten():
    keeper = Keeper(grace=2.0)
    keeper.step(0, {'/gap': {A, B}}, {'/gap': {B}})
    assert keeper.step(1, {'/gap': {B}}, {'/gap': {B}}) == [] and keeper.missing == {}
    assert keeper.step(10, {'/gap': {B}}, {'/gap': {B}}) == []


def test_topics_and_publishers_are_kept_apart():
    keeper = Keeper(grace=1.0, backoff_first=10.0)
    keeper.step(0, {'/gap': {A}, '/speed': {A, B}}, {'/speed': {A}})
    due = keeper.step(1, {'/gap': {A}, '/speed': {A, B}}, {'/speed': {A}})
    assert sorted((t, u) for t, u, _, _ in due) == [('/gap', A), ('/speed', B)]
    assert keeper.step(2, {'/gap': {A}, '/speed': {A, B}}, {'/gap': {A}, '/speed': {A}}) == []
    assert list(keeper.missing) == [('/speed', B)]


def test_no_grace_connects_at_the_first_look():
    assert Keeper(grace=0.0).step(0, {'/gap': {A}}, {}) == [('/gap', A, 0.0, 1)]


@pytest.mark.parametrize('grace,first,most', [(-1, 4, 60), (5, 0, 60), (5, 10, 5), (float('nan'), 4, 60)])
def test_bad_timings_are_refused(grace, first, most):
    with pytest.raises(ValueError):
        Keeper(grace=grace, backoff_first=first, backoff_max=most)


@pytest.mark.parametrize('case', range(3))
def test_random_looks_never_act_early_and_never_leave_a_lost_publisher_for_longer_than_the_cap(case):
    """Publishers that come and go, connections that rospy makes and loses, looks at random times: an
    attempt only after the grace of continuous absence, attempts for one publisher at least the first
    backoff apart, and a publisher lost for good tried again at least once every backoff_max."""
    seed = int(os.environ.get('AFT_SEED', random.randrange(1 << 30))) + case
    rng = random.Random(seed)
    grace, first, most = rng.uniform(0, 6), rng.uniform(0.5, 5), 0.0
    most = rng.uniform(first, 40)
    keeper = Keeper(grace=grace, backoff_first=first, backoff_max=most)
    uris = [A, B, 'http://10.0.0.4:4103/']
    topics = ['/gap', '/speed']
    absent_since, last_try = {}, {}
    t = 0.0
    for _ in range(600):
        t += rng.uniform(0.05, 3.0)
        wanted = {topic: {u for u in uris if rng.random() < 0.9} for topic in topics}
        have = {topic: {u for u in wanted[topic] if rng.random() < 0.5} for topic in topics}
        lacking = {(topic, u) for topic in topics for u in wanted[topic] - have[topic]}
        for key in list(absent_since):
            if key not in lacking:
                del absent_since[key]
                last_try.pop(key, None)
        for key in lacking:
            absent_since.setdefault(key, t)
        for topic, uri, missing_s, attempt in keeper.step(t, wanted, have):
            key = (topic, uri)
            assert key in lacking, 'seed %d: %s tried while connected' % (seed, key)
            assert t - absent_since[key] >= grace - 1e-9, 'seed %d: %s tried before its grace' % (seed, key)
            assert abs(missing_s - (t - absent_since[key])) < 1e-9, seed
            if key in last_try:
                assert t - last_try[key] >= first - 1e-9, 'seed %d: %s tried twice within %.2f s' % (seed, key, first)
            last_try[key] = t
        for key, since in absent_since.items():
            latest = last_try.get(key, since + grace - 3.0 - 1e-9)   # (a look may come 3 s late)
            assert t - latest <= max(grace, most) + 3.0 + 1e-9, 'seed %d: %s left for %.1f s' % (seed, key, t - latest)


def test_the_keepers_period_comes_from_the_environment():
    from aft_ftm.ros.rejoin import period_from_env
    name = 'AFT_SUBSCRIPTION_CHECK_PERIOD'
    assert period_from_env({}, name, 2.0) == 2.0
    assert period_from_env({name: '0'}, name, 2.0) == 0.0
    with pytest.raises(ConfigError, match=name):
        period_from_env({name: 'often'}, name, 2.0)
