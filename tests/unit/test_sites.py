"""Power-off of a site's whole process tree, with real processes (no ROS)."""
import os
import subprocess
import sys
import time

import psutil

from aft_ftm.sites import Site, power_off, process_tree

# A parent whose children start their own sessions, as roslaunch's nodes do.
TREE = ('import os, subprocess, sys, time\n'
        'for _ in range(3):\n'
        '    subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], start_new_session=True)\n'
        'print("ready", flush=True)\n'
        'time.sleep(60)\n')


def start_tree():
    site = Site('t', [sys.executable, '-c', TREE])
    site.proc = subprocess.Popen(site.argv, stdout=subprocess.PIPE, start_new_session=True)
    assert site.proc.stdout.readline().strip() == b'ready'
    return site


def test_power_off_kills_every_process_of_the_site_even_in_other_sessions():
    site = start_tree()
    try:
        pids = [p.pid for p in process_tree(site.pid)]
        assert len(pids) == 4
        assert len({os.getsid(p) for p in pids}) == 4
        assert site.power_off() == 4
        time.sleep(0.05)
        assert not [p for p in pids if psutil.pid_exists(p) and psutil.Process(p).status() != 'zombie']
    finally:
        site.stop(grace=1)


def test_stop_never_raises_and_leaves_nothing():
    site = start_tree()
    pids = [p.pid for p in process_tree(site.pid)]
    site.stop(grace=1)
    site.stop(grace=1)
    assert not [p for p in pids if psutil.pid_exists(p) and psutil.Process(p).status() != 'zombie']


def test_power_off_of_a_missing_process_is_a_no_op():
    proc = subprocess.Popen([sys.executable, '-c', 'pass'])
    proc.wait()
    assert power_off(proc.pid) == 0
