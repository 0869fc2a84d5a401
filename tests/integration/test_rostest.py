"""Graph-level tests: each rostest file of every package, run as rostest runs it (own master).

Every process a rostest starts carries AFT_TEST_TAG in its environment; after the run, pass or
fail, any process still carrying it is killed and the test fails.
"""
import glob
import json
import os
import subprocess
import tempfile
import uuid

import pytest
from leftovers import kill_tagged
from reporting import report

SRC = os.path.join(os.path.dirname(__file__), '..', '..', 'catkin_ws', 'src')
PACKAGES = ('aft_ftm', 'aft_service_manager', 'aft_examples', 'aft_bench', 'tjp_sim')
LAUNCH_DIR = os.path.join(SRC, 'aft_ftm', 'launch')
ROSTESTS = [(pkg, os.path.basename(p)) for pkg in PACKAGES
            for p in sorted(glob.glob(os.path.join(SRC, pkg, 'test', '*.test')))]


@pytest.mark.parametrize('package,test_file', ROSTESTS, ids=['%s/%s' % t for t in ROSTESTS])
def test_rostest(package, test_file):
    tag = uuid.uuid4().hex
    results = tempfile.mkdtemp(prefix='aft_results_')
    env = dict(os.environ, AFT_TEST_TAG=tag, AFT_RESULTS_DIR=results)
    try:
        # Not --text: with it rostest exits 0 even when tests fail.
        run = subprocess.run(['rostest', package, test_file], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, timeout=1800)
        output = run.stdout.decode(errors='replace')
    finally:
        leftovers = kill_tagged(tag)
    for path in sorted(glob.glob(os.path.join(results, '*.json'))):
        with open(path) as f:
            report('%s: %s' % (os.path.basename(path)[:-5], json.dumps(json.load(f), sort_keys=True)))
    not_drawn = os.path.join(results, 'not_drawn.txt')   # (aft_ftm.suite.say_not_drawn)
    skipped = []
    if os.path.exists(not_drawn):
        with open(not_drawn) as f:
            skipped = sorted({line.strip() for line in f if line.strip()})
    if skipped:   # rostest's summary counts them as passed: said here, never silent
        report('%s: %d cases not drawn in the short suite (AFT_SUITE=full runs them): %s' % (
            test_file, len(skipped), ', '.join(skipped)))
    if run.returncode != 0 or 'RESULT: SUCCESS' not in output:
        details = ''
        for xml in glob.glob(os.path.join(os.environ.get('ROS_HOME', os.path.expanduser('~/.ros')),
                                          'test_results', package, '*%s*.xml' % test_file[:-5])):
            with open(xml, errors='replace') as f:
                details += f.read()[-8000:]
        pytest.fail('rostest %s failed (exit %d):\n%s\n%s' % (test_file, run.returncode, output[-4000:], details))
    assert not leftovers, 'processes left running after %s: %s' % (
        test_file, [' '.join(p.cmdline()[:4]) for p in leftovers if p.is_running()])


# Arguments for the launch files that have required ones, as a user would give them.
REPLICA = ['site:=master', 'peer:=slave', 'role:=primary']
LAUNCH_ARGS = {
    'replica.launch': REPLICA + ['mechanism:=lfr', 'server:=/master/account', 'get_state:=/m/get_state',
                                     'set_state:=/m/set_state'],
    'proxy.launch': ['service:=/account', 'service_type:=aft_msgs/Account'],
    'pbr.launch': ['service:=/account', 'service_type:=aft_msgs/Account', 'primary_server:=/a/account',
                   'primary_get_state:=/a/g', 'primary_set_state:=/a/s', 'backup_server:=/b/account',
                   'backup_get_state:=/b/g', 'backup_set_state:=/b/s'],
    'demo_replica_site.launch': REPLICA,
    'stages.launch': REPLICA,
    'mechanism.launch': ['ns:=x', 'mechanism:=tr', 'inp:=/i', 'out:=/o', 'server:=/account'],
    'proceed.launch': ['site:=master', 'server:=/master/account'],
    'demo_mechanism_site.launch': ['mechanism:=ad'],
    'car.launch': ['scenario:=board_power_loss'],
    'board.launch': ['board:=board_a', 'peer:=board_b'],
}


def launch_files():
    paths = []
    for pkg in PACKAGES:
        paths += sorted(glob.glob(os.path.join(SRC, pkg, 'launch', '*.launch')))
        paths += sorted(glob.glob(os.path.join(SRC, pkg, 'test', '*.test')))
    return paths


def _rospack():
    """One package index for every lookup (each new one walks the whole ROS_PACKAGE_PATH again)."""
    import rospkg
    global _ROSPACK
    if _ROSPACK is None:
        _ROSPACK = rospkg.RosPack()
    return _ROSPACK


_ROSPACK = None


@pytest.mark.parametrize('path', launch_files(), ids=os.path.basename)
def test_launch_file_loads_and_every_node_exists(path):
    import roslaunch.config
    import roslaunch.xmlloader
    import roslib.packages
    config = roslaunch.config.ROSLaunchConfig()
    roslaunch.xmlloader.XmlLoader().load(path, config, argv=LAUNCH_ARGS.get(os.path.basename(path), []),
                                         verbose=False)
    nodes = list(config.nodes) + list(config.tests)
    assert nodes, 'no node in %s' % path
    for node in nodes:
        assert roslib.packages.find_node(node.package, node.type, rospack=_rospack()), \
            '%s: node %s/%s has no executable' % (os.path.basename(path), node.package, node.type)


def test_a_missing_required_argument_is_named():
    import roslaunch.config
    import roslaunch.xmlloader
    path = os.path.join(LAUNCH_DIR, 'proxy.launch')
    loader = roslaunch.xmlloader.XmlLoader()
    loader.ignore_unset_args = False   # roslaunch reads it without setting it
    with pytest.raises(roslaunch.xmlloader.XmlParseException, match="requires the 'service_type' arg"):
        loader.load(path, roslaunch.config.ROSLaunchConfig(), argv=['service:=/a'], verbose=False)


def test_mechanisms_nest_to_any_depth_a_protocol_standing_in_for_each_proceed():
    import roslaunch.config
    import roslaunch.xmlloader
    path = os.path.join(LAUNCH_DIR, 'replica.launch')
    config = roslaunch.config.ROSLaunchConfig()
    roslaunch.xmlloader.XmlLoader().load(path, config, argv=LAUNCH_ARGS['replica.launch'][:3] + [
        'server:=/master/account', 'inner:=tr+ad'], verbose=False)
    nodes = {n.namespace + n.name: n for n in config.nodes}
    assert '/master/proceed' not in nodes and '/master/tr/proceed' not in nodes
    assert '/master/tr/ad/proceed' in nodes     # only the innermost calls the server
    remaps = {name: dict(n.remap_args) for name, n in nodes.items()}
    assert remaps['/master/tr/protocol'] == {'pxy2pro': '/master/bfr2prd', 'pro2pxy': '/master/prd2aft'}
    assert remaps['/master/tr/ad/protocol'] == {'pxy2pro': '/master/tr/bfr2prd', 'pro2pxy': '/master/tr/prd2aft'}
    # ... and a hung server there fail-stops the whole replica site.
    assert remaps['/master/tr/ad/proceed'] == {'server': '/master/account', 'fail_stop': '/master/fail_stop'}


@pytest.mark.parametrize('adaptable,replaceable_required', [('false', True), ('true', False)])
def test_an_adaptable_site_lets_its_stages_be_replaced_without_stopping_the_site(adaptable, replaceable_required):
    import roslaunch.config
    import roslaunch.xmlloader
    path = os.path.join(LAUNCH_DIR, 'replica.launch')
    config = roslaunch.config.ROSLaunchConfig()
    roslaunch.xmlloader.XmlLoader().load(path, config, argv=REPLICA + [
        'server:=/master/account', 'adaptable:=' + adaptable], verbose=False)
    required = {n.namespace + n.name: n.required for n in config.nodes}
    for name in ('/master/before', '/master/proceed', '/master/after'):
        assert required[name] == replaceable_required, name
    for name in ('/master/protocol', '/master/crash_detector', '/master/recovery'):
        assert required[name], name
    # ... and its crash detector watches them all the same: a stage's crash that no adaptation retired
    # fails the site over at once, where it used to wait for the Protocol's timeouts.
    assert config.params['/master/crash_detector/watch_replaceable'].value is (not replaceable_required)
