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
