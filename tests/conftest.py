"""Test set-up: the libraries of every package importable from the source tree, and the shared fakes."""
import fcntl
import glob
import os
import shutil
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
for package in ('aft_ftm', 'aft_service_manager', 'aft_examples', 'aft_bench', 'tjp_sim'):
    sys.path.insert(0, os.path.join(ROOT, 'catkin_ws', 'src', package, 'src'))
sys.path.insert(0, HERE)

# Every temporary directory of a run (the tests', and those of every process they start: deployments'
# logs, ROS homes, rostest nodes') goes in one scratch directory, removed when the run passes and kept,
# named, when it fails. Left in /tmp, they came to 1.4 GB in 3 800 directories over a few days of runs.
SCRATCH = tempfile.mkdtemp(prefix='aft_tests_')
os.environ['TMPDIR'] = SCRATCH
tempfile.tempdir = SCRATCH
STARTED = time.time()


def remove_free_turns(since):
    """The adaptation turns' lock files (aft_ftm.turns, one per ROS master, in /tmp whatever TMPDIR says)
    that this run's masters made: each master's port is new, so a run left dozens. One still held
    (an engine alive) is kept."""
    from aft_ftm.turns import Turn
    for path in glob.glob(os.path.join(Turn.DIRECTORY, 'aft_adaptation_*.lock')):
        try:
            if os.stat(path).st_mtime < since:
                continue
            fd = os.open(path, os.O_RDWR)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.unlink(path)
        except OSError:
            pass
        finally:
            os.close(fd)


def pytest_configure(config):
    config.addinivalue_line('markers', 'family(name, keep): one of a family of live cases of which the short suite '
                                       'runs keep, drawn from AFT_SUITE_SEED (aft_ftm.suite)')


def pytest_report_header(config):
    from aft_ftm import suite
    return 'suite: %s, AFT_SUITE_SEED=%d (the draw of each family\'s cases; AFT_SUITE=full runs them all)' % (
        suite.suite(), suite.seed())


def pytest_collection_modifyitems(config, items):
    """The short suite runs keep cases of each family (@pytest.mark.family(name, keep)): the others are
    skipped, the reason naming the family, the seed and how to run them."""
    import pytest
    from aft_ftm import suite
    families = {}
    for item in items:
        mark = item.get_closest_marker('family')
        if mark is not None:
            families.setdefault(mark.args[0], (mark.args[1], []))[1].append(item)
    which, seed = suite.suite(), suite.seed()
    for family, (keep, members) in families.items():
        chosen = suite.drawn(family, [item.nodeid for item in members], keep, seed, which)
        for item in members:
            if item.nodeid not in chosen:
                item.add_marker(pytest.mark.skip(reason=suite.not_drawn(family, keep, len(members), seed)))


def pytest_sessionfinish(session, exitstatus):
    remove_free_turns(STARTED - 1.0)
    if (exitstatus == 0 or not os.listdir(SCRATCH)) and not os.environ.get('AFT_KEEP_TMP'):
        shutil.rmtree(SCRATCH, ignore_errors=True)
    else:
        session.config.aft_kept = SCRATCH


def pytest_terminal_summary(terminalreporter):
    # (pytest shows its header only without -q: the draw's seed is said here too, at the end)
    terminalreporter.write_line(pytest_report_header(terminalreporter.config))
    kept = getattr(terminalreporter.config, 'aft_kept', None)
    if kept:
        terminalreporter.write_line('logs and temporary files of this run kept in %s' % kept)
    from reporting import FIGURES
    if FIGURES:
        terminalreporter.section('figures reported by the tests')
        for line in FIGURES:
            terminalreporter.write_line(line)
