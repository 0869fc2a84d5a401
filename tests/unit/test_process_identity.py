"""aft_ftm.process_identity: a pid learned over XML-RPC is signalled only if the kernel says that process
is the node (it listens on the URI's port, in its own network name space; its command line and
environment give it the node's name space and name). Real processes, no ROS master."""
import os
import shutil
import subprocess
import sys
import time

import pytest
from aft_ftm.process_identity import listening_ports, node_names_of, node_process_problem

LISTENER = r'''
import os, socket, sys, time
bind = os.environ.get('BIND', '127.0.0.1')
s = socket.socket(socket.AF_INET6 if ':' in bind else socket.AF_INET)
s.bind((bind, int(os.environ.get('PORT', 0))))
s.listen(1)
print(s.getsockname()[1], flush=True)
time.sleep(60)
'''


def _start(argv_tail=(), env=None, prefix=()):
    command = list(prefix) if prefix and prefix[0] == sys.executable else list(prefix) + [sys.executable, '-c', LISTENER]
    proc = subprocess.Popen(command + list(argv_tail), stdout=subprocess.PIPE, env=dict(os.environ, **(env or {})))
    port = int(proc.stdout.readline())
    return proc, port


@pytest.fixture
def started():
    procs = []

    def start(*args, **kwargs):
        proc, port = _start(*args, **kwargs)
        procs.append(proc)
        return proc, port
    yield start
    for proc in procs:
        proc.kill()
        proc.wait()


@pytest.mark.parametrize('argv, env, expected', [
    ([], {}, ('/', None)),
    ([], {'ROS_NAMESPACE': 'slave'}, ('/slave/', None)),
    (['__name:=after'], {'ROS_NAMESPACE': '/slave'}, ('/slave/', '/slave/after')),
    (['__ns:=/master', '__name:=after'], {'ROS_NAMESPACE': '/slave'}, ('/master/', '/master/after')),
    (['__name:=/elsewhere/x'], {'ROS_NAMESPACE': '/slave'}, ('/slave/', '/elsewhere/x')),
    (['__name:=a', '__name:=b'], {}, ('/', '/b')),   # the last remapping wins, as in rospy
])
def test_the_name_a_process_takes_is_read_as_rospy_reads_it(argv, env, expected):
    assert node_names_of(['python3', 'node'] + argv, env) == expected


def test_a_node_process_passes(started):
    proc, port = started(['__name:=after', '__log:=/tmp/x.log'], {'ROS_NAMESPACE': '/slave/'})
    assert port in listening_ports(proc.pid)
    assert node_process_problem(proc.pid, '/slave/after', 'http://127.0.0.1:%d/' % port) is None
    assert node_process_problem(proc.pid, '/slave/after', 'http://localhost:%d' % port) is None
    # __name remapped: rospy turns anonymity off, so the name is whole (no suffix passes)
    assert node_process_problem(proc.pid, '/slave/after_v2', 'http://127.0.0.1:%d/' % port) == \
        'process %d runs node /slave/after, not /slave/after_v2' % proc.pid


def test_a_process_named_by_a_forged_registration_is_refused(started):
    proc, port = started(['__name:=witness'], {'ROS_NAMESPACE': '/'})
    uri = 'http://127.0.0.1:%d/' % port
    # another port: a forged XML-RPC server answering this pid
    why = node_process_problem(proc.pid, '/witness', 'http://127.0.0.1:%d/' % (port + 1 if port < 65535 else 1))
    assert 'does not listen on 127.0.0.1 port' in why and str(proc.pid) in why
    # its own port, but registered under a name of the fenced site: the process runs another node
    why = node_process_problem(proc.pid, '/slave/evil', uri)
    assert why == 'process %d runs node /witness, not /slave/evil' % proc.pid
    # pid 1, gone pids, nonsense
    assert node_process_problem(1, '/slave/evil', uri).startswith('process 1 ')
    assert 'cannot be read' in node_process_problem(2 ** 22 + 12345, '/slave/evil', uri)
    assert 'no process' in node_process_problem(0, '/slave/evil', uri)
    assert 'cannot be read' in node_process_problem('x', '/slave/evil', uri)
    assert 'names no host and port' in node_process_problem(proc.pid, '/slave/evil', 'http://127.0.0.1/')
    # the same port on another loopback address: a forged server there is not this process
    assert 'does not listen on 127.0.0.2 port' in node_process_problem(proc.pid, '/witness',
                                                                        'http://127.0.0.2:%d/' % port)
    # the asking process itself
    assert 'is the process asking' in node_process_problem(os.getpid(), '/witness', uri)


def test_a_ros_master_or_roslaunch_is_never_taken_for_a_node(started, tmp_path):
    """No __name:=, root name space: only the program says it is no node (a registration of a name to
    retire at the master's address would have the master signalled)."""
    master = tmp_path / 'rosmaster'
    master.write_text(LISTENER)
    proc, port = started(prefix=[sys.executable, str(master)], argv_tail=['--core'])
    why = node_process_problem(proc.pid, '/proceed', 'http://127.0.0.1:%d/' % port)
    assert why is not None and 'no node' in why and 'rosmaster' in why


def test_without_a_name_remapping_the_name_space_must_be_the_nodes(started):
    proc, port = started([], {'ROS_NAMESPACE': '/slave'})
    uri = 'http://127.0.0.1:%d/' % port
    assert node_process_problem(proc.pid, '/slave/anything', uri) is None
    why = node_process_problem(proc.pid, '/master/protocol', uri)
    assert why == 'process %d runs in name space /slave/, not in /master/protocol\'s (/master/)' % proc.pid


@pytest.mark.skipif(os.geteuid() != 0 or not shutil.which('unshare'), reason='a network name space needs root')
def test_a_process_in_another_network_name_space_is_seen_in_its_own(started):
    """An emulated host's node listens in its own name space: /proc/PID/net/tcp is read for that process
    (psutil reads only the caller's name space and would not find the socket)."""
    proc, port = started(['__name:=after'], {'ROS_NAMESPACE': '/slave', 'BIND': '0.0.0.0'},
                         prefix=['unshare', '--net', '--'])
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and os.readlink('/proc/%d/ns/net' % proc.pid) == os.readlink('/proc/self/ns/net'):
        time.sleep(0.01)   # unshare execs python3 once the name space is made
    assert os.readlink('/proc/%d/ns/net' % proc.pid) != os.readlink('/proc/self/ns/net')
    assert port in listening_ports(proc.pid)
    assert node_process_problem(proc.pid, '/slave/after', 'http://10.0.0.1:%d/' % port) is None
    import psutil
    assert port not in {c.laddr.port for c in psutil.Process(proc.pid).connections() if c.status == 'LISTEN'}
    # a loopback URI names a process of this network name space: there, 127.0.0.1 is another host
    why = node_process_problem(proc.pid, '/slave/after', 'http://127.0.0.1:%d/' % port)
    assert why is not None and 'another network name space' in why


TCP_HEADER = '  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode\n'


def _fake_proc(root, pid, sockets, listening, argv, env, net='net:[1]', own_net='net:[1]'):
    """A /proc of one process (pid) holding the socket inodes ``sockets``, in a network name space
    whose listening sockets are ``listening`` [(hex address:port, inode)]; /proc/self in ``own_net``."""
    base = root / str(pid)
    (base / 'fd').mkdir(parents=True)
    for n, inode in enumerate(sockets):
        os.symlink('socket:[%s]' % inode, str(base / 'fd' / str(n)))
    (base / 'net').mkdir()
    rows = ['%4d: %s 00000000:0000 0A 00000000:00000000 00:00000000 00000000     0        0 %s 1 0 100 0 0 10 0'
            % (n, local, inode) for n, (local, inode) in enumerate(listening)]
    (base / 'net' / 'tcp').write_text(TCP_HEADER + '\n'.join(rows) + '\n')
    (base / 'cmdline').write_bytes(b'\0'.join(a.encode() for a in argv) + b'\0')
    (base / 'environ').write_bytes(b'\0'.join(('%s=%s' % kv).encode() for kv in env.items()) + b'\0')
    (base / 'ns').mkdir()
    os.symlink(net, str(base / 'ns' / 'net'))
    (root / 'self' / 'ns').mkdir(parents=True)
    os.symlink(own_net, str(root / 'self' / 'ns' / 'net'))
    return str(root)


def test_a_second_listener_on_the_same_port_makes_the_uri_ambiguous(tmp_path):
    """The node on 0.0.0.0:11411 (inode 1), another process's socket on 127.0.0.1:11411 (inode 2, as
    SO_REUSEPORT allows): http://127.0.0.1:11411 may reach either, so the pid is not taken."""
    proc = _fake_proc(tmp_path, 4242, ['1'], [('00000000:2C93', '1'), ('0100007F:2C93', '2')],
                      ['python3', 'after', '__name:=after'], {'ROS_NAMESPACE': '/slave'})
    why = node_process_problem(4242, '/slave/after', 'http://127.0.0.1:11411/', proc=proc)
    assert why == ('another process than 4242 also listens on port 11411 (at 127.0.0.1): /slave/after\'s URI '
                   'http://127.0.0.1:11411/ does not tell which it reaches')


def test_the_fake_proc_passes_the_node_itself(tmp_path):
    """The control of the test above: alone on its port, the same process is the node."""
    proc = _fake_proc(tmp_path, 4242, ['1'], [('00000000:2C93', '1'), ('0100007F:2C94', '2')],
                      ['python3', 'after', '__name:=after'], {'ROS_NAMESPACE': '/slave'})
    assert node_process_problem(4242, '/slave/after', 'http://127.0.0.1:11411/', proc=proc) is None
    # but not for a loopback URI if it runs in another network name space than the asker
    other = _fake_proc(tmp_path / 'b', 4242, ['1'], [('00000000:2C93', '1')], ['python3', 'after', '__name:=after'],
                       {'ROS_NAMESPACE': '/slave'}, net='net:[2]')
    assert 'another network name space' in node_process_problem(4242, '/slave/after', 'http://127.0.0.1:11411/',
                                                                  proc=other)


def test_only_the_parent_of_a_learned_node_and_not_above_the_asker_is_its_launcher():
    """Recovery kills the process tree of the failed site's launcher, named by a heartbeat or a failure
    report that anyone may forge: the pid must be the parent of a node learned of the name space by pid
    (when it was learned; roslaunch starts its nodes itself), not a process further up (a daemon such as
    sshd), and not above Recovery itself (the shell or test both sites come from, init)."""
    from aft_ftm.ros.fencing import NamespaceFence, _lineage
    import psutil
    launcher = subprocess.Popen(['bash', '-c', 'sleep 60 & wait'])
    daemon = subprocess.Popen(['bash', '-c', 'bash -c "sleep 60 & wait" & wait'])   # a daemon above a launcher
    try:
        deadline = time.monotonic() + 10.0
        while not psutil.Process(launcher.pid).children() and time.monotonic() < deadline:
            time.sleep(0.01)
        node = psutil.Process(launcher.pid).children()[0]
        fence = NamespaceFence('/master', '/test')
        fence.lineage['/master/node'] = _lineage(node.pid)
        created = psutil.Process(launcher.pid).create_time()
        assert fence.started(launcher.pid, created) == '/master/node'
        assert fence.started(launcher.pid, created + 5.0) is None          # the pid reused by another process
        assert fence.started(node.pid, node.create_time()) is None         # the node itself launched nothing
        while len(psutil.Process(daemon.pid).children(recursive=True)) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        inner = psutil.Process(daemon.pid).children()[0]
        fence.lineage['/master/deep'] = _lineage(inner.children()[0].pid)
        assert fence.started(inner.pid, inner.create_time()) == '/master/deep'
        assert fence.started(daemon.pid, psutil.Process(daemon.pid).create_time()) is None   # further up
        for above_me in [os.getpid(), os.getppid(), 1]:
            assert fence.started(above_me, psutil.Process(above_me).create_time()) is None
        fence.lineage['/master/node'] = _lineage(launcher.pid)              # a node whose parent is above me
        assert fence.started(os.getpid(), psutil.Process().create_time()) is None
        fence.lineage['/master/node'] = _lineage(node.pid)
        stranger = subprocess.Popen(['sleep', '60'])
        try:
            assert fence.started(stranger.pid, psutil.Process(stranger.pid).create_time()) is None
        finally:
            stranger.kill()
            stranger.wait()
    finally:
        for root in (launcher, daemon):
            for child in psutil.Process(root.pid).children(recursive=True):
                child.kill()
            root.kill()
            root.wait()


class FakeMaster(object):
    """What NamespaceFence asks the ROS master: the names registered and each one's API uri."""

    def __init__(self):
        self.uris = {}

    def getSystemState(self):
        return [['/topic', sorted(self.uris)]], [], []

    def lookupNode(self, name):
        return self.uris[name]


LAUNCHER = r"""
import os, subprocess, sys, time
if os.environ.get('FORKED') and os.fork() == 0:   # a child forked, not exec'd yet: its launcher's argv
    time.sleep(60)
    os._exit(0)
for spec in sys.argv[1:]:
    ns, name = spec.split(':')
    subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)', '__name:=' + name],
                     env=dict(os.environ, ROS_NAMESPACE=ns))
print('ready', flush=True)
time.sleep(60)
"""


class _Ports(object):
    def __init__(self):
        self.published = []

    def publish(self, port, msg):
        self.published.append(msg)


@pytest.fixture
def launchers(tmp_path, monkeypatch):
    """start(program, 'ns:name', ...): a process whose command line runs ``program`` (roslaunch, or
    anything else) and whose children are named as roslaunch names nodes; every tree killed at the end."""
    import psutil
    import rospy
    monkeypatch.setattr(rospy, 'get_name', lambda: '/slave/recovery')
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))
    started = []

    def start(program, *children, forked=False):
        script = tmp_path / program
        script.write_text(LAUNCHER)
        proc = subprocess.Popen([sys.executable, str(script)] + list(children), stdout=subprocess.PIPE,
                                env=dict(os.environ, FORKED='1' if forked else ''))
        started.append(proc)
        assert proc.stdout.readline().strip() == b'ready'
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and sum('__name:=' in ' '.join(c.cmdline())
                                                  for c in psutil.Process(proc.pid).children()) < len(children):
            time.sleep(0.01)
        return proc
    yield start
    for proc in started:
        try:
            for child in psutil.Process(proc.pid).children(recursive=True):
                child.kill()
        except psutil.Error:
            pass
        proc.kill()
        proc.wait()


def _recovery(failed_pid):
    """The failover's view: a Recovery of /slave (built without ROS) and the failure naming failed_pid."""
    import rospy
    from aft_msgs.msg import Failure
    from aft_ftm.ros.fencing import NamespaceFence
    from aft_ftm.ros.recovery_node import RecoveryNode
    from aft_ftm.sites import this_host
    node = RecoveryNode.__new__(RecoveryNode)
    node.fence, node.peer_ns, node.ports = NamespaceFence('/master', '/slave/recovery'), '/master', _Ports()
    failure = Failure(site='master', host=this_host(), pid=failed_pid, reason='silent', silence=0.0,
                      detected=rospy.Time.from_sec(time.time()))
    return node, failure


def test_a_launcher_is_known_by_its_children_in_proc_even_before_any_of_its_nodes_told_its_pid(launchers):
    """healing.test in CI: the primary failed (its server stopped) within a second of the backup's start,
    before the backup's fence had asked the primary's nodes for their pids. The launcher the heartbeats
    named was refused as nobody's launcher and the stopped server lived on. Now a roslaunch whose
    children name themselves nodes of the failed site (/proc: a heartbeat cannot forge it) is its
    launcher, and its whole tree is killed."""
    for forked in (False, True):   # (a child forked, not exec'd yet, is no other's node: review of session 35)
        site = launchers('roslaunch', '/master:bank_server', '/master:after', forked=forked)
        node, failure = _recovery(site.pid)
        roots, why = node._launcher(failure)
        assert [r.pid for r in roots] == [site.pid] and why == 'launcher %d of master (it started ' \
            '/master/bank_server)' % site.pid
        assert node.ports.published == []


def test_a_forged_heartbeat_naming_a_process_that_is_no_launcher_kills_nothing(launchers):
    """Review of session 35: the adaptation engine starts guards that carry their node's command line
    (``__name:=before``, ROS_NAMESPACE /master): by its children alone, the engine passed for /master's
    launcher, and a forged heartbeat naming it had its whole tree killed (the surviving site's
    replacement nodes with it). A process that runs no launcher, or whose children are of another name
    space (the client's roslaunch), is refused with the alarm fence_refused."""
    import psutil
    for program, children in (('adapt', ('/master:before',)), ('roslaunch', ('/client:proxy', '/master_other:x')),
                              ('roslaunch', ())):
        other = launchers(program, *children)
        node, failure = _recovery(other.pid)
        roots, why = node._launcher(failure)
        assert roots == [] and why.startswith('pid %d, named as the launcher of master, started no node of /master'
                                              % other.pid), why
        (told,) = node.ports.published
        assert (told.kind, told.detail) == ('fence_refused', why)
        assert psutil.Process(other.pid).status() != psutil.STATUS_STOPPED


def test_a_launcher_running_other_nodes_too_is_stopped_and_only_the_failed_sites_nodes_are_killed(launchers):
    """Review of session 35: a launcher that runs the failed site's nodes and others (another site, a
    service of the board) had its whole tree killed; only the failed site's nodes are now, and the
    launcher is left stopped (it starts none of them again: a respawn, a node not started yet), with
    the alarm fence_partial."""
    import psutil
    mixed = launchers('roslaunch', '/master:bank_server', '/aft:witness')
    node, failure = _recovery(mixed.pid)
    roots, why = node._launcher(failure)
    children = {c.pid: ' '.join(c.cmdline()) for c in psutil.Process(mixed.pid).children()}
    assert [r.pid for r in roots] == [p for p, c in children.items() if '__name:=bank_server' in c]
    assert why == 'launcher %d of master also runs /aft/witness: stopped, and only its 1 nodes of /master killed' \
        % mixed.pid
    assert psutil.Process(mixed.pid).status() == psutil.STATUS_STOPPED
    (told,) = node.ports.published
    assert told.kind == 'fence_partial' and 'its other nodes run on' in told.detail
    psutil.Process(mixed.pid).resume()
    from aft_ftm.ros.fencing import is_launcher, launcher_children
    assert launcher_children([(7, '/master_other/x'), (8, None), (9, '/master/a')], '/master/') == (
        [(9, '/master/a')], ['/master_other/x', 'pid 8 (no node)'])
    assert is_launcher(['/usr/bin/python3', '/usr/bin/roslaunch', 'x.launch'])
    assert is_launcher([sys.executable, '-m', 'aft_ftm.ros.guarded_launch', '--poll', '0.2'])
    assert not is_launcher([sys.executable, '/opt/ros/lib/aft_ftm/adapt', '__name:=adapt'])


def test_a_dead_nodes_registration_whose_port_reaches_another_process_is_stale_not_forged(started, monkeypatch):
    """A power loss kills a site's nodes and nobody unregisters them: on a busy host another process
    may then listen on a dead node's port and answer its API. Fencing must not signal that process,
    and must not raise fence_refused (no forgery: the uri is the one the node was learned at).
    A registration at another uri naming a process that is not the node, or one made again at that uri
    after the stale one was cleaned up at the master, stays refused."""
    from aft_ftm.ros import fencing
    pids = {}   # port -> the pid the API there answers

    class Api(object):
        def __init__(self, uri, _timeout):
            self.port = int(uri.rsplit(':', 1)[1].strip('/'))

        def getPid(self, _caller):
            return 1, '', pids[self.port]
    monkeypatch.setattr(fencing, 'node_api', Api)
    fence = fencing.NamespaceFence('/master', '/test')
    fence.master = FakeMaster()
    node, port = started(['__name:=after'], {'ROS_NAMESPACE': '/master'})
    pids[port] = node.pid
    fence.master.uris['/master/after'] = 'http://127.0.0.1:%d/' % port
    fence.learn()
    assert fence.known['/master/after'][0] == node.pid and not fence.unlearned
    node.kill()
    node.wait()
    stranger, same_port = started([], {'PORT': str(port)})   # another process binds the dead node's port
    assert same_port == port
    pids[port] = stranger.pid
    fence.learn()
    assert fence.refused == {} and '/master/after' in fence.stale and fence.unlearned == []
    assert fence.processes() == {}   # nothing to signal
    # the stale registration cleaned up at the master, then the name registered again at that very uri
    # (whoever holds the port now): not the registration the node left, so a forgery, refused
    del fence.master.uris['/master/after']
    fence.learn()
    assert fence.stale == {} and fence.refused == {}
    fence.master.uris['/master/after'] = 'http://127.0.0.1:%d/' % port
    fence.learn()
    assert 'runs in name space /, not in' in fence.refused['/master/after'] and fence.stale == {}, fence.refused
    del fence.master.uris['/master/after']
    fence.learn()
    # the name registered again at another uri whose process is not the node: a forgery, refused
    other, other_port = started([], {})
    pids[other_port] = other.pid
    fence.master.uris['/master/after'] = 'http://127.0.0.1:%d/' % other_port
    fence.learn()
    assert 'runs in name space /, not in' in fence.refused['/master/after'], fence.refused
    assert other_port != port
    # the node started again under its name, at a port of its own: learned
    again, again_port = started(['__name:=after'], {'ROS_NAMESPACE': '/master'})
    pids[again_port] = again.pid
    fence.master.uris['/master/after'] = 'http://127.0.0.1:%d/' % again_port
    fence.learn()
    assert fence.known['/master/after'][0] == again.pid and not fence.refused and not fence.stale


def test_a_node_shutting_down_is_refused_only_if_it_is_still_there_after_a_grace(started, monkeypatch):
    """A node shutting down closes its API before its process ends: asked in between, the pid it gave
    listens nowhere. A process whose command line names the node is neither learned nor refused for
    CLOSING_GRACE (asked again meanwhile); gone by then, nothing is refused; still there, it is refused
    as any other (a launch guard carries its node's command line too: never taken for the node)."""
    from aft_ftm.ros import fencing
    pids, now = {}, [100.0]

    class Api(object):
        def __init__(self, uri, _timeout):
            self.port = int(uri.rsplit(':', 1)[1].strip('/'))

        def getPid(self, _caller):
            if self.port not in pids:
                raise ConnectionRefusedError('nobody answers')
            return 1, '', pids[self.port]
    monkeypatch.setattr(fencing, 'node_api', Api)
    fence = fencing.NamespaceFence('/slave/tr', '/test')
    fence.master = FakeMaster()
    fence.clock = lambda: now[0]
    node, port = started(['__name:=proceed'], {'ROS_NAMESPACE': '/slave/tr'})
    closed = port + 1 if port < 65535 else port - 1   # its API closed: the port it was registered at
    pids[closed] = node.pid
    fence.master.uris['/slave/tr/proceed'] = 'http://127.0.0.1:%d/' % closed
    fence.learn()
    assert fence.unlearned == ['/slave/tr/proceed'] and fence.refused == {} and fence.known == {}
    now[0] += fencing.NamespaceFence.CLOSING_GRACE / 2
    fence.learn()
    assert fence.unlearned == ['/slave/tr/proceed'] and fence.refused == {}
    # still there after the grace: refused (not the node at that uri), never learned
    now[0] += fencing.NamespaceFence.CLOSING_GRACE
    fence.learn()
    assert 'does not listen' in fence.refused['/slave/tr/proceed'] and fence.known == {}
    assert fence.processes() == {}
    # the usual end: the process gone within the grace, then its name gone from the master
    del fence.master.uris['/slave/tr/proceed']
    fence.learn()
    assert fence.refused == {} and fence.closing == {}
    fence.master.uris['/slave/tr/proceed'] = 'http://127.0.0.1:%d/' % closed
    fence.learn()
    assert fence.unlearned == ['/slave/tr/proceed'] and fence.refused == {}
    node.kill()
    node.wait()
    del pids[closed]   # its API gone with it
    now[0] += 2 * fencing.NamespaceFence.CLOSING_GRACE
    fence.learn()
    assert fence.refused == {} and fence.known == {}
    del fence.master.uris['/slave/tr/proceed']
    fence.learn()
    assert fence.unlearned == [] and fence.refused == {} and fence.closing == {}
    # a process whose command line names another node gets no grace
    other, other_port = started(['__name:=after'], {'ROS_NAMESPACE': '/slave/tr'})
    pids[other_port + 1] = other.pid
    fence.master.uris['/slave/tr/proceed'] = 'http://127.0.0.1:%d/' % (other_port + 1)
    fence.learn()
    assert '/slave/tr/proceed' in fence.refused and fence.unlearned == []


def test_the_board_watchdog_kills_only_a_launcher_of_the_failed_board(launchers):
    """Review of session 36: the car's watchdog killed the tree of whatever pid the primary's last
    heartbeat named: a forged beat naming pid 1 (its own ancestor), a process that runs no launcher, a
    launcher of other nodes. Now it checks the pid as Recovery does, and says what it refused."""
    import types
    import psutil
    from aft_ftm.ros.watchdog_node import WatchdogNode
    from aft_ftm.sites import this_host

    def watchdog():
        node = WatchdogNode.__new__(WatchdogNode)
        node.proxies, node.host, node.reports = {}, this_host(), []
        node._close = lambda proxies: None
        node._report = lambda report: node.reports.append((report.kind, report.detail))
        return node

    def fail(node, pid):
        stopped = []
        killed = node._power_off('board_a', types.SimpleNamespace(
            last_info=types.SimpleNamespace(host=this_host(), pid=pid), silence=0.0), lambda: stopped.append(1))
        return killed, stopped
    other = launchers('adapt', '/board_a:controller_pid')
    foreign = launchers('roslaunch', '/tjp:command_manager')
    for pid in (1, os.getppid(), other.pid, foreign.pid):
        node = watchdog()
        killed, stopped = fail(node, pid)
        assert killed == 0 and stopped == [1], pid                   # the take-over goes on
        assert node.reports and node.reports[0][0] in ('fence_refused', 'fail_silence_unenforced'), (pid, node.reports)
        assert psutil.pid_exists(pid) and psutil.Process(pid).status() != psutil.STATUS_STOPPED, pid
    board = launchers('roslaunch', '/board_a:controller_pid', '/board_a:cycle_after')
    children = [c.pid for c in psutil.Process(board.pid).children()]
    node = watchdog()
    killed, stopped = fail(node, board.pid)
    assert killed == 3 and stopped == [1] and node.reports == []
    assert not any(psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE for p in children)
