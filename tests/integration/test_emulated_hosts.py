"""Emulated hosts (network namespaces), for real: traffic crosses their links, and each fault does
what it says. Needs root; skipped (with the reason) where namespaces cannot be made.

Peers are plain Python sockets (net_peer.py) started inside the hosts with Hosts.run_in; the test
process itself is in the root namespace and reaches the hosts only through them. Every wait is on a
line a peer prints, with a deadline.
"""
import os
import select
import signal
import subprocess
import sys
import time

import psutil
import pytest

from aft_ftm import hosts_exec
from aft_ftm.hosts_exec import Hosts, PlatformError
from aft_ftm.power_switch import parse_spec
from aft_ftm.power_switch_exec import call_switch
from aft_ftm.sites import pid_gone
from reporting import report

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
PEER = os.path.join(HERE, 'net_peer.py')
HOSTS_CLI = os.path.join(ROOT, 'scripts', 'hosts')
PORT = 7000
BULK = 150000            # bytes: about 1.5 s at 800 kbit/s
LIMIT = 800              # kbit/s


def _platform_or_skip():
    try:
        hosts_exec.check_platform()
    except PlatformError as e:
        pytest.skip(str(e))


class Lines(object):
    """The stdout lines of a process, each read with a deadline."""

    def __init__(self, popen):
        self.popen, self.buffer = popen, b''

    def next(self, timeout=5.0):
        deadline = time.monotonic() + timeout
        while b'\n' not in self.buffer:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError('no line from %s within %g s' % (self.popen.args, timeout))
            ready, _, _ = select.select([self.popen.stdout], [], [], left)
            if ready:
                data = os.read(self.popen.stdout.fileno(), 4096)
                if not data:
                    raise AssertionError('%s ended without a line (exit %s)' % (self.popen.args, self.popen.wait(5)))
                self.buffer += data
        line, self.buffer = self.buffer.split(b'\n', 1)
        return line.decode()

    def rest(self):
        """Every line left, once the process has ended (its stdout at EOF)."""
        while True:
            data = os.read(self.popen.stdout.fileno(), 4096)
            if not data:
                break
            self.buffer += data
        lines, self.buffer = self.buffer.decode().split('\n'), b''
        return [line for line in lines if line]


def peer(hosts, host, *args, stdin=None):
    popen = hosts.run_in(host, [sys.executable, PEER] + [str(a) for a in args], stdout=subprocess.PIPE,
                         stdin=stdin, bufsize=0)
    return popen, Lines(popen)


def once(hosts, host, *args, timeout=10.0):
    """Run a peer to its end; its one line, split."""
    popen, lines = peer(hosts, host, *args)
    try:
        return lines.next(timeout).split()
    finally:
        popen.wait(timeout)


def server(hosts, host):
    popen, lines = peer(hosts, host, 'serve', PORT)
    assert lines.next() == 'ready'
    return popen


def kbits(words):
    assert words[0] == 'sent' and int(words[1]) == BULK, words
    return BULK * 8 / 1000.0 / float(words[2])


def test_traffic_partition_rate_freeze_power_off():
    _platform_or_skip()
    prefix = None
    try:
        with Hosts(['a', 'b', 'c']) as hosts:
            prefix = hosts.topology.prefix
            a, c = hosts.ip('a'), hosts.ip('c')
            assert a != c and a.startswith('10.213.')
            assert os.environ.get('ROS_IP') != a
            shown = hosts.run_in('a', [sys.executable, '-c', 'import os; print(os.environ["ROS_IP"], '
                                       'os.environ["ROS_HOSTNAME"])'], stdout=subprocess.PIPE)
            assert shown.communicate(timeout=10)[0].decode().split() == [a, a]
            server(hosts, 'a')

            # reachable by A's address from B, across the links (the root namespace has no route to it)
            assert once(hosts, 'b', 'probe', a, PORT, 1.0)[0] == 'ok'

            # partition of A: B's connect gives up within its bounded time; healing restores it
            hosts.partition('a')
            started = time.monotonic()
            words = once(hosts, 'b', 'probe', a, PORT, 1.0)
            assert words[0] == 'fail', words
            assert time.monotonic() - started < 5.0
            report('emulated hosts: partitioned host A, connect from B failed (%s) after %s s (connect timeout 1 s)'
                   % (words[1], words[2]))
            hosts.heal('a')
            assert once(hosts, 'b', 'probe', a, PORT, 1.0)[0] == 'ok'

            # pair partition A|C: C no longer reaches A, B still does
            hosts.partition('a', 'c')
            assert once(hosts, 'c', 'probe', a, PORT, 0.5)[0] == 'fail'
            assert once(hosts, 'b', 'probe', a, PORT, 1.0)[0] == 'ok'
            hosts.heal('a', 'c')
            assert once(hosts, 'c', 'probe', a, PORT, 1.0)[0] == 'ok'

            # rate limit of A: a bulk transfer B->A falls to about the limit
            unlimited = kbits(once(hosts, 'b', 'send', a, PORT, BULK))
            hosts.rate('a', LIMIT)
            limited = kbits(once(hosts, 'b', 'send', a, PORT, BULK))
            hosts.unrate('a')
            again = kbits(once(hosts, 'b', 'send', a, PORT, BULK))
            report('emulated hosts: bulk B->A %d kB: %.0f kbit/s unlimited, %.0f kbit/s limited to %d kbit/s, '
                   '%.0f kbit/s after unrate' % (BULK // 1000, unlimited, limited, LIMIT, again))
            assert limited < 0.5 * unlimited
            assert limited < 1.5 * LIMIT
            assert again > 2 * limited

            # freeze of one process for 0.5 s: its ticks stop, then resume
            ticker, ticks = peer(hosts, 'a', 'tick')
            before = [float(ticks.next()) for _ in range(3)]
            freeze = hosts.freeze(ticker.pid, 0.5)
            assert freeze.wait(3.0)
            after = [float(ticks.next()) for _ in range(30)]
            gaps = [y - x for x, y in zip(before[-1:] + after, after)]
            assert max(gaps) >= 0.45, gaps
            assert ticker.poll() is None
            report('emulated hosts: process frozen for 0.5 s, longest gap between its ticks %.3f s' % max(gaps))

            # control: a crash of a server process (not a power loss) is seen at once by its client
            control = server(hosts, 'c')
            holder, held = peer(hosts, 'b', 'hold', c, PORT, stdin=subprocess.PIPE)
            assert held.next() == 'connected'
            control.kill()
            control.wait(5)
            holder.stdin.write(b'recv 2.0\n')
            assert held.next() in ('closed', 'reset')
            holder.kill()

            # power loss of A: B's open connection hears nothing; every process of A is dead, daemons too
            holder, held = peer(hosts, 'b', 'hold', a, PORT, stdin=subprocess.PIPE)
            assert held.next() == 'connected'
            spawner, spawned = peer(hosts, 'a', 'daemon')
            daemon_pid = int(spawned.next())
            started_in_a = [p for p, _ in hosts._started['a']]
            killed = hosts.power_off('a')
            assert daemon_pid in killed and ticker.pid in killed
            holder.stdin.write(b'recv 1.0\n')
            assert held.next() == 'timeout'
            for popen in started_in_a:
                assert popen.poll() is not None, popen.args
            for pid in killed:
                assert pid_gone(pid), pid
            assert hosts.processes('a') == []
            report('emulated hosts: power loss of A killed %d processes; B\'s open connection saw nothing in 1 s'
                   % len(killed))

            # power on: A made again, same address, reachable again
            hosts.power_on('a')
            server(hosts, 'a')
            assert once(hosts, 'b', 'probe', a, PORT, 1.0)[0] == 'ok'

            # the power switch confirms C off once C is cut off and every process of it stopped (what a
            # promotion needs); the kill and the tear-down follow, and C is off for good afterwards
            ticker_c, ticks_c = peer(hosts, 'c', 'tick')
            first = float(ticks_c.next())
            switch = hosts.power_switch()
            outcome = call_switch(parse_spec('unix:' + switch.path), 'c', 10.0)
            answered = time.monotonic()
            assert outcome.confirmed, outcome.detail
            assert 'processes stopped' in outcome.detail, outcome.detail
            assert call_switch(parse_spec('unix:' + switch.path), 'c', 10.0).confirmed   # asked again: off
            assert once(hosts, 'b', 'probe', c, PORT, 0.5)[0] == 'fail'
            assert ticker_c.wait(10) is not None and hosts.state('c') == 'off'
            last = [first] + [float(t) for t in ticks_c.rest()]   # C's ticks: none after the switch's answer
            assert max(last) < answered, (last[-3:], answered)
            report('emulated hosts: the power switch confirmed C off %s' % outcome.detail)
    finally:
        if prefix is not None:
            assert hosts_exec.leftovers(prefix) == []


def test_sigterm_tears_down_and_sigkill_leftovers_are_cleaned():
    _platform_or_skip()
    # As an interactive program: Ctrl-C raises KeyboardInterrupt even where this test runs as a
    # background job (whose children inherit SIGINT ignored, and then keep ignoring it).
    code = ('import signal, sys, time\n'
            'signal.signal(signal.SIGINT, signal.default_int_handler)\n'
            'from aft_ftm.hosts_exec import Hosts\n'
            'with Hosts(["x", "y"]) as hosts:\n'
            '    hosts.run_in("x", ["sleep", "30"])\n'
            '    print(hosts.topology.prefix, flush=True)\n'
            '    time.sleep(30)\n')
    for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGKILL):
        child = subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.PIPE, bufsize=0)
        try:
            prefix = Lines(child).next(10.0)
            assert hosts_exec.leftovers(prefix)
            child.send_signal(signum)
            try:
                child.wait(30)    # the tear-down runs ip commands: seconds on a loaded machine
            except subprocess.TimeoutExpired:
                raise AssertionError('the owner of hosts %s did not end within 30 s of %s'
                                     % (prefix, signal.Signals(signum).name))
        finally:
            child.kill()
        if signum == signal.SIGKILL:
            assert hosts_exec.leftovers(prefix), 'a run killed by SIGKILL cannot clean up: its leftovers stay'
            removed = hosts_exec.cleanup_leftovers()
            assert prefix + '-x' in removed
        assert hosts_exec.leftovers(prefix) == [], signal.Signals(signum).name


def cli(*args, user=None):
    argv = [sys.executable, HOSTS_CLI] + list(args)
    if user is not None:
        argv = ['setpriv', '--reuid=%d' % user, '--regid=%d' % user, '--clear-groups'] + argv
    done = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=30)
    return done.returncode, done.stdout.decode()


def test_cli_up_fault_down():
    _platform_or_skip()
    rc, text = cli('up', '--hosts', 'p,q')
    try:
        assert rc == 0, text
        prefix = text.split()[1].rstrip(',')
        assert cli('up')[0] == 2                                       # already up: refused
        rc, text = cli('fault', 'partition', 'nosuch')
        assert (rc, 'unknown host \'nosuch\'') == (2, text.strip().split(': ', 1)[1][:21]), text
        assert cli('fault', 'rate', 'fast', 'p')[0] == 2
        assert cli('fault', 'rate', '800', 'p')[0] == 0
        assert cli('fault', 'partition', 'q')[0] == 0
        rc, text = cli('status')
        assert 'rate 800 kbit/s' in text and 'partitioned' in text, text
        rc, text = cli('status', user=65534)
        assert rc == 2 and 'need root' in text, text
    finally:
        rc, text = cli('down')
    assert rc == 0, text
    assert hosts_exec.leftovers(prefix) == []


SINK = ('import sys\nfrom aft_ftm.link_probe import Sink\n'
        'sink = Sink(sys.argv[1], 0).start()\nprint(sink.endpoint[1], flush=True)\nsys.stdin.read()\n')
PROBE = ('import sys\nfrom aft_ftm.link_probe import probe, rate\n'
         'print(rate(*probe((sys.argv[1], int(sys.argv[2])), 0.3)), flush=True)\n')


def test_the_link_monitor_probe_measures_a_rate_limit_across_hosts():
    """The figure the monitor adapts on (aft_ftm.link_probe) follows a real limit of the link: far above
    Table I's high bandwidth (1 MB/s) unlimited, about the limit (100 kB/s) once limited."""
    _platform_or_skip()
    with Hosts(['a', 'b']) as hosts:
        sink = hosts.run_in('a', [sys.executable, '-c', SINK, hosts.ip('a')], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, bufsize=0)
        port = int(Lines(sink).next())

        def measure():
            popen = hosts.run_in('b', [sys.executable, '-c', PROBE, hosts.ip('a'), str(port)], stdout=subprocess.PIPE)
            return float(popen.communicate(timeout=20)[0].decode().strip())
        unlimited = measure()
        hosts.rate('a', LIMIT)
        limited = [measure() for _ in range(3)]
        hosts.unrate('a')
        report('link probe across hosts: %.0f kB/s unlimited, %s kB/s limited to %d kbit/s (%.0f kB/s)'
               % (unlimited / 1e3, ', '.join('%.0f' % (x / 1e3) for x in limited), LIMIT, LIMIT / 8.0))
        assert unlimited > 1e6
        median = sorted(limited)[1]
        assert 0.5 * LIMIT * 125 < median < 1.5 * LIMIT * 125, limited


def test_a_command_is_started_on_the_host_of_a_process():
    """What the Adaptation Engine uses to start a site's new nodes next to its running ones
    (aft_ftm.where.run_where): in the process's network namespace, with its ROS addresses."""
    from aft_ftm.where import run_where
    _platform_or_skip()
    here, env = run_where(os.getpid(), ['true'], {'ROS_IP': 'keep'})
    assert (here, env['ROS_IP']) == (['true'], 'keep')
    with Hosts(['a']) as hosts:
        sleeper = hosts.run_in('a', ['sleep', '60'])
        pid = sleeper.pid
        assert wait_for_child(pid, 'sleep'), 'no sleep process in host a'
        target = next(p for p in [psutil.Process(pid)] + psutil.Process(pid).children(recursive=True)
                      if p.name() == 'sleep').pid
        argv, env = run_where(target, [sys.executable, '-c', 'import os, socket; s = socket.socket(); '
                                       's.bind((os.environ["ROS_IP"], 0)); print(os.environ["ROS_IP"])'],
                              {'ROS_IP': '127.0.0.1', 'ROS_MASTER_URI': 'http://127.0.0.1:1'})
        assert argv[0] == 'nsenter'
        done = subprocess.run(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, timeout=20)
        # It could bind the host's own address: it runs in that host.
        assert done.stdout.decode().strip() == hosts.ip('a'), done.stderr.decode()
        # the host's own ROS addresses, not this process's
        assert env['ROS_MASTER_URI'] == psutil.Process(target).environ().get('ROS_MASTER_URI') != 'http://127.0.0.1:1'


def wait_for_child(pid, name, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            procs = [psutil.Process(pid)] + psutil.Process(pid).children(recursive=True)
        except psutil.NoSuchProcess:
            return False
        if any(p.name() == name for p in procs):
            return True
        time.sleep(0.02)
    return False
