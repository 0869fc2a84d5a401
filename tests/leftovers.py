"""Processes a test started and left running: each carries the test's AFT_TEST_TAG in its environment."""
import psutil


def tagged(tag):
    """The processes whose environment has AFT_TEST_TAG=tag."""
    procs = []
    for proc in psutil.process_iter():
        try:
            if proc.environ().get('AFT_TEST_TAG') == tag:
                procs.append(proc)
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            pass
    return procs


def kill_tagged(tag):
    """Kill every process still carrying tag; returns them (empty if the test cleaned up after itself)."""
    procs = tagged(tag)
    for proc in procs:
        try:
            proc.kill()
        except psutil.NoSuchProcess:
            pass
    return procs


def run_tagged(script, args=(), timeout=180, home_prefix='aft_test_home_'):
    """Run a Python script (its text) in a process of its own under a fresh AFT_TEST_TAG and ROS_HOME;
    kill whatever carrying the tag is left, and fail the test if anything was. Returns
    (exit status, output)."""
    import os
    import subprocess
    import sys
    import tempfile
    import uuid
    tag = uuid.uuid4().hex
    env = dict(os.environ, AFT_TEST_TAG=tag, ROS_HOME=tempfile.mkdtemp(prefix=home_prefix))
    try:
        run = subprocess.run([sys.executable, '-c', script] + list(args), env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, timeout=timeout)
    finally:
        leftovers = kill_tagged(tag)
    assert not leftovers, 'processes left running: %s' % [p.pid for p in leftovers]
    return run.returncode, run.stdout.decode(errors='replace')


def run_seeded(script, args=(), timeout=300, home_prefix='aft_test_home_'):
    """run_tagged() a seeded script: the seed (AFT_SEED, else drawn) comes first in its arguments; it must
    exit 0 and end with 'ok'. The output's tail is printed, and a failure names the seed that replays it."""
    import os
    import random
    seed = int(os.environ.get('AFT_SEED', random.randrange(1 << 16)))
    code, output = run_tagged(script, args=[str(seed)] + list(args), timeout=timeout, home_prefix=home_prefix)
    print(output[-2000:])
    assert code == 0 and output.rstrip().endswith('ok'), 'seed %d (AFT_SEED replays):\n%s' % (seed, output[-5000:])
    return output
