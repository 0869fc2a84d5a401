"""The car's scenario command, stopped by SIGTERM (a test's time limit, a supervisor) at a moment drawn
from a printed seed, while it starts its nodes or while the car drives: it stops every process of its
run and says why (exit 2). Before session 50 the signal's RunError, raised wherever the main thread
was, was swallowed by the set-up's `except Exception` around a master call: the run went on to its
end, and a SIGTERM from a test whose pipes were closed left the master, the boards and the simulator
running."""
import os
import random
import signal
import subprocess
import time

import psutil

from aft_ftm.sites import process_tree

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENARIO = os.path.join(ROOT, 'catkin_ws', 'devel', 'lib', 'tjp_sim', 'scenario')
SEED = int(os.environ.get('AFT_SEED', int(time.time()) % 100000))


def runs(process):
    """Alive and not a zombie (one read: a process ending meanwhile is not an error)."""
    try:
        return process.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def test_a_scenario_stopped_by_sigterm_stops_every_process_of_its_run(tmp_path):
    rng = random.Random(SEED)
    at = rng.uniform(1.0, 7.0)   # its nodes start within about 5 s under TLS: both phases are drawn
    env = {k: v for k, v in os.environ.items() if k != 'ROS_MASTER_URI'}   # it starts a master of its own
    argv = [SCENARIO, 'board_power_loss', '--json', '--no-plot', '--tls', '--out', str(tmp_path / 'run')]
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    seen = {}   # pid -> psutil.Process of every process of the run seen before the signal
    try:
        deadline = time.monotonic() + at
        while time.monotonic() < deadline and proc.poll() is None:
            seen.update((p.pid, p) for p in process_tree(proc.pid))
            time.sleep(0.05)
        assert proc.poll() is None, 'AFT_SEED=%d: the scenario ended by itself before its SIGTERM' % SEED
        nodes = len(seen)
        proc.send_signal(signal.SIGTERM)
        try:
            _, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            raise AssertionError('AFT_SEED=%d: SIGTERM at %.2f s: the scenario still runs 60 s later' % (SEED, at))
        said = err.decode(errors='replace')
        assert proc.returncode == 2 and 'terminated by signal 15' in said, (
            'AFT_SEED=%d: SIGTERM at %.2f s: exit %d:\n%s' % (SEED, at, proc.returncode, said[-2000:]))
        time.sleep(0.5)   # (a zombie's parent, ended, hands it to init, which reaps it)
        left = [p for p in seen.values() if p.pid != proc.pid and runs(p)]
        assert not left, 'AFT_SEED=%d: SIGTERM at %.2f s (%d processes then): left running: %s' % (
            SEED, at, nodes, [' '.join(p.cmdline()[:3]) for p in left])
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for p in seen.values():
            try:
                if p.is_running():
                    p.kill()
            except psutil.Error:
                pass
