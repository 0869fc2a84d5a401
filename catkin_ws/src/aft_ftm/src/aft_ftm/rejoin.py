"""Whether a node must register again with the ROS master. No ROS here.

A ROS master restarted on the same port knows no node: rospy registers once, at init_node, and
never again, so a running node's services cannot be looked up, its topics get no new peers, and
nothing started afterwards can find it (plain ROS 1; roscpp behaves the same). A node that checks
now and then that the master still knows it, and registers everything again when it does not,
survives the master's restart.

Two probes: the master's pid (getPid) and its lookupNode of the node's own name. A new pid is a
new master: register again, even where the node is known (a subscription made after the restart
registers the node, not its older topics). lookupNode answers with the node's own URI (known), with
another URI (another node took the name: the master has shut this one down, or will; never register
over it), or with an error (unknown: register again; a master restarted with its old pid, as pid 1
of a container is). A master that does not answer is only waited for.

A node the master still knows may have lost its registrations all the same: ``rosnode cleanup``
(and the deployments' own clean-up of dead nodes) unregisters every node that does not answer a
ping in time, and a live node slow under load is taken for dead. Its subscriptions then get no new
publishers for ever (found by the hosts campaign: a backup's crash detector, cleaned while a site
was relaunched on a loaded machine, never heard its re-joined peer, which it excluded ten times
in a row). So a third probe looks up the node's own ``~get_loggers`` service, which every rospy
node registers: gone, or registered to another address, and the node registers everything again.
"""
import enum
import re

# rosmaster's words when a node registers under a name another address held (registrations.py): it
# then asks the old address to shut down, naming the node it means. Fencing's request to a failed
# site's node (aft_ftm.ros.fencing) names it the same way.
_BUMPED = re.compile(r'^\[(?P<name>[^\]]*)\] Reason: (new node registered with same name|fail-silence of .*)$')


def misdirected_shutdown(message, own_name):
    """Whether a shutdown request of a ROS master or of fencing (its ``message``) names another node
    than ``own_name``.

    When a host comes back with its address (a power loss, a site relaunched), its new processes may be
    given the very ports its dead ones had. A node of the dead site registering again bumps its old
    registration, and the master sends the shutdown to the old address: to whatever new process now
    listens there, which plain rospy obeys. The message names the node it is meant for; another node
    must ignore it."""
    match = _BUMPED.match(message or '')
    return bool(match) and match.group('name') != own_name


class Lookup(enum.Enum):
    KNOWN = 'the master knows this node'
    UNKNOWN = 'the master does not know this node: register again'
    REPLACED = 'the master knows another node by this name: leave it'
    UNREACHABLE = 'the master does not answer'


def judge(answer, own_uri, service=None, own_service_uri=None):
    """The Lookup from a lookupNode answer: (code, message, uri), or None when the call failed; and,
    when given, from a lookupService answer for the node's own ~get_loggers (same form)."""
    if answer is None:
        return Lookup.UNREACHABLE
    code, _, uri = answer
    if code != 1:
        return Lookup.UNKNOWN
    if not _same_uri(uri, own_uri):
        return Lookup.REPLACED
    if own_service_uri is not None:
        if service is None:
            return Lookup.UNREACHABLE
        if service[0] != 1 or not _same_uri(service[2], own_service_uri):
            return Lookup.UNKNOWN   # known, but its registrations were removed (a clean-up took it for dead)
    return Lookup.KNOWN


def master_pid(answer):
    """The pid from a getPid answer (code, message, pid), or None (failed, or not a pid)."""
    if answer is None or answer[0] != 1:
        return None
    return answer[2]


def _same_uri(a, b):
    return (a or '').rstrip('/') == (b or '').rstrip('/')


class Rejoin(object):
    """What to do after each pair of probes, and what to say (once per change, not at every probe).
    The caller calls registered(pid) once it has registered again (until then every probe asks)."""

    def __init__(self):
        self.last = None
        self.pid = None        # the master's pid this node is registered with
        self.rejoins = 0

    def step(self, pid, lookup):
        """pid: the master's (None: no answer); lookup: a Lookup. Returns (register_again, message or None)."""
        if pid is None:
            lookup = Lookup.UNREACHABLE
        elif self.pid is None and lookup == Lookup.KNOWN:
            self.pid = pid   # the first probe: the master init_node registered with
        elif lookup == Lookup.KNOWN and pid != self.pid:
            lookup = Lookup.UNKNOWN   # a new master that knows the node only by its newer topics
        changed = lookup != self.last
        self.last = lookup
        if lookup == Lookup.UNKNOWN:
            return True, 'the ROS master (pid %s) does not know all of this node (restarted?): registering again' % pid
        if not changed:
            return False, None
        if lookup == Lookup.REPLACED:
            return False, 'another node has taken this name at the ROS master: not registering again'
        if lookup == Lookup.UNREACHABLE:
            return False, 'the ROS master does not answer: will register again once it does, if needed'
        return False, None

    def registered(self, pid):
        self.pid = pid
        self.rejoins += 1
        self.last = Lookup.KNOWN
