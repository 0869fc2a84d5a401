"""replica.launch's group commit (~max_batch of the Protocol), read by roslaunch's own loader without
starting anything: batches only for PBR on a site no adaptation may switch. An explicit max_batch on
an adaptable site or for LFR gave batches the mechanism cannot follow (review of group commit,
session 33). No ROS master."""
import os

import pytest
import roslaunch.config
import roslaunch.xmlloader

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
LAUNCH = os.path.join(ROOT, 'catkin_ws', 'src', 'aft_ftm', 'launch', 'replica.launch')


def max_batch(mechanism, adaptable, given):
    config = roslaunch.config.ROSLaunchConfig()
    roslaunch.xmlloader.XmlLoader().load(LAUNCH, config, verbose=False, argv=[
        'mechanism:=' + mechanism, 'adaptable:=' + adaptable, 'max_batch:=' + given, 'site:=master', 'peer:=slave',
        'role:=primary', 'server:=bank_server'])
    return config.params['/master/protocol/max_batch'].value


@pytest.mark.parametrize('mechanism, adaptable, given, expected', [
    ('pbr', 'false', 'auto', 16), ('pbr', 'false', '8', 8),
    ('pbr', 'true', 'auto', 1), ('pbr', 'true', '8', 1),
    ('lfr', 'false', 'auto', 1), ('lfr', 'false', '8', 1)])
def test_batches_only_for_pbr_on_a_site_no_adaptation_may_switch(mechanism, adaptable, given, expected):
    assert max_batch(mechanism, adaptable, given) == expected
