"""Every node and command answers --help without starting work: no master is reachable here, so
one that tried to start (init_node, a service call, a roslaunch) would hang or fail instead."""
import concurrent.futures
import glob
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
NODES = sorted(glob.glob(os.path.join(ROOT, 'catkin_ws', 'src', '*', 'nodes', '*')))
SCRIPTS = sorted(p for p in glob.glob(os.path.join(ROOT, 'scripts', '*')) if not p.endswith('.sh'))
NO_MASTER = dict(os.environ, ROS_MASTER_URI='http://127.0.0.1:9')   # discard port: nothing answers


def help_failure(argv):
    """None if argv --help exits 0 with a usage line and a description; else what went wrong."""
    try:
        run = subprocess.run(argv + ['--help'], env=NO_MASTER, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             stdin=subprocess.DEVNULL, timeout=60)
    except subprocess.TimeoutExpired:
        return '%s --help still running after 60 s (it started work)' % ' '.join(argv)
    text = run.stdout.decode(errors='replace')
    if run.returncode != 0:
        return '%s --help exited %d:\n%s' % (' '.join(argv), run.returncode, text[-1500:])
    if 'usage:' not in text or len(text.strip().splitlines()) < 3:
        return '%s --help says too little:\n%s' % (' '.join(argv), text)
    return None


def failures(commands):
    with concurrent.futures.ThreadPoolExecutor(max_workers=3) as pool:
        return [f for f in pool.map(help_failure, commands) if f]


def test_every_node_answers_help():
    # The devel space's wrapper of each node, which rosrun finds and runs: without rosrun's package
    # crawl each takes half the time (the suite's budget); rosrun itself is run by every rostest.
    commands = [[os.path.join(ROOT, 'catkin_ws', 'devel', 'lib', p.split(os.sep)[-3], os.path.basename(p))]
                for p in NODES]
    assert len(commands) > 30
    found = failures(commands)
    assert not found, '\n\n'.join(found)


def test_every_script_answers_help():
    commands = [[sys.executable, p] for p in SCRIPTS]
    assert len(commands) > 10
    found = failures(commands)
    assert not found, '\n\n'.join(found)
