"""One witness per replicated service: every node of a replica that follows the witness's
configurations follows those of the witness its site was given, not a fixed topic.

Until session 40 every node subscribed to /aft/witness/configuration whatever its site's ``witness``
said: the replicas of a second service on one ROS master, with a witness of their own, heard the first
service's configurations (which name other sites) and fail-stopped as deposed, and never heard their
own witness's. The launch files are read by roslaunch's own loader, and the adaptation scripts by the
engine's, without starting anything. No ROS master."""
import os

import pytest
import roslaunch.config
import roslaunch.xmlloader
from aft_ftm import adaptation
from aft_ftm.ros.witness_client import CONFIGURATION_TOPIC, DEFAULT_WITNESS, configuration_topic

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
LAUNCH = os.path.join(ROOT, 'catkin_ws', 'src', 'aft_ftm', 'launch')
SCRIPTS = os.path.join(ROOT, 'catkin_ws', 'src', 'aft_ftm', 'adaptations')
# The node types whose code follows the witness's configurations in a replica (each reads ~witness);
# an After only PBR's and LFR's (TR's and A&D's know their site, to fail-stop it, but follow no witness).
FOLLOWERS = {'protocol', 'before', 'proceed', 'crash_detector', 'recovery', 'after'}


def test_the_configurations_are_the_witness_nodes_own_topic_beside_its_service():
    assert configuration_topic(DEFAULT_WITNESS) == CONFIGURATION_TOPIC == '/aft/witness/configuration'
    assert configuration_topic('/bank/witness/request') == '/bank/witness/configuration'
    assert configuration_topic('/a/b/c/witness/request') == '/a/b/c/witness/configuration'
    assert configuration_topic('witness/request') == 'witness/configuration'   # relative: resolved as the service is
    assert configuration_topic('request') == 'configuration'


def load(name, *argv):
    config = roslaunch.config.ROSLaunchConfig()
    roslaunch.xmlloader.XmlLoader().load(os.path.join(LAUNCH, name), config, verbose=False, argv=list(argv))
    return config


def followers(config):
    """{node name: its ~witness or None} for the nodes of a replica (``~site`` set) that follow the witness."""
    found = {}
    for node in config.nodes:
        name = node.namespace.rstrip('/') + '/' + node.name
        site = config.params.get(name + '/site')
        if node.package != 'aft_ftm' or node.type not in FOLLOWERS or site is None or not site.value:
            continue
        mechanism = config.params.get(name + '/mechanism')
        if node.type == 'after' and (mechanism is None or mechanism.value not in ('pbr', 'lfr')):
            continue
        witness = config.params.get(name + '/witness')
        found[name] = None if witness is None else witness.value
    return found


@pytest.mark.parametrize('mechanism, inner', [('pbr', ''), ('pbr', 'tr'), ('pbr', 'ad+tr'), ('lfr', '')])
def test_every_follower_of_a_replica_is_given_its_sites_witness(mechanism, inner):
    config = load('replica.launch', 'site:=nav_a', 'peer:=nav_b', 'role:=primary', 'server:=/nav_a/plan',
                  'mechanism:=' + mechanism, 'inner:=' + inner, 'witness:=/nav/witness/request',
                  'request_assertions:=[m:f]')
    found = followers(config)
    # Protocol, Recovery, crash detector, After, a Proceed (the innermost), and each nested mechanism's Before
    assert len(found) == 5 + len([m for m in inner.split('+') if m]), found
    assert set(found.values()) == {'/nav/witness/request'}, found


def test_a_replica_without_a_witness_follows_none():
    config = load('replica.launch', 'site:=nav_a', 'peer:=nav_b', 'role:=primary', 'server:=/nav_a/plan',
                  'inner:=tr', 'witness:=none')
    found = followers(config)
    assert found and set(found.values()) <= {'', None}, found
    assert config.params['/nav_a/crash_detector/follow_witness'].value is False


def test_a_second_pbr_launch_takes_its_own_witness_proxy_and_sites():
    config = load('pbr.launch', 'service:=/plan', 'service_type:=nav_msgs/GetPlan', 'primary_server:=/a/plan',
                  'primary_get_state:=/a/get', 'primary_set_state:=/a/set', 'backup_server:=/b/plan',
                  'backup_get_state:=/b/get', 'backup_set_state:=/b/set', 'witness_ns:=nav', 'primary_site:=nav_a',
                  'backup_site:=nav_b', 'ftm_ns:=/nav_ftm', 'proxy_name:=nav_proxy')
    witnesses = [n for n in config.nodes if n.type == 'witness']
    assert [(w.namespace, w.name) for w in witnesses] == [('/nav/', 'witness')]
    # nothing of it under the names of the default service's nodes (a node started under a taken name
    # makes the ROS master shut the other down)
    names = {n.namespace.rstrip('/') + '/' + n.name for n in config.nodes}
    assert names.isdisjoint({'/proxy', '/aft/witness', '/master/protocol', '/slave/protocol'}), sorted(names)
    found = followers(config)
    assert {n.split('/')[1] for n in found} == {'nav_a', 'nav_b'}, found
    assert set(found.values()) == {'/nav/witness/request'}, found


def test_the_compose_adaptation_gives_its_nested_mechanism_the_sites_witness():
    with open(os.path.join(SCRIPTS, 'compose.yaml')) as f:
        text = f.read()
    default = adaptation.load(text, source='compose.yaml')
    given = adaptation.load(text, {'witness': '/nav/witness/request', 'site': ['nav_a', 'nav_b']}, source='compose.yaml')
    for script, expected in ((default, DEFAULT_WITNESS), (given, '/nav/witness/request')):
        assert script.launch, 'compose launches nothing'
        for launch in script.launch:
            args = dict(launch.args)
            assert args['witness'] == expected, args
            config = load('mechanism.launch', *('%s:=%s' % kv for kv in launch.args))
            found = followers(config)
            assert len(found) == 2 and set(found.values()) == {expected}, found   # its Before and Proceed


def test_the_engine_reads_each_new_node_s_witness_and_site_from_the_launch_files_it_would_start():
    """What the adaptation engine checks before anything changes (review of session 41): every follower
    of a replica, with its witness and site; a mechanism outside a replica (no site) follows none, and
    is not asked for the witness it is given by default."""
    from aft_ftm.ros.adaptation_engine import services_called_by
    base = ['ns:=/master/tr', 'mechanism:=tr', 'inp:=/i', 'out:=/o', 'server:=/master/account']
    calls, witnesses = services_called_by(load('mechanism.launch', *(base + ['site:=master',
                                                                           'witness:=/nav/witness/request'])))
    assert witnesses and set(witnesses.values()) == {('/nav/witness/request', 'master')}, witnesses
    assert all('/nav/witness/request' in calls[node] for node in witnesses if node in calls)
    calls, witnesses = services_called_by(load('mechanism.launch', *base))   # no site: outside a replica
    assert witnesses == {} and not any('/aft/witness/request' in names for names in calls.values()), calls
