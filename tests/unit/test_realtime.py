"""RealtimeBurst: a failover's steps under SCHED_FIFO, and nothing else (root here, as in CI)."""
import os
import threading

import pytest

from aft_ftm.realtime import RealtimeBurst


def policy():
    return os.sched_getscheduler(0)


def test_the_block_and_the_threads_it_starts_run_fifo_and_the_caller_returns_to_the_usual_policy():
    burst = RealtimeBurst(7)
    assert burst.check() is None, burst.error
    seen = {}

    def step():
        seen['step'] = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)

    before = policy()
    with burst() as boosted:
        assert boosted
        assert (policy(), os.sched_getparam(0).sched_priority) == (os.SCHED_FIFO, 7)
        thread = threading.Thread(target=step)
        thread.start()
        thread.join()
    assert seen['step'] == (os.SCHED_FIFO, 7)
    assert policy() == before == os.SCHED_OTHER


def test_the_usual_policy_comes_back_when_the_block_raises():
    with pytest.raises(RuntimeError):
        with RealtimeBurst(5)():
            raise RuntimeError('a step failed')
    assert policy() == os.SCHED_OTHER


def test_priority_zero_is_off_and_out_of_range_is_refused_by_name():
    with RealtimeBurst(0)() as boosted:
        assert not boosted and policy() == os.SCHED_OTHER
    for bad in (-1, 100):
        with pytest.raises(ValueError, match='real-time priority %d' % bad):
            RealtimeBurst(bad)


def test_a_refusal_is_remembered_and_the_block_still_runs(monkeypatch):
    def refuse(*args):
        raise PermissionError(1, 'Operation not permitted')
    monkeypatch.setattr(os, 'sched_setscheduler', refuse)
    burst = RealtimeBurst(10)
    assert 'SCHED_FIFO 10 refused' in burst.check()
    ran = []
    with burst() as boosted:
        ran.append(boosted)
    assert ran == [False]
