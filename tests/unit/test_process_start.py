"""aft_ftm.process_start: a process's start on the boot clock, the identity every process agrees on
whatever the wall clock does (psutil's create_time moves with a clock step). Real processes, and a
fake /proc for the odd command names. No ROS."""
import os
import subprocess
import sys

import psutil

from aft_ftm.process_start import CLOCK_TICKS, started


def test_a_process_start_is_the_kernel_s_clock_ticks_since_boot():
    me = started(os.getpid())
    assert me is not None and me > 0 and abs(me * CLOCK_TICKS - round(me * CLOCK_TICKS)) < 1e-6   # whole ticks
    # psutil's create_time is its boot time plus the same ticks. Its boot time is the kernel's btime,
    # derived from the wall clock and read again on each psutil.boot_time() call: a clock stepped
    # between two reads (CI, session 40: 11 s apart within one test) moves it. So the check takes the
    # one boot time psutil cached and added, not a second read.
    import psutil._pslinux as pslinux
    psutil.boot_time()                                   # read and cached once
    off = psutil.Process(os.getpid()).create_time() - pslinux.BOOT_TIME - me
    assert abs(off) < 1e-3, off
    child = subprocess.Popen([sys.executable, '-c', 'import sys; sys.stdin.read()'], stdin=subprocess.PIPE)
    try:
        assert started(child.pid) >= me                       # started later
        assert started(child.pid) == started(child.pid)       # asked again: the same, exactly
    finally:
        child.stdin.close()
        child.wait(10)
    assert started(child.pid) is None                        # gone


def test_a_zombie_has_a_start_only_when_asked_for_it():
    child = subprocess.Popen([sys.executable, '-c', 'pass'])
    import time
    for _ in range(200):   # exited, not reaped yet: a zombie
        if psutil.Process(child.pid).status() == psutil.STATUS_ZOMBIE:
            break
        time.sleep(0.01)
    try:
        assert started(child.pid) is None and started(child.pid, zombie=True) > 0
    finally:
        child.wait(10)


def test_a_command_name_with_brackets_and_spaces_does_not_shift_the_fields(tmp_path):
    """The name in /proc/PID/stat is in brackets and may hold anything, brackets and spaces too."""
    (tmp_path / '77').mkdir()
    fields = ['S', '1', '77', '77', '0', '-1', '4194560'] + ['0'] * 12 + ['123456'] + ['0'] * 30
    (tmp_path / '77' / 'stat').write_bytes(b'77 (a) b) c (d) ' + ' '.join(fields).encode())
    assert started(77, proc=str(tmp_path)) == 123456 / CLOCK_TICKS
    fields[0] = 'Z'
    (tmp_path / '77' / 'stat').write_bytes(b'77 (x) ' + ' '.join(fields).encode())
    assert started(77, proc=str(tmp_path)) is None and started(77, zombie=True, proc=str(tmp_path)) == 123456 / CLOCK_TICKS


def test_a_wall_clock_step_moves_psutil_s_create_time_but_not_a_site_s_incarnation(monkeypatch):
    """The boot time psutil adds is the kernel's btime, which a clock step moves; each process reads it
    once. Two processes of one site on either side of a step (Recovery, an After started later) told
    the witness two incarnations, and the one that differed was "not the one serving"."""
    import psutil._pslinux as pslinux
    from aft_ftm.ros.witness_client import incarnation
    psutil.boot_time()                                   # cached: the one create_time adds
    before, mine = psutil.Process().create_time(), incarnation(os.getpid())
    monkeypatch.setattr(pslinux, 'BOOT_TIME', pslinux.BOOT_TIME + 3600.0)   # the clock stepped an hour
    assert abs(psutil.Process().create_time() - before - 3600.0) < 1.0
    assert incarnation(os.getpid()) == mine and mine.startswith('%d@' % os.getpid())


def test_a_launcher_started_again_after_a_reboot_with_the_same_pid_and_time_is_another_incarnation(monkeypatch):
    """Review of session 35: an incarnation was the launcher's pid and its start on the boot clock. A
    machine booting the same way again (systemd starting the launch with the same pid in the same
    10 ms) was the same incarnation for the witness, and a lone primary started again blank was told to
    serve. The boot's id is part of it now."""
    from aft_ftm.ros import witness_client
    monkeypatch.setattr(witness_client, 'started', lambda pid, zombie=False: 12.34)
    monkeypatch.setattr(witness_client, 'boot_id', lambda: '1d2c3b4a-0000-4000-8000-000000000001')
    first = witness_client.incarnation(4242)
    monkeypatch.setattr(witness_client, 'boot_id', lambda: '9f8e7d6c-0000-4000-8000-000000000002')
    assert witness_client.incarnation(4242) != first and first == '4242@12.34@1d2c3b4a'
    monkeypatch.undo()
    assert len(witness_client.boot_id()) == 36   # this machine's, as the kernel gives it
