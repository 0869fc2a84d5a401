"""Test set-up: the libraries of every package importable from the source tree, and the shared fakes."""
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
for package in ('aft_ftm', 'aft_service_manager', 'aft_examples', 'aft_bench', 'tjp_sim'):
    sys.path.insert(0, os.path.join(ROOT, 'catkin_ws', 'src', package, 'src'))
sys.path.insert(0, HERE)


def pytest_terminal_summary(terminalreporter):
    from reporting import FIGURES
    if FIGURES:
        terminalreporter.section('figures reported by the tests')
        for line in FIGURES:
            terminalreporter.write_line(line)
