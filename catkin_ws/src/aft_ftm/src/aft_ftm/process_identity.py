"""Is this pid really that ROS node? Checked before any signal is sent to a pid learned over XML-RPC.

The ROS master's XML-RPC API is open to anyone on the network: a process can register any node name
with the URI of an XML-RPC server of its own, whose ``getPid`` answers any pid. Fencing and the
Adaptation Engine learn pids that way (``lookupNode`` then ``getPid``), and they run as root: taken
on trust, a forged registration under a failed site's name space (``/slave/x``, pid 1) would have
Recovery SIGKILL pid 1, and a forged node to retire would have the Adaptation Engine kill it.

A pid is taken as node ``name`` at ``uri`` only if what the kernel says of that process agrees:
- it listens on the URI's TCP port at the URI's address (or on every address), in its own network
  name space (``/proc/PID/net/tcp*``, read for that process, so emulated hosts are seen as they are;
  psutil reads this process's name space only), no other socket listens there on that port at the
  URI's addresses, and a loopback URI names a process of the asker's own network name space;
- it is not the process asking, nor a ROS master or roslaunch;
- the name space its command line and environment give it (``__ns:=``, ``ROS_NAMESPACE``, as rospy
  reads them) is the node's, and a ``__name:=`` remapping in its command line names the node.
A forged server cannot make another process listen at its address and port, nor change that process's
command line. What is left open: a registration pointing at a real node of the same name space under
another name, when that node's command line does not remap ``__name`` (its pid passes); a fence of
that name space kills that node anyway.
Plain Python (no rospy): /proc and rosgraph.names only."""
import ipaddress
import os
import socket
from urllib.parse import urlparse

from rosgraph import names

LISTEN = '0A'   # TCP state in /proc/net/tcp
WILDCARDS = {'0.0.0.0', '::'}


def _socket_inodes(pid, proc='/proc'):
    inodes = set()
    fd_dir = os.path.join(proc, str(pid), 'fd')
    for fd in os.listdir(fd_dir):
        try:
            target = os.readlink(os.path.join(fd_dir, fd))
        except OSError:   # closed meanwhile
            continue
        if target.startswith('socket:['):
            inodes.add(target[len('socket:['):-1])
    return inodes


def _address(hex_address):
    """The text address of a /proc/net/tcp{,6} local address field's host part."""
    raw = bytes.fromhex(hex_address)
    # the kernel prints each 32-bit word in host order (little-endian here)
    raw = b''.join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
    if len(raw) == 4:
        return socket.inet_ntop(socket.AF_INET, raw)
    text = socket.inet_ntop(socket.AF_INET6, raw)
    return text[len('::ffff:'):] if text.startswith('::ffff:') and '.' in text else text


def _listening_table(pid, proc='/proc'):
    """[(address, port, inode)] of every TCP socket listening in the network name space of process
    ``pid`` (of any process there), IPv4 and IPv6. Raises OSError if it cannot be read."""
    table = []
    for name in ('tcp', 'tcp6'):
        try:
            with open(os.path.join(proc, str(pid), 'net', name)) as f:
                lines = f.read().splitlines()[1:]
        except FileNotFoundError:   # no IPv6 in this kernel
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 9 and fields[3] == LISTEN:
                host, port = fields[1].rsplit(':', 1)
                table.append((_address(host), int(port, 16), fields[9]))
    return table


def listening_sockets(pid, proc='/proc'):
    """{(address, port)} of the TCP sockets process ``pid`` listens on (IPv4 and IPv6), in its own
    network name space. Raises OSError if the process is gone or cannot be read."""
    inodes = _socket_inodes(pid, proc)
    return {(a, p) for a, p, inode in _listening_table(pid, proc) if inode in inodes}


def listening_ports(pid, proc='/proc'):
    """The TCP ports process ``pid`` listens on, in its own network name space."""
    return {port for _, port in listening_sockets(pid, proc)}


def addresses_of(host):
    """The addresses ``host`` resolves to (itself if it is one), without an IPv6 scope (as the kernel's
    socket tables show them); empty if it does not resolve."""
    try:
        return {info[4][0].split('%', 1)[0] for info in socket.getaddrinfo(host, None, proto=socket.IPPROTO_TCP)}
    except (socket.gaierror, UnicodeError, ValueError):
        return set()


def _argv_and_env(pid, proc='/proc'):
    with open(os.path.join(proc, str(pid), 'cmdline'), 'rb') as f:
        argv = [a.decode(errors='replace') for a in f.read().split(b'\0') if a]
    with open(os.path.join(proc, str(pid), 'environ'), 'rb') as f:
        env = {}
        for entry in f.read().split(b'\0'):
            key, sep, value = entry.decode(errors='replace').partition('=')
            if sep:
                env[key] = value
    return argv, env


def node_names_of(argv, env):
    """(name space, full node name or None) a rospy process started with ``argv`` and ``env`` takes:
    the name is known only if its command line remaps ``__name``."""
    namespace = names.get_ros_namespace(env=env, argv=argv)
    remapped = [a[len('__name:='):] for a in argv if a.startswith('__name:=')]
    if not remapped:
        return namespace, None
    name = remapped[-1]
    return namespace, name if name.startswith('/') else names.ns_join(namespace, name)


def _namespace_of_node(node):
    return names.make_global_ns(names.namespace(node))


def _loopback(address):
    try:
        return ipaddress.ip_address(address.split('%', 1)[0]).is_loopback or address in WILDCARDS
    except ValueError:
        return False


def _net_namespace(pid, proc='/proc'):
    return os.readlink(os.path.join(proc, str(pid), 'ns', 'net'))


NOT_NODES = ('rosmaster', 'roslaunch', 'roscore')   # a process running one of these is no node


def names_itself(pid, node, proc='/proc'):
    """Whether process ``pid``'s command line remaps ``__name`` to ``node`` (False if it cannot be read).
    Never a reason to signal it (a wrapper such as a launch guard carries its node's command line too):
    only to wait a moment before calling a registration naming it forged (see fencing's learn)."""
    try:
        return node_names_of(*_argv_and_env(pid, proc))[1] == node
    except (OSError, ValueError, TypeError):
        return False


def node_process_problem(pid, node, uri, proc='/proc'):
    """None if process ``pid`` can be node ``node`` registered at ``uri``; else why it cannot (a
    sentence naming the pid, the node and what disagrees)."""
    try:
        parsed = urlparse(uri)
        port, host = parsed.port, parsed.hostname
    except ValueError:
        port = host = None
    if port is None or not host:
        return 'the URI %s of %s names no host and port' % (uri, node)
    try:
        pid = int(pid)
        if pid <= 0:
            return 'pid %d is no process (%s at %s said it was)' % (pid, node, uri)
        if pid == os.getpid():
            return 'pid %d is the process asking (%s at %s said it was)' % (pid, node, uri)
        # Listening on the URI's port at its address (or on every address), and nobody else there: a
        # server on another address of the host (127.0.0.2, ::1) with the same port is another process.
        addresses = addresses_of(host)
        there = [(a, inode) for a, p, inode in _listening_table(pid, proc)
                 if p == port and (a in addresses or a in WILDCARDS)]
        own = _socket_inodes(pid, proc)
        if not any(inode in own for _, inode in there):
            return 'process %d does not listen on %s port %d (%s\'s URI %s): it is not the node there' % (
                pid, host, port, node, uri)
        others = sorted({a for a, inode in there if inode not in own})
        if others:
            return 'another process than %d also listens on port %d (at %s): %s\'s URI %s does not tell ' \
                'which it reaches' % (pid, port, ', '.join(others), node, uri)
        if any(_loopback(a) for a in addresses) and _net_namespace(pid, proc) != _net_namespace('self', proc):
            return 'process %d runs in another network name space than this one: %s in %s\'s URI %s is ' \
                'not its address' % (pid, host, node, uri)
        argv, env = _argv_and_env(pid, proc)
    except (OSError, ValueError, TypeError) as e:
        return 'process %s (said to be %s at %s) cannot be read: %s' % (pid, node, uri, e)
    programs = {os.path.basename(a) for a in argv[:2]}
    if programs & set(NOT_NODES):
        return 'process %d runs %s, no node (%s at %s said it was)' % (pid, ' '.join(argv[:2]), node, uri)
    namespace, name = node_names_of(argv, env)
    if name is not None:
        if name != node:
            return 'process %d runs node %s, not %s' % (pid, name, node)
    elif namespace != _namespace_of_node(node):
        return 'process %d runs in name space %s, not in %s\'s (%s)' % (pid, namespace, node,
                                                                       _namespace_of_node(node))
    return None
