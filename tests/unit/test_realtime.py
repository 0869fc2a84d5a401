"""RealtimeBurst: a failover step under SCHED_FIFO, and nothing else (root here, as in CI)."""
import os
import threading

import pytest

from aft_ftm.realtime import RealtimeBurst


def policy():
    """The calling thread's policy, without the reset-on-fork flag, and its priority."""
    return os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK, os.sched_getparam(0).sched_priority


def test_the_block_runs_fifo_what_it_starts_does_not_and_the_caller_gets_its_policy_back():
    burst = RealtimeBurst(7)
    assert burst.check() is None, burst.error
    seen = {}

    def started_inside():   # a timer, a thread of a library: it must not keep real-time priority
        seen['thread'] = policy()

    before = policy()
    with burst() as boosted:
        assert boosted
        assert policy() == (os.SCHED_FIFO, 7)
        thread = threading.Thread(target=started_inside)
        thread.start()
        thread.join()
    assert seen['thread'] == (os.SCHED_OTHER, 0)
    assert policy() == before == (os.SCHED_OTHER, 0)


def test_a_thread_already_real_time_gets_its_own_policy_back():
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(3))
    try:
        with RealtimeBurst(9)():
            assert policy() == (os.SCHED_FIFO, 9)
        assert policy() == (os.SCHED_FIFO, 3)
    finally:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def test_the_usual_policy_comes_back_when_the_block_raises():
    with pytest.raises(RuntimeError):
        with RealtimeBurst(5)():
            raise RuntimeError('a step failed')
    assert policy() == (os.SCHED_OTHER, 0)


def test_priority_zero_is_off_and_out_of_range_is_refused_by_name():
    with RealtimeBurst(0)() as boosted:
        assert not boosted and policy() == (os.SCHED_OTHER, 0)
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
