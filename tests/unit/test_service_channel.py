"""The service manager's local channel (aft_service_manager.channel) with real processes, no ROS:
beats through a shared slot, what wakes the manager through its socket with the sender's pid
stamped by the kernel, and a warm spare held until its promotion."""
import os
import signal
import struct
import subprocess
import sys
import time

from aft_service_manager import channel


def test_a_beat_is_seen_in_the_slot_with_its_time_and_status(tmp_path):
    path = channel.slot_path(str(tmp_path), 'c4g')
    reader = channel.BeatSlot(path, create=True)
    assert reader.read() is None                          # no beat yet
    writer = channel.BeatSlot(path)
    before = time.monotonic()
    writer.write()
    beats, at, status = reader.read()
    assert (beats, status) == (1, 'ok') and before <= at <= time.monotonic()
    writer.write('error')
    assert reader.read()[0::2] == (2, 'error')
    assert os.stat(path).st_mode & 0o777 == 0o600


def test_a_beat_caught_half_written_is_not_taken(tmp_path):
    path = channel.slot_path(str(tmp_path), 'a')
    reader = channel.BeatSlot(path, create=True)
    channel.BeatSlot(path).write()
    struct.pack_into('<Q', reader.map, 0, 3)             # a writer stopped mid-beat: the count is odd
    assert reader.read() is None


def test_a_file_that_is_no_slot_is_refused(tmp_path):
    path = tmp_path / 'short.beat'
    path.write_bytes(b'12')
    try:
        channel.BeatSlot(str(path))
    except ValueError as e:
        assert 'not a beat slot' in str(e)
    else:
        raise AssertionError('a 2-byte file was taken as a slot')


SERVICE = r'''
import os, sys, time
from aft_service_manager.channel import ServiceEnd
end = ServiceEnd.from_environment('c4g')
if os.environ.get('AFT_SPARE') == '1':
    print('promoted' if end.wait_promoted(10.0) else 'never promoted', flush=True)
end.beat()
end.beat()
end.beat('error', 'joint limit')
time.sleep(0.2)
'''


def run_service(tmp_path, manager, spare=False):
    slot = channel.BeatSlot(channel.slot_path(str(tmp_path), 'c4g.1'), create=True)
    env = dict(os.environ, AFT_BEAT_FILE=slot.path, AFT_MANAGER_SOCKET=manager.address())
    if spare:
        env['AFT_SPARE'] = '1'
    return slot, subprocess.Popen([sys.executable, '-c', SERVICE], env=env, stdout=subprocess.PIPE,
                                  universal_newlines=True)


def wait_for(manager, count, timeout=10.0):
    got, deadline = [], time.monotonic() + timeout
    while len(got) < count and time.monotonic() < deadline:
        got += manager.receive()
        time.sleep(0.005)
    return got


def test_what_must_wake_the_manager_comes_with_the_senders_pid(tmp_path):
    manager = channel.ManagerSocket(channel.socket_path(str(tmp_path), 'manager_sm'))
    try:
        slot, proc = run_service(tmp_path, manager)
        said = wait_for(manager, 2)
        proc.wait(10)
        # the first beat and the error woke it; the second ok beat did not (the slot has it)
        assert said == [(proc.pid, 'started c4g '), (proc.pid, 'error c4g joint limit')]
        assert slot.read()[0::2] == (3, 'error')
        assert [channel.parse(t) for _, t in said] == [('started', 'c4g', ''), ('error', 'c4g', 'joint limit')]
        assert channel.parse('promote c4g') is None and channel.parse('ok') is None
    finally:
        manager.close()
    assert not os.path.exists(manager.path)


def test_a_long_state_directory_puts_the_socket_in_the_abstract_namespace(tmp_path):
    deep = tmp_path / ('d' * 90)
    deep.mkdir()
    address = channel.socket_path(str(deep), 'manager_sm')
    assert address.startswith('\0')
    manager = channel.ManagerSocket(address)
    try:
        _, proc = run_service(tmp_path, manager)
        said = wait_for(manager, 2)
        proc.wait(10)
        assert [t for _, t in said] == ['started c4g ', 'error c4g joint limit'] and said[0][0] == proc.pid
    finally:
        manager.close()


def test_a_warm_spare_says_it_is_ready_and_does_nothing_until_promoted(tmp_path):
    manager = channel.ManagerSocket(channel.socket_path(str(tmp_path), 'manager_sm'))
    try:
        slot, proc = run_service(tmp_path, manager, spare=True)
        assert wait_for(manager, 1) == [(proc.pid, 'ready c4g ')]
        time.sleep(0.3)
        assert slot.read() is None and manager.receive() == []   # idle: no beat, nothing said
        promoted = time.monotonic()
        os.kill(proc.pid, signal.SIGUSR1)
        said = wait_for(manager, 1)
        assert said[0] == (proc.pid, 'started c4g ')
        assert time.monotonic() - promoted < 1.0
        out, _ = proc.communicate(timeout=10)
        assert out.strip() == 'promoted'
    finally:
        manager.close()


def test_without_a_channel_in_its_environment_a_service_has_none(tmp_path):
    assert channel.ServiceEnd.from_environment('a', {}) is None
    assert channel.ServiceEnd.from_environment('a', {'AFT_BEAT_FILE': str(tmp_path / 'x')}) is None


def test_the_watchdog_fires_only_when_the_beats_stop(tmp_path):
    """The kernel watches the beats: each re-arms the timer; it fires (its descriptor readable) only
    a timeout after the last one, so a healthy service never wakes the manager."""
    import select
    watchdog = channel.Watchdog()
    try:
        slot = channel.BeatSlot(channel.slot_path(str(tmp_path), 'a'), create=True)
        end = channel.ServiceEnd('a', slot.path, '/nonexistent.sock', watchdog=(channel.Watchdog(watchdog.fd), 0.1))
        started = time.monotonic()
        while time.monotonic() - started < 0.5:           # beats every 20 ms for 0.5 s: never fires
            end.beat()
            stopped = time.monotonic()                    # the last beat
            assert not select.select([watchdog], [], [], 0.02)[0]
        assert not watchdog.fired()
        assert select.select([watchdog], [], [], 2.0)[0]  # the beats stop: it fires a timeout later
        assert 0.09 <= time.monotonic() - stopped < 1.0
        assert watchdog.fired() and not watchdog.fired()  # read once, then cleared
        watchdog.arm(0)                                    # disarmed: never fires
        assert not select.select([watchdog], [], [], 0.2)[0]
    finally:
        watchdog.close()


def test_the_manager_sees_whether_a_service_armed_its_watchdog(tmp_path):
    """A service that did not inherit the watchdog (roslaunch closes descriptors) beats into its slot
    but never arms it: the manager, seeing it unarmed, keeps the heartbeat deadline itself."""
    watchdog = channel.Watchdog()
    try:
        assert not watchdog.armed()                            # never armed: nothing would wake the manager
        slot = channel.BeatSlot(channel.slot_path(str(tmp_path), 'a'), create=True)
        channel.ServiceEnd('a', slot.path, '/nonexistent.sock').beat()   # beats without the watchdog
        assert slot.read() is not None and not watchdog.armed()
        channel.ServiceEnd('a', slot.path, '/nonexistent.sock', watchdog=(channel.Watchdog(watchdog.fd), 0.05)).beat()
        assert watchdog.armed()                                # armed by the service's beat, through its descriptor
        time.sleep(0.1)
        assert not watchdog.armed() and watchdog.fired()       # fired: the kernel woke (would wake) the manager
    finally:
        watchdog.close()


def test_a_spare_is_promoted_by_the_managers_byte_and_never_by_the_managers_death(tmp_path):
    """The promotion pipe: a byte promotes the spare at once. Its end closing (the manager died,
    nothing was written) is no promotion: the spare stays idle, for the next manager to adopt it and
    promote it by SIGUSR1, rather than run beside the active instance."""
    manager = channel.ManagerSocket(channel.socket_path(str(tmp_path), 'manager_sm'))
    try:
        for died in (False, True):
            slot = channel.BeatSlot(channel.slot_path(str(tmp_path), 'c4g.%d' % died), create=True)
            r, w = os.pipe()
            env = dict(os.environ, AFT_BEAT_FILE=slot.path, AFT_MANAGER_SOCKET=manager.address(), AFT_SPARE='1',
                       AFT_PROMOTE_FD=str(r))
            proc = subprocess.Popen([sys.executable, '-c', SERVICE], env=env, stdout=subprocess.PIPE,
                                    universal_newlines=True, pass_fds=(r,))
            os.close(r)
            assert wait_for(manager, 1) == [(proc.pid, 'ready c4g ')]
            if not died:
                os.write(w, b'p')
                os.close(w)
            else:
                os.close(w)                                   # the manager is gone
                time.sleep(0.6)
                assert slot.read() is None and proc.poll() is None, 'promoted by its manager\'s death'
                os.kill(proc.pid, signal.SIGUSR1)             # the next manager, which adopted it
            assert wait_for(manager, 2)[0] == (proc.pid, 'started c4g ')
            out, _ = proc.communicate(timeout=10)
            assert out.strip() == 'promoted'
    finally:
        manager.close()


def test_a_stalled_manager_never_blocks_a_services_beat_and_no_change_of_status_is_lost(tmp_path):
    """The manager's socket holds a few datagrams; a manager stopped (SIGSTOP, busy) with it full
    blocked the service in its beat, its own cycle with it (review of stop 39)."""
    import socket
    path = str(tmp_path / 'stalled.sock')
    manager = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    manager.bind(path)                                 # never read while "stopped"
    try:
        slot = channel.BeatSlot(channel.slot_path(str(tmp_path), 'a'), create=True)
        end = channel.ServiceEnd('a', slot.path, path)
        import threading

        def beats():
            for i in range(200):                       # a change of status at every beat
                end.beat('error' if i % 2 else 'ok', 'x')
        cycle = threading.Thread(target=beats, daemon=True)
        cycle.start()
        cycle.join(5.0)
        assert not cycle.is_alive(), 'the service blocked in its beat'   # for ever before, at about the 11th
        said = []
        manager.setblocking(False)
        while True:                                    # the manager runs again and reads its queue
            try:
                said.append(manager.recv(4096).decode())
            except BlockingIOError:
                break
        assert said and len(said) < 200                # what did not fit was not sent...
        end.beat('error', 'x')                         # the status of the last beat above, which did not fit
        last = []
        while True:
            try:
                last.append(manager.recv(4096).decode())
            except BlockingIOError:
                break
        assert last == ['error a x']                   # ...the latest status is told once there is room
    finally:
        manager.close()
