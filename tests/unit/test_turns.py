"""Two Adaptation Engines take turns (aft_ftm.turns): real flocks, threads and a process, no ROS."""
import signal
import subprocess
import sys
import threading
import time

import pytest

from aft_ftm.turns import Busy, Turn


def test_a_second_engine_waits_for_the_first_and_goes_once_it_is_done(tmp_path):
    first, second = Turn('http://m:11311', str(tmp_path)), Turn('http://m:11311', str(tmp_path))
    assert first.take('engine A running switch', 1.0) < 0.5
    said, got = [], {}

    def wait():
        got['waited'] = second.take('engine B running compose', 10.0, waiting=said.append)
    thread = threading.Thread(target=wait)
    thread.start()
    time.sleep(0.3)
    assert thread.is_alive() and said and 'engine A running switch' in said[0], said
    first.give()
    thread.join(5.0)
    assert not thread.is_alive() and got['waited'] >= 0.3
    assert 'engine B running compose' in first.holder()
    second.give()


def test_an_engine_that_waits_too_long_or_is_interrupted_is_told_who_holds_the_turn(tmp_path):
    first, second = Turn('http://m:11311', str(tmp_path)), Turn('http://m:11311', str(tmp_path))
    first.take('pid 1 /monitor running switch', 1.0)
    with pytest.raises(Busy, match='held the turn for 0 s and still does: pid 1 /monitor running switch'):
        second.take('pid 2', 0.2)
    with pytest.raises(Busy, match='SIGINT while waiting'):
        second.take('pid 2', 30.0, stop=lambda: 'SIGINT')
    assert Turn('http://other:11311', str(tmp_path)).take('another master', 0.1) < 0.1   # not the same turn
    first.give()


def test_a_killed_holder_never_keeps_the_turn(tmp_path):
    holder = subprocess.Popen([sys.executable, '-c', 'import sys, time\nsys.path[:0] = %r\n'
                               'from aft_ftm.turns import Turn\nTurn("http://m:11311", %r).take("killed", 1.0)\n'
                               'print("held", flush=True)\ntime.sleep(60)\n' % (sys.path, str(tmp_path))],
                              stdout=subprocess.PIPE)
    try:
        assert holder.stdout.readline().strip() == b'held'
        turn = Turn('http://m:11311', str(tmp_path))
        with pytest.raises(Busy):
            turn.take('me', 0.2)
        holder.send_signal(signal.SIGKILL)
        holder.wait(10)
        assert turn.take('me', 5.0) < 5.0
        turn.give()
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait(10)


def test_one_master_is_one_turn_however_its_uri_is_spelt(tmp_path):
    from aft_ftm.turns import master_key
    assert master_key('http://localhost:11311/') == master_key('http://127.0.0.1:11311') == \
        master_key('http://LOCALHOST:11311')
    assert master_key('http://127.0.0.1:11312') != master_key('http://127.0.0.1:11311')
    first = Turn('http://localhost:11311/', str(tmp_path))
    first.take('A', 1.0)
    with pytest.raises(Busy):
        Turn('http://127.0.0.1:11311', str(tmp_path)).take('B', 0.1)
    first.give()


def test_a_turn_that_cannot_be_taken_is_refused_naming_why(tmp_path):
    (tmp_path / 'ro').mkdir(mode=0o500)
    turn = Turn('http://m:11311', str(tmp_path / 'ro'))
    import os
    if os.geteuid() == 0:   # root writes anywhere: a path under a file instead
        (tmp_path / 'file').write_text('x')
        turn = Turn('http://m:11311', str(tmp_path / 'file'))
    with pytest.raises(Busy, match='cannot take the adaptation turn'):
        turn.take('me', 0.1)
