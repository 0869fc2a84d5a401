"""The programs ``on_failure: run`` starts (aft_service_manager.programs), with real processes and no
ROS: a program that exits non-zero, cannot start, or hangs past its ``program_timeout`` is reported
as failed, a hung one is killed with every process of its session, and none outlives the manager.
Before (review of session 36) they were started and forgotten: never reaped, never bounded, their
failures unsaid."""
import os
import time

import psutil
import pytest

from aft_service_manager.programs import Programs
from aft_service_manager.services import ServiceConfigError, parse_config


def ended(programs, timeout=10.0):
    """check() until nothing runs (bounded); returns every outcome."""
    outcomes, deadline = [], time.monotonic() + timeout
    while programs.running and time.monotonic() < deadline:
        outcomes += programs.check(time.monotonic())
        time.sleep(0.01)
    assert not programs.running
    return outcomes


def test_a_program_that_runs_through_is_logged_and_one_that_exits_non_zero_is_a_failure():
    programs = Programs()
    assert programs.start('a', 'exit', ['sh', '-c', 'exit 0'], dict(os.environ), time.monotonic(), 5.0) is None
    assert programs.start('b', 'hang', ['sh', '-c', 'exit 3'], dict(os.environ), time.monotonic(), 5.0) is None
    outcomes = {o.service: o for o in ended(programs)}
    assert not outcomes['a'].failed and 'ran' in outcomes['a'].detail
    assert outcomes['b'].failed and outcomes['b'].fault == 'hang' and 'exited with status 3' in outcomes['b'].detail
    assert (programs.started, programs.failed, programs.timed_out) == (2, 1, 0)


def test_a_program_that_cannot_start_is_a_failure_said_at_once():
    programs = Programs()
    outcome = programs.start('a', 'exit', ['/nonexistent/notify'], dict(os.environ), 0.0, 5.0)
    assert outcome.failed and 'could not start' in outcome.detail and programs.running == []


def test_a_program_past_its_timeout_is_killed_with_every_process_it_started_and_reaped_later():
    programs = Programs()
    start = time.monotonic()
    programs.start('a', 'memory', ['sh', '-c', 'sleep 60 & sleep 60; wait'], dict(os.environ), start, 0.3)
    time.sleep(0.2)
    leader = psutil.Process(programs.running[0].popen.pid)
    family = [leader] + leader.children(recursive=True)
    assert len(family) >= 2 and programs.check(time.monotonic()) == []      # within its time: nothing to say
    assert programs.next_deadline() == pytest.approx(start + 0.3)
    time.sleep(0.15)
    [outcome] = programs.check(time.monotonic())
    assert outcome.failed and 'still running after' in outcome.detail and programs.timed_out == 1
    gone, alive = psutil.wait_procs(family, timeout=5.0)
    assert not alive, 'left running: %s' % alive
    assert ended(programs) == [] and programs.next_deadline() is None        # reaped, said once


def test_the_programs_still_running_end_with_the_manager():
    programs = Programs()
    programs.start('a', 'exit', ['sleep', '60'], dict(os.environ), time.monotonic(), 30.0)
    proc = psutil.Process(programs.running[0].popen.pid)
    assert programs.end_all() == 1 and programs.running == []
    assert proc.wait(5.0) is not None or not proc.is_running()


def test_program_timeout_is_read_and_a_bad_one_refused():
    conf = parse_config('services:\n  a: {command: x, on_failure: run, program: [notify]}\n')
    assert conf['services']['a']['program_timeout'] == 30.0
    with pytest.raises(ServiceConfigError, match='program_timeout must be a finite number > 0'):
        parse_config('services:\n  a: {command: x, on_failure: run, program: [notify], program_timeout: 0}\n')
