"""The campaign's fault schedule: seeded, covering the catalogue, within its rules. No ROS."""
import collections
import random

import pytest

from aft_examples import schedule
from aft_examples.schedule import CATALOGUE, ScheduleError, catalogue, make, resolve_role


def test_the_catalogue_holds_every_fault_of_the_issue():
    kinds = collections.defaultdict(set)
    for entry in CATALOGUE:
        kinds[entry.kind].add(entry.target)
    for node in ('protocol', 'before', 'proceed', 'after', 'bank_server', 'crash_detector', 'recovery'):
        assert {'primary/' + node, 'backup/' + node} <= kinds['kill'] & kinds['freeze_node']
    assert {'proxy', 'witness', 'ros_master'} <= kinds['kill']
    assert kinds['power_loss'] == kinds['freeze_site'] == {'primary', 'backup'}
    assert {'primary', 'backup', 'client', 'witness'} <= kinds['partition']
    assert len(kinds['partition_pair']) == 6 and kinds['bandwidth'] and kinds['adapt'] == {'switch', 'compose',
                                                                                          'update'}


@pytest.mark.parametrize('seed', range(20))
def test_same_seed_same_schedule_and_every_entry_takes_its_turn(seed):
    offered = ('process', 'hosts', 'adapt', 'adapt_mechanism')
    entries = catalogue(offered)
    rounds = random.Random(seed).randint(1, 4)
    n = len(entries) * rounds
    first = make(n, seed, offered)
    assert first == make(n, seed, offered), 'seed %d: not reproducible' % seed
    counts = collections.Counter((f.kind, f.target) for f in first)
    assert counts == {(e.kind, e.target): rounds for e in entries}, 'seed %d' % seed
    assert {f.kind for f in first} <= {e.kind for e in entries}
    assert not any(f.target == 'ros_master' for f in first), 'seed %d: a fault the backend cannot inject' % seed
    updates_only = {(f.kind, f.target) for f in make(n, seed, ('process', 'adapt')) if f.kind == 'adapt'}
    assert updates_only == {('adapt', 'update')}, 'seed %d: %s' % (seed, updates_only)


@pytest.mark.parametrize('seed', range(20))
def test_durations_gaps_and_segments_within_the_rules(seed):
    faults = make(237, seed, ('process', 'hosts', 'master'), mechanisms=('pbr', 'lfr'), per_segment=25)
    for f in faults:
        if (f.kind, f.target) == ('kill', 'ros_master'):   # how long the killed master stays down
            assert schedule.MASTER_DOWN_RANGE[0] <= f.duration <= schedule.MASTER_DOWN_RANGE[1], f
            continue
        low, high = {'freeze_node': schedule.FREEZE_RANGE, 'freeze_site': schedule.FREEZE_RANGE,
                     'partition': schedule.PARTITION_RANGE, 'partition_pair': schedule.PARTITION_RANGE,
                     'bandwidth': schedule.BANDWIDTH_RANGE}.get(f.kind, (0.0, 0.0))
        assert low <= f.duration <= high, 'seed %d: %s' % (seed, f)
        assert schedule.GAP_RANGE[0] <= f.gap <= schedule.GAP_RANGE[1]
        assert f.segment == f.index // 25 and f.mechanism == ('pbr', 'lfr')[f.segment % 2]
    assert [f.index for f in faults] == list(range(237))
    short = [f for f in faults if f.kind.startswith('freeze') and f.duration < 0.15]
    long = [f for f in faults if f.kind.startswith('freeze') and f.duration > 1.0]
    assert short and long, 'seed %d: freezes should fall both under and past detection' % seed


def test_bad_requests_are_named():
    with pytest.raises(ScheduleError, match='integer >= 0'):
        make(-1, 0)
    with pytest.raises(ScheduleError, match='unknown capabilities'):
        make(10, 0, ('telepathy',))
    with pytest.raises(ScheduleError, match='offers nothing'):
        make(10, 0, ())


def test_roles_resolve_to_the_sites_serving_them():
    assert resolve_role('primary/after', 'slave', 'master') == 'slave/after'
    assert resolve_role('backup', 'slave', 'master') == 'master'
    assert resolve_role('proxy', 'slave', 'master') == 'proxy'
