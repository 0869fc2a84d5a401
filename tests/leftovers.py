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
