"""Installable like any ROS package: ``catkin_make install`` into a fresh prefix, then, in an
environment that knows only that install space (no source tree, no devel space on any path), the
PBR demo answers a client exactly once and a car scenario runs with its files found through the
package path. Every process started carries the test's AFT_TEST_TAG and is killed at the end."""
import os
import shutil
import socket
import subprocess
import tempfile
import time
import uuid

import pytest
from leftovers import kill_tagged

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
VENV_BIN = os.path.join(ROOT, '.venv', 'bin')
CLEAN_ENV = {'HOME': os.environ.get('HOME', '/root'), 'LANG': 'C.UTF-8',
             'PATH': VENV_BIN + ':/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin'}


def free_port():
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@pytest.fixture(scope='module')
def install_space():
    work = tempfile.mkdtemp(prefix='aft_install_')
    prefix = os.path.join(work, 'install')
    build = subprocess.run(
        ['catkin_make', '-C', os.path.join(ROOT, 'catkin_ws'), '--build', os.path.join(work, 'build'), '-DCATKIN_DEVEL_PREFIX=' + os.path.join(work, 'devel'),
         '-DCMAKE_INSTALL_PREFIX=' + prefix, '-DPYTHON_EXECUTABLE=' + os.path.join(VENV_BIN, 'python3'),
         '-DCATKIN_ENABLE_TESTING=OFF', 'install'],
        cwd=os.path.join(ROOT, 'catkin_ws'), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=600,
        env=CLEAN_ENV)   # not this shell's: it has the devel space sourced, which the install would chain to
    assert build.returncode == 0, 'catkin_make install failed:\n%s' % build.stdout.decode(errors='replace')[-4000:]
    try:
        yield work, prefix
    finally:
        shutil.rmtree(work, ignore_errors=True)


def in_install_space(prefix, work, script, tag, timeout):
    """Run a bash script with only the install space sourced; returns (exit status, output)."""
    env = dict(CLEAN_ENV, HOME=work, AFT_TEST_TAG=tag, ROS_HOME=os.path.join(work, 'ros'),
               ROS_MASTER_URI='http://127.0.0.1:%d' % free_port())
    text = 'set -e\nsource %s/setup.bash\n%s' % (prefix, script)
    try:
        run = subprocess.run(['bash', '-c', text], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             timeout=timeout, start_new_session=True)
        return run.returncode, run.stdout.decode(errors='replace')
    finally:
        kill_tagged(tag)


def test_the_install_space_holds_the_packages_and_nothing_of_the_source_tree(install_space):
    work, prefix = install_space
    code, out = in_install_space(prefix, work, 'echo "$ROS_PACKAGE_PATH"; rospack list-names; '
                                 'python3 -c "import aft_ftm, aft_examples, tjp_sim; print(aft_ftm.__file__)"; '
                                 'ls "$(rospack find aft_examples)/config/tls_policy.yaml" '
                                 '"$(rospack find aft_examples)/config/sec_policy.yaml" '
                                 '"$(rospack find tjp_sim)/config/tls_policy.yaml"',   # the demos' policies
                                 uuid.uuid4().hex, 60)
    assert code == 0, out
    assert ROOT not in out.replace(prefix, ''), 'the install space points into the source tree:\n%s' % out
    for package in ('aft_msgs', 'aft_ftm', 'aft_service_manager', 'aft_examples', 'aft_bench', 'tjp_sim'):
        assert package in out.split(), out


@pytest.mark.family('install_space_runs', 1)
def test_the_readme_walkthrough_runs_from_the_install_space(install_space):
    """README "Five commands": the PBR demo, a client, adapt mid-run, a power loss, the figures."""
    work, prefix = install_space
    script = '''
roslaunch aft_examples demo_one_host.launch timeout:=0.2 > %(work)s/demo.log 2>&1 &
for i in $(seq 1 120); do rosservice list 2>/dev/null | grep -qx /account && break; sleep 0.5; done
rosrun aft_examples bank_client _count:=2500 _pause:=0.002 > %(work)s/client.log 2>&1 &
client=$!
sleep 1
rosrun aft_ftm adapt compose
rosrun aft_ftm power_off /master
wait $client
cat %(work)s/client.log
rosrun aft_ftm status --verbose || echo "status exit $?"
''' % {'work': work}
    code, out = in_install_space(prefix, work, script, uuid.uuid4().hex, 300)
    assert code == 0, out[-4000:]
    assert 'adaptation compose done' in out and '/master: ' in out and 'frozen then killed' in out, out[-4000:]
    assert 'bank_client: 2500 sent, 2500 answered, 2500 correct, 0 lost, 0 duplicated, 0 reordered' in out, out[-4000:]
    # the survivor serves alone and says so (WARN, status exit 1); its Recovery reports the failover
    assert 'slave    pbr   ALONE' in out and 'status exit 1' in out, out[-4000:]
    assert 'master failed (no heartbeat' in out and 'recovered in' in out, out[-4000:]


@pytest.mark.family('install_space_runs', 1)
def test_a_car_scenario_runs_from_the_install_space(install_space):
    work, prefix = install_space
    out_dir = os.path.join(work, 'car')
    started = time.monotonic()
    code, out = in_install_space(prefix, work, 'rosrun tjp_sim scenario ultrasonic_crash --no-plot --out %s' % out_dir,
                                 uuid.uuid4().hex, 600)
    assert code == 0, out[-3000:]
    assert os.path.isfile(os.path.join(out_dir, 'summary.json')) and 'record: %s' % out_dir in out, out[-3000:]
    print('car scenario from the install space: %.0f s' % (time.monotonic() - started))
