"""The ROS master's reachability as Recovery sees it: one alarm when it stops answering, repeated at
most every `repeat` seconds, and its return said once. No ROS."""
import random

import pytest

from aft_ftm.master_watch import Decision, MasterState, MasterWatch


N, A, B = Decision.NOTHING, Decision.ALARM, Decision.BACK


@pytest.mark.parametrize('misses,probes,decisions', [
    (1, [True, True], [N, N]),
    (1, [False], [A]),                                       # dead from the first probe
    (1, [True, False, False, True], [N, A, N, B]),
    (1, [False, True, False], [A, B, A]),                    # each outage alarms
    (2, [True, False, True, False, False, False, True], [N, N, N, N, A, N, B]),   # one slow answer is no outage
    (3, [False, False, False], [N, N, A]),
])
def test_decisions_per_probe(misses, probes, decisions):
    watch = MasterWatch(repeat=60.0, misses=misses)
    assert [watch.probe(ok, now=float(t)) for t, ok in enumerate(probes)] == decisions


def test_an_outage_alarms_once_per_repeat_and_counts_its_length():
    watch = MasterWatch(repeat=10.0)
    alarms = [t for t in range(0, 35) if watch.probe(False, now=100.0 + t, error='refused') == Decision.ALARM]
    assert alarms == [1, 11, 21, 31]   # the second miss in a row (default misses=2), then every 10 s
    assert watch.state == MasterState.UNREACHABLE and watch.unreachable_for(135.0) == 35.0   # since the 1st miss
    assert watch.error == 'refused'
    assert watch.probe(True, now=136.0) == Decision.BACK and watch.unreachable_for(136.0) is None


@pytest.mark.parametrize('seed', range(20))
def test_every_outage_is_alarmed_and_every_return_said_once(seed):
    rng = random.Random(seed)
    misses = rng.randint(1, 3)
    watch = MasterWatch(repeat=rng.choice([0.5, 5.0, 60.0]), misses=misses)
    probes = [rng.random() < 0.6 for _ in range(200)]
    decisions = [watch.probe(ok, now=t * 0.25) for t, ok in enumerate(probes)]
    # An outage: a run of at least `misses` unanswered probes; alarmed at its misses-th probe, and its end said.
    runs, start = [], None
    for i, ok in enumerate(probes + [True]):
        if not ok and start is None:
            start = i
        elif ok and start is not None:
            runs.append((start, i))
            start = None
    outages = [(a, b) for a, b in runs if b - a >= misses]
    assert [decisions[a + misses - 1] for a, _ in outages] == [Decision.ALARM] * len(outages), 'seed %d' % seed
    assert decisions.count(Decision.BACK) == len([b for _, b in outages if b < len(probes)]), 'seed %d' % seed
    assert all(d == Decision.NOTHING for ok, d in zip(probes, decisions) if ok and d != Decision.BACK)
    assert all(decisions[i] == Decision.NOTHING for a, b in runs if b - a < misses for i in range(a, b))


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match='repeat'):
        MasterWatch(repeat=0)
    with pytest.raises(ValueError, match='misses'):
        MasterWatch(misses=0)
