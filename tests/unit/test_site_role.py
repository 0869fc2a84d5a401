"""What a replica does when its server hangs, by what the witness says of its site. No ROS.

A hang fail-stops a replica only while a peer can take over: a site that serves alone holds the only
copy of the state (CI, healing.test round 9: a lone primary fail-stopped on a 0.5 s server timeout
under load, and nothing served again)."""
import random

import pytest

from aft_ftm.protocol import Role
from aft_ftm.recovery import OnHang, SiteRole
from aft_ftm.witness import Op, Witness


@pytest.mark.parametrize('site, configurations, role, on_hang', [
    # (site, configurations heard in order as (epoch, primary, backup), role, what a hang does)
    ('master', [], None, OnHang.FAIL_STOP),                                   # no witness heard
    ('master', [(1, 'master', '')], Role.ALONE, OnHang.WAIT),                 # first primary, no backup yet
    ('master', [(1, 'master', ''), (2, 'master', 'slave')], Role.PRIMARY, OnHang.FAIL_STOP),
    ('slave', [(1, 'master', ''), (2, 'master', 'slave')], Role.BACKUP, OnHang.FAIL_STOP),
    ('master', [(2, 'master', 'slave'), (3, 'master', '')], Role.ALONE, OnHang.WAIT),     # backup excluded
    ('slave', [(2, 'master', 'slave'), (3, 'slave', '')], Role.ALONE, OnHang.WAIT),       # promoted
    ('master', [(2, 'master', 'slave'), (3, 'slave', '')], None, OnHang.FAIL_STOP),       # deposed
    ('master', [(3, 'master', ''), (4, 'master', 'slave')], Role.PRIMARY, OnHang.FAIL_STOP),  # re-joined
    ('', [(1, 'master', '')], None, OnHang.WAIT),                             # in no replica: nobody else
])
def test_a_hang_fail_stops_only_a_replica_whose_peer_can_take_over(site, configurations, role, on_hang):
    view = SiteRole(site)
    for epoch, primary, backup in configurations:
        view.on_configuration(epoch, primary, backup)
    assert (view.role, view.on_hang()) == (role, on_hang)


def test_against_a_real_witness_the_site_waits_exactly_while_it_is_the_only_one_serving():
    """Random register/admit/exclude/promote sequences on the witness (seeded): a hang is waited
    out exactly when the witness's configuration names the site primary with no backup."""
    seed = random.randrange(1 << 30)
    rng = random.Random(seed)
    for _ in range(200):
        witness = Witness()
        views = {s: SiteRole(s) for s in ('master', 'slave')}
        incarnations = {'master': 'm1', 'slave': 's1'}
        for step in range(rng.randint(1, 12)):
            site = rng.choice(['master', 'slave'])
            peer = 'slave' if site == 'master' else 'master'
            op = rng.choice([Op.REGISTER, Op.ADMIT, Op.EXCLUDE, Op.PROMOTE])
            witness.request(op, site, incarnations[site], peer=peer, peer_incarnation=incarnations[peer],
                            claim=rng.random() < 0.5)
            for view in views.values():
                view.on_configuration(witness.epoch, witness.primary, witness.backup)
            for name, view in views.items():
                serving_alone = witness.primary == name and not witness.backup
                assert (view.on_hang() == OnHang.WAIT) == serving_alone, (
                    'seed %d: %s in (%d, %r, %r)' % (seed, name, witness.epoch, witness.primary, witness.backup))


@pytest.mark.parametrize('configurations, peer, on_hang, asked', [
    # The configuration names a backup: the detector decides (True, False, None: it did not answer).
    ([(2, 'master', 'slave')], True, OnHang.FAIL_STOP, True),
    ([(2, 'master', 'slave')], False, OnHang.WAIT, True),      # seed 15 segment 20: the backup just failed
    ([(2, 'master', 'slave')], None, OnHang.WAIT, True),       # the detector frozen: unsure, so wait
    ([], False, OnHang.WAIT, True),                            # no witness: the detector alone decides
    ([], True, OnHang.FAIL_STOP, True),
    # Alone: nobody to fail over to, whatever the detector would say; it is not even asked.
    ([(3, 'master', '')], True, OnHang.WAIT, False),
    # Deposed (in no configuration): its peer is the primary; a hang fail-stops it if that peer is alive.
    ([(3, 'slave', '')], True, OnHang.FAIL_STOP, True),
])
def test_a_hang_fail_stops_only_when_the_detector_hears_the_peer_alive_now(configurations, peer, on_hang, asked):
    view = SiteRole('master')
    for epoch, primary, backup in configurations:
        view.on_configuration(epoch, primary, backup)
    calls = []

    def peer_alive():
        calls.append(1)
        return peer
    assert view.on_hang(peer_alive) == on_hang
    assert bool(calls) == asked
    if on_hang == OnHang.WAIT:
        assert 'master' in view.why_wait('site slave: declared failed')


def test_the_detector_says_the_peer_may_take_over_only_while_heard_within_the_timeout():
    from aft_ftm.detector import HeartbeatMonitor
    monitor = HeartbeatMonitor(0.03, started_at=0.0, stall_after=0.01)
    assert monitor.can_take_over(0.0, 0.03) == (False, 'never heard')
    monitor.beat(1.0)
    assert monitor.can_take_over(1.02, 0.03)[0] is True
    # Silent past the timeout: not yet declared failed (the check has not run), but it may not take over.
    alive, why = monitor.can_take_over(1.5, 0.03)
    assert not alive and why.startswith('silent for 500.0 ms')
    monitor.beat(1.6)
    assert monitor.can_take_over(1.61, 0.03)[0] is True
    monitor.announced(1.62, 'fail-stop')   # its last heartbeat said it stops
    assert monitor.can_take_over(1.62, 0.03) == (False, 'declared failed')
    monitor.check(1.63)
    assert monitor.can_take_over(1.63, 0.03) == (False, 'declared failed')
