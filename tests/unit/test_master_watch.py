"""The ROS master's reachability as Recovery sees it: one alarm when it stops answering, repeated at
most every `repeat` seconds, and its return said once. No ROS."""
import random

import pytest

from aft_ftm.master_watch import Decision, MasterState, MasterWatch


@pytest.mark.parametrize('probes,decisions', [
    ([True, True], [Decision.NOTHING, Decision.NOTHING]),
    ([False], [Decision.ALARM]),                                       # dead from the first probe
    ([True, False, False, True], [Decision.NOTHING, Decision.ALARM, Decision.NOTHING, Decision.BACK]),
    ([False, True, False], [Decision.ALARM, Decision.BACK, Decision.ALARM]),   # each outage alarms
])
def test_decisions_per_probe(probes, decisions):
    watch = MasterWatch(repeat=60.0)
    assert [watch.probe(ok, now=float(t)) for t, ok in enumerate(probes)] == decisions


def test_an_outage_alarms_once_per_repeat_and_counts_its_length():
    watch = MasterWatch(repeat=10.0)
    alarms = [t for t in range(0, 35) if watch.probe(False, now=100.0 + t, error='refused') == Decision.ALARM]
    assert alarms == [0, 10, 20, 30]
    assert watch.state == MasterState.UNREACHABLE and watch.unreachable_for(135.0) == 35.0
    assert watch.error == 'refused'
    assert watch.probe(True, now=136.0) == Decision.BACK and watch.unreachable_for(136.0) is None


@pytest.mark.parametrize('seed', range(20))
def test_every_outage_is_alarmed_and_every_return_said_once(seed):
    rng = random.Random(seed)
    watch = MasterWatch(repeat=rng.choice([0.5, 5.0, 60.0]))
    probes = [rng.random() < 0.6 for _ in range(200)]
    decisions = [watch.probe(ok, now=t * 0.25) for t, ok in enumerate(probes)]
    outages = sum(1 for i, ok in enumerate(probes) if not ok and (i == 0 or probes[i - 1]))
    returns = sum(1 for i, ok in enumerate(probes) if ok and i > 0 and not probes[i - 1])
    first_alarms = [d for i, d in enumerate(decisions) if not probes[i] and (i == 0 or probes[i - 1])]
    assert first_alarms == [Decision.ALARM] * outages, 'seed %d' % seed
    assert decisions.count(Decision.BACK) == returns, 'seed %d' % seed
    assert all(d == Decision.NOTHING for ok, d in zip(probes, decisions) if ok and d != Decision.BACK)


def test_a_bad_repeat_is_refused():
    with pytest.raises(ValueError, match='repeat'):
        MasterWatch(repeat=0)
