"""Emulated hosts: one Linux network namespace per host, on one private bridge. The plans only.

This module decides *what* to run, never runs it: every function returns the exact ``ip``/``tc``
command lines (argv lists, no shell) and the signals to send, so the plans are tested without root.
:mod:`aft_ftm.hosts_exec` carries them out.

The layout of a run whose prefix is ``aft1a2b`` (``aft`` and 4 hex digits, on every name so that a
killed run's leftovers are found by name)::

    namespace aft1a2b-sw        the switch: bridge aft1a2b-br and the switch end of every cable
      aft1a2b-s0 ... aft1a2b-sN    switch ends, enslaved to aft1a2b-br
    namespace aft1a2b-<host>    one per host, e.g. aft1a2b-client
      lo (up), aft1a2b-hI          the host's end of its cable, address 10.213.X.(10+I)/24

Nothing is created in the root namespace: no route or link of the machine changes, and a host has
no default route, so its traffic stays on the private link (or its own loopback). ``X`` is chosen
so that 10.213.X.0/24 overlaps no network the machine already uses (:func:`choose_network`).

Invariants:

- every namespace and link name starts with ``<prefix>-``; interface names fit IFNAMSIZ (15);
- addresses are unique, inside 10.213.X.0/24, and private; MACs are fixed and locally administered;
- :func:`plan_down` undoes :func:`plan_up`: the undo of each step that creates something, in reverse;
- a power loss takes the host's link down *before* any process is stopped or killed, so nothing the
  dying processes' kernel sends (FIN, RST) leaves the host.

The faults, each a plan (a list of :class:`Step` and :class:`Signal`):

- partition of a host: its cable's switch end goes down (:func:`plan_link_down`); the host's own
  interface keeps its address and route, as when a cable is cut: its packets vanish, nobody gets an
  error at once. Healing brings it up again.
- partition of a pair: each of the two hosts gets a permanent neighbour (ARP) entry for the other's
  address pointing at a MAC that no interface has, so their packets to each other are dropped
  silently while both still reach everybody else. (This kernel has neither nftables nor iptables,
  nor the tc classifiers and drop action; this needs neither.)
- rate limit: a token bucket (``tc htb``) on both ends of the host's cable, so both its upload and
  its download are limited, low-delay packets (the heartbeats) first (:func:`plan_rate`). This
  kernel has no netem: no delay, loss or reordering.
- power loss: link down, then SIGSTOP of every process of the host, then SIGKILL of them all.
  Power on makes the host again from nothing (a new namespace: no socket of the old one survives).
- freeze: SIGSTOP of a host's processes or of one process, SIGCONT after a bounded time.

:class:`Network` is the explicit state machine of the hosts (:class:`HostState`, every edge in
:data:`EDGES`, one ``_change()``): it refuses a fault that does not apply (a partition of a host
that is off, ...) with a message naming the host, and plans the ones that do.
"""
import collections
import enum
import ipaddress
import re
import signal

from .errors import AftError

DEFAULT_HOSTS = ('client', 'master', 'slave', 'witness', 'rosmaster')
PROJECT_PREFIX = 'aft'
BASE = '10.213'                  # the networks used: 10.213.X.0/24
FIRST_HOST = 10                  # host I has address 10.213.X.(FIRST_HOST + I)
MAX_HOSTS = 50
MAX_FREEZE = 60.0                # seconds
MIN_KBIT, MAX_KBIT = 8, 10000000
QUEUE_LATENCY = 0.1              # s: how much traffic a rate limit's queue holds (more is dropped)
IFNAMSIZ = 15
_HOST = re.compile(r'^[a-z][a-z0-9]{0,15}$')
_RUN = re.compile(r'^[a-z]{1,8}[0-9a-f]{4}$')


class HostsError(AftError):
    """Root of the errors of the emulated hosts."""


class TopologyError(HostsError):
    """A topology or a fault was asked with a bad value; the message names it. Nothing was changed."""


class FaultError(HostsError):
    """A fault that does not apply to the host's state (e.g. a partition of a host that is off)."""


Host = collections.namedtuple('Host', 'name index ip mac namespace host_if switch_if')
Step = collections.namedtuple('Step', 'argv undo why')     # argv: a command line; undo: argv or None
Signal = collections.namedtuple('Signal', 'signum pids why')


def run_prefix_pattern(prefix=PROJECT_PREFIX):
    """The names a run with this project prefix creates: ``<prefix><4 hex>-...``."""
    if not re.match(r'^[a-z]{1,8}$', prefix):
        raise TopologyError('the project prefix must be 1 to 8 lower-case letters, got %r' % (prefix,))
    return re.compile(r'^(%s[0-9a-f]{4})-' % prefix)


def check_host_name(name):
    if not isinstance(name, str) or not _HOST.match(name):
        raise TopologyError('bad host name %r: a lower-case letter then up to 15 letters or digits' % (name,))
    if name in ('sw', 'br'):
        raise TopologyError('bad host name %r: reserved for the switch' % name)
    return name


def parse_hosts(text):
    """'client,master' -> ('client', 'master'); every name checked, duplicates refused."""
    names = tuple(n.strip() for n in text.split(',')) if isinstance(text, str) else tuple(text)
    if not names or names == ('',):
        raise TopologyError('no host named: give at least one, e.g. client,master')
    for name in names:
        check_host_name(name)
    seen = set()
    for name in names:
        if name in seen:
            raise TopologyError('host %r is named twice' % name)
        seen.add(name)
    if len(names) > MAX_HOSTS:
        raise TopologyError('%d hosts asked, at most %d' % (len(names), MAX_HOSTS))
    return names


def check_kbit(kbit):
    if isinstance(kbit, bool) or not isinstance(kbit, int):
        try:
            kbit = int(str(kbit), 10)
        except ValueError:
            raise TopologyError('bad rate %r: an integer number of kbit/s' % (kbit,))
    if not MIN_KBIT <= kbit <= MAX_KBIT:
        raise TopologyError('bad rate %d kbit/s: between %d and %d' % (kbit, MIN_KBIT, MAX_KBIT))
    return kbit


def check_seconds(seconds):
    try:
        value = float(seconds)
    except (TypeError, ValueError):
        raise TopologyError('bad freeze time %r: seconds, e.g. 0.5' % (seconds,))
    if not 0 < value <= MAX_FREEZE:
        raise TopologyError('bad freeze time %r: more than 0 and at most %g s' % (seconds, MAX_FREEZE))
    return value


def choose_network(prefix, taken):
    """The first 10.213.X.0/24 (X starting from the prefix's hex digits) that overlaps none of the
    networks in ``taken`` (CIDR strings or networks; default routes, /0, are ignored)."""
    used = []
    for net in taken:
        net = ipaddress.ip_network(net, strict=False)
        if net.version == 4 and net.prefixlen > 0:
            used.append(net)
    start = int(prefix[-4:], 16) % 256
    for step in range(256):
        candidate = ipaddress.ip_network('%s.%d.0/24' % (BASE, (start + step) % 256))
        if not any(candidate.overlaps(net) for net in used):
            return candidate
    raise TopologyError('every network %s.X.0/24 is already used on this machine' % BASE)


class Topology(object):
    """The hosts of one run: names, addresses, namespaces and links. Pure data, checked at once."""

    def __init__(self, hosts, prefix, network):
        if not isinstance(prefix, str) or not _RUN.match(prefix):
            raise TopologyError('bad run prefix %r: 1 to 8 lower-case letters and 4 hex digits, e.g. aft1a2b'
                                % (prefix,))
        self.prefix = prefix
        network = ipaddress.ip_network(network)
        if network.prefixlen != 24 or not network.is_private or not str(network).startswith(BASE + '.'):
            raise TopologyError('bad network %s: a %s.X.0/24' % (network, BASE))
        self.network = network
        names = parse_hosts(hosts)
        self.switch_ns = '%s-sw' % prefix
        self.bridge = '%s-br' % prefix
        pp = prefix[-4:]
        self.dead_mac = '02:af:%s:%s:ff:ff' % (pp[:2], pp[2:])    # no interface has it
        self.hosts = collections.OrderedDict()
        for i, name in enumerate(names):
            self.hosts[name] = Host(
                name=name, index=i, ip=str(network.network_address + FIRST_HOST + i),
                mac='02:af:%s:%s:00:%02x' % (pp[:2], pp[2:], i),
                namespace='%s-%s' % (prefix, name), host_if='%s-h%d' % (prefix, i), switch_if='%s-s%d' % (prefix, i))
        for name in (self.bridge,) + tuple(h.switch_if for h in self.hosts.values()):
            if len(name) > IFNAMSIZ:
                raise TopologyError('run prefix %r too long: interface name %s is over %d characters'
                                    % (prefix, name, IFNAMSIZ))

    @classmethod
    def make(cls, hosts=DEFAULT_HOSTS, prefix=None, taken=(), token=None):
        """A new topology. ``token`` (4 hex digits, random if None: pass ``secrets.token_hex(2)``)
        makes the run prefix ``aft<token>``; the network avoids every network in ``taken``."""
        if prefix is None:
            if token is None or not re.match(r'^[0-9a-f]{4}$', str(token)):
                raise TopologyError('bad run token %r: 4 hex digits' % (token,))
            prefix = PROJECT_PREFIX + token
        return cls(hosts, prefix, choose_network(prefix, taken))

    def names(self):
        return list(self.hosts)

    def host(self, name):
        try:
            return self.hosts[name]
        except KeyError:
            raise TopologyError('unknown host %r: the hosts are %s' % (name, ', '.join(self.hosts)))

    def namespaces(self):
        return [self.switch_ns] + [h.namespace for h in self.hosts.values()]

    def to_dict(self):
        return {'prefix': self.prefix, 'network': str(self.network), 'hosts': self.names()}

    @classmethod
    def from_dict(cls, data):
        try:
            return cls(data['hosts'], data['prefix'], data['network'])
        except (KeyError, TypeError) as e:
            raise TopologyError('bad topology record %r: %s' % (data, e))


# -- plans ---------------------------------------------------------------------------------------
def _ip(ns, *args):
    return ['ip', '-n', ns] + list(args)


def _tc(ns, *args):
    return ['tc', '-n', ns] + list(args)


def plan_host_up(top, name):
    """The steps that make one host: its namespace, loopback, cable to the switch, address."""
    h = top.host(name)
    return [
        Step(['ip', 'netns', 'add', h.namespace], ['ip', 'netns', 'del', h.namespace], 'the host %s' % name),
        Step(_ip(h.namespace, 'link', 'set', 'lo', 'up'), None, 'its loopback'),
        Step(['ip', 'link', 'add', h.host_if, 'netns', h.namespace, 'address', h.mac, 'type', 'veth',
              'peer', 'name', h.switch_if, 'netns', top.switch_ns],
             _ip(top.switch_ns, 'link', 'del', h.switch_if), 'its cable (a veth pair) to the switch'),
        Step(_ip(top.switch_ns, 'link', 'set', h.switch_if, 'master', top.bridge), None, 'plugged into the bridge'),
        Step(_ip(top.switch_ns, 'link', 'set', h.switch_if, 'up'), None, 'switch end up'),
        Step(_ip(h.namespace, 'addr', 'add', '%s/%d' % (h.ip, top.network.prefixlen), 'dev', h.host_if), None,
             'its address (and the only route: the private network)'),
        Step(_ip(h.namespace, 'link', 'set', h.host_if, 'up'), None, 'host end up'),
    ]


def plan_up(top):
    """Every step that brings the hosts up, in order. A step's ``undo`` removes what it created."""
    steps = [
        Step(['ip', 'netns', 'add', top.switch_ns], ['ip', 'netns', 'del', top.switch_ns], 'the switch'),
        Step(_ip(top.switch_ns, 'link', 'add', top.bridge, 'type', 'bridge'),
             _ip(top.switch_ns, 'link', 'del', top.bridge), 'its bridge'),
        Step(_ip(top.switch_ns, 'link', 'set', top.bridge, 'up'), None, 'bridge up'),
    ]
    for name in top.hosts:
        steps.extend(plan_host_up(top, name))
    return steps


def undo(steps):
    """The undo of each step that has one, in reverse order."""
    return [s.undo for s in reversed(steps) if s.undo is not None]


def plan_down(top):
    """The command lines that remove everything :func:`plan_up` made (the undo of it, in reverse)."""
    return undo(plan_up(top))


def plan_link_down(top, name):
    h = top.host(name)
    return [Step(_ip(top.switch_ns, 'link', 'set', h.switch_if, 'down'),
                 _ip(top.switch_ns, 'link', 'set', h.switch_if, 'up'), 'cable of %s cut at the switch' % name)]


def plan_link_up(top, name):
    h = top.host(name)
    return [Step(_ip(top.switch_ns, 'link', 'set', h.switch_if, 'up'),
                 _ip(top.switch_ns, 'link', 'set', h.switch_if, 'down'), 'cable of %s plugged in again' % name)]


def plan_pair_partition(top, a, b):
    """a and b no longer hear each other (both still hear everybody else)."""
    ha, hb = _pair(top, a, b)
    return [Step(_ip(x.namespace, 'neigh', 'replace', y.ip, 'lladdr', top.dead_mac, 'nud', 'permanent',
                     'dev', x.host_if),
                 _ip(x.namespace, 'neigh', 'del', y.ip, 'dev', x.host_if),
                 '%s sends what is meant for %s to no one' % (x.name, y.name)) for x, y in ((ha, hb), (hb, ha))]


def plan_pair_heal(top, a, b):
    ha, hb = _pair(top, a, b)
    return [Step(_ip(x.namespace, 'neigh', 'del', y.ip, 'dev', x.host_if), None,
                 '%s finds %s again (ARP)' % (x.name, y.name)) for x, y in ((ha, hb), (hb, ha))]


def _pair(top, a, b):
    ha, hb = top.host(a), top.host(b)
    if a == b:
        raise TopologyError('a pair partition needs two different hosts, got %r twice' % a)
    return ha, hb


def burst_bytes(kbit):
    """The token bucket's burst for a limit of kbit kbit/s: 20 ms of traffic and at least two full frames."""
    return max(2 * 1514, check_kbit(kbit) * 1000 // 8 // 50)


# What a link's rate limit sends first: packets whose IP TOS says low delay (0x10), which the crash
# detectors' heartbeat connections carry (aft_ftm.ros.qos). Behind a full token bucket the heartbeats
# waited with the data, were dropped past the bucket's latency and resent by TCP 200 ms or more later:
# a 500 ms detector fenced a healthy site (session 50). A network with QoS gives them priority too.
URGENT_TOS = 0x10


def queue_bytes(kbit):
    """The bytes a class's queue holds under a rate limit: QUEUE_LATENCY of traffic and a burst, what
    the single token bucket held before the classes (tbf's latency 100 ms)."""
    return int(check_kbit(kbit) * 1000 / 8 * QUEUE_LATENCY) + burst_bytes(kbit)


def plan_rate(top, name, kbit):
    """A rate limit on both ends of the host's cable, its upload (host end) and download (switch end):
    a hierarchical token bucket (htb; this kernel has no prio qdisc) of two classes sharing the rate,
    the urgent one (IP TOS low delay: the heartbeats) served first, each with a queue of what the
    bucket alone held (:func:`queue_bytes`). A limit already there is replaced (htb cannot be changed
    in place: the root is reset first)."""
    h = top.host(name)
    burst = str(burst_bytes(kbit))
    limit = str(queue_bytes(kbit))
    # htb serves every class under its own rate before any that borrows, whatever their prio: the urgent
    # class is assured nearly the whole rate (a review: at half of it, heartbeats beyond it waited behind
    # the data again, as under the campaign's 200 kbit/s), the data a tenth, borrowing what is left.
    # The two rates add up to the limit, never more.
    bulk = max(1, kbit // 10)
    urgent = kbit - bulk
    steps = []
    for ns, dev, what in ((h.namespace, h.host_if, 'upload of %s' % name),
                          (top.switch_ns, h.switch_if, 'download of %s' % name)):
        def tc(*args):
            return _tc(ns, *args[:2] + ('dev', dev) + args[2:])

        def cls(parent, classid, rate, *more):
            return tc('class', 'replace', 'parent', parent, 'classid', classid, 'htb', 'rate', '%dkbit' % rate,
                      'ceil', '%dkbit' % kbit, 'burst', burst, 'cburst', burst, *more)
        steps += [
            Step(tc('qdisc', 'replace', 'root', 'pfifo_fast'), None, '%s: any limit before removed' % what),
            Step(tc('qdisc', 'replace', 'root', 'handle', '1:', 'htb', 'default', '20'),
                 tc('qdisc', 'del', 'root'), '%s limited to %d kbit/s' % (what, kbit)),
            Step(cls('1:', '1:1', kbit), None, '%s: the whole rate' % what),
            Step(cls('1:1', '1:10', urgent, 'prio', '0'), None, '%s: the urgent class, served first' % what),
            Step(cls('1:1', '1:20', bulk, 'prio', '1'), None, '%s: the rest' % what),
            Step(tc('qdisc', 'replace', 'parent', '1:10', 'handle', '10:', 'bfifo', 'limit', limit), None,
                 '%s: the urgent queue holds %s bytes' % (what, limit)),
            Step(tc('qdisc', 'replace', 'parent', '1:20', 'handle', '20:', 'bfifo', 'limit', limit), None,
                 '%s: the data\'s queue holds %s bytes' % (what, limit)),
            Step(tc('filter', 'replace', 'parent', '1:', 'protocol', 'ip', 'prio', '1', 'u32', 'match', 'ip', 'tos',
                    '0x%02x' % URGENT_TOS, '0xfc', 'flowid', '1:10'), None, '%s: low-delay packets urgent' % what)]
    return steps


def plan_unrate(top, name):
    h = top.host(name)
    return [Step(_tc(ns, 'qdisc', 'del', 'dev', dev, 'root'), None, 'limit removed')
            for ns, dev in ((h.namespace, h.host_if), (top.switch_ns, h.switch_if))]


def plan_power_off(top, name, pids):
    """Link down FIRST (nothing more leaves the host), then every process stopped, then killed.
    ``pids``: every process of the host, listed by the caller."""
    pids = sorted(set(int(p) for p in pids))
    return plan_link_down(top, name) + [
        Signal(signal.SIGSTOP, pids, 'no process of %s runs a step more than another' % name),
        Signal(signal.SIGKILL, pids, 'every process of %s dies' % name)]


def plan_power_on(top, name):
    """The host made again from nothing: old namespace removed (with every socket the dead processes
    left), a new one made, with the same address."""
    return [Step(argv, None, 'old %s removed' % name) for argv in undo(plan_host_up(top, name))] \
        + plan_host_up(top, name)


def plan_forget_dead_entries(top, name, others):
    """Every host of ``others`` finds ``name`` again: a dead ARP entry left there by a pair partition
    that ended with ``name``'s power loss is removed (a no-op where there is none)."""
    host = top.host(name)
    return [Step(_ip(top.host(o).namespace, 'neigh', 'flush', 'to', host.ip, 'dev', top.host(o).host_if, 'nud',
                     'permanent'), None, '%s finds %s again (no dead ARP entry left)' % (o, name))
            for o in others if o != name]


def plan_freeze(pids, seconds):
    """SIGSTOP now, SIGCONT after ``seconds`` (the caller's timer)."""
    seconds = check_seconds(seconds)
    pids = sorted(set(int(p) for p in pids))
    return (Signal(signal.SIGSTOP, pids, 'frozen for %g s' % seconds), seconds,
            Signal(signal.SIGCONT, pids, 'thawed'))


# -- the hosts' state machine ---------------------------------------------------------------------
class HostState(enum.Enum):
    UP = 'up'              # linked to the switch
    CUT = 'partitioned'    # cable cut: its processes run, nothing goes in or out
    OFF = 'off'            # powered off: cable cut and every process killed


EDGES = {
    (HostState.UP, HostState.CUT): 'partition: its link goes down, its processes go on',
    (HostState.CUT, HostState.UP): 'heal: its link comes up again',
    (HostState.UP, HostState.OFF): 'power loss: link down first, then every process killed',
    (HostState.CUT, HostState.OFF): 'power loss of a partitioned host: every process killed',
    (HostState.OFF, HostState.UP): 'power on: the host made again from nothing, linked',
}


class Network(object):
    """The state of the hosts of one topology: each host's state, rate limits and pair partitions.

    Each fault method checks the fault applies, and returns its plan; the caller carries the plan
    out, then calls :meth:`commit` with the same plan's changes. State changes only in _change().
    """

    def __init__(self, topology):
        self.topology = topology
        self.state = collections.OrderedDict((name, HostState.UP) for name in topology.hosts)
        self.rates = {}           # host -> kbit
        self.pairs = set()        # frozenset({a, b})

    # each returns (plan, changes); commit(changes) after the plan was carried out
    def partition(self, name):
        self._need(name, (HostState.UP,), 'partition')
        return plan_link_down(self.topology, name), [('state', name, HostState.CUT)]

    def heal(self, name):
        self._need(name, (HostState.CUT,), 'heal')
        return plan_link_up(self.topology, name), [('state', name, HostState.UP)]

    def partition_pair(self, a, b):
        plan = plan_pair_partition(self.topology, a, b)
        for name in (a, b):
            self._need(name, (HostState.UP, HostState.CUT), 'pair partition')
        if frozenset((a, b)) in self.pairs:
            raise FaultError('%s and %s are already partitioned from each other' % (a, b))
        return plan, [('pair', frozenset((a, b)), True)]

    def heal_pair(self, a, b):
        plan = plan_pair_heal(self.topology, a, b)
        if frozenset((a, b)) not in self.pairs:
            raise FaultError('%s and %s are not partitioned from each other' % (a, b))
        for name in (a, b):
            self._need(name, (HostState.UP, HostState.CUT), 'pair heal')
        return plan, [('pair', frozenset((a, b)), False)]

    def rate(self, name, kbit):
        self._need(name, (HostState.UP, HostState.CUT), 'rate limit')
        kbit = check_kbit(kbit)
        return plan_rate(self.topology, name, kbit), [('rate', name, kbit)]

    def unrate(self, name):
        self._need(name, (HostState.UP, HostState.CUT), 'rate limit removal')
        if name not in self.rates:
            raise FaultError('host %s has no rate limit to remove' % name)
        return plan_unrate(self.topology, name), [('rate', name, None)]

    def power_off(self, name, pids):
        self._need(name, (HostState.UP, HostState.CUT), 'power off')
        changes = [('state', name, HostState.OFF), ('rate', name, None)]
        changes += [('pair', pair, False) for pair in self.pairs if name in pair]
        return plan_power_off(self.topology, name, pids), changes

    def power_on(self, name):
        self._need(name, (HostState.OFF,), 'power on')
        # A pair partition ended by the power loss left a dead ARP entry for this host in its peer:
        # the host back on with the same address must be reachable again.
        others = [o for o in self.topology.hosts if self.state[o] is not HostState.OFF]
        return plan_power_on(self.topology, name) + plan_forget_dead_entries(self.topology, name, others), \
            [('state', name, HostState.UP)]

    def runs(self, name):
        """Whether processes can be started in the host (it is not off)."""
        self.topology.host(name)
        return self.state[name] is not HostState.OFF

    def commit(self, changes):
        for kind, key, value in changes:
            if kind == 'state':
                self._change(key, value)
            elif kind == 'rate':
                if value is None:
                    self.rates.pop(key, None)
                else:
                    self.rates[key] = value
            elif kind == 'pair':
                (self.pairs.add if value else self.pairs.discard)(key)
            else:
                raise ValueError('unknown change %r' % (kind,))

    def _need(self, name, states, fault):
        self.topology.host(name)
        if self.state[name] not in states:
            raise FaultError('cannot %s host %s: it is %s' % (fault, name, self.state[name].value))

    def _change(self, name, new):
        old = self.state[name]
        if (old, new) not in EDGES:
            raise FaultError('host %s cannot go from %s to %s' % (name, old.value, new.value))
        self.state[name] = new

    def to_dict(self):
        return {'topology': self.topology.to_dict(),
                'state': dict((n, s.value) for n, s in self.state.items()),
                'rates': dict(self.rates), 'pairs': sorted(sorted(p) for p in self.pairs)}

    @classmethod
    def from_dict(cls, data):
        try:
            net = cls(Topology.from_dict(data['topology']))
            for name, value in data['state'].items():
                net.topology.host(name)
                net.state[name] = HostState(value)
            for name, kbit in data['rates'].items():
                net.topology.host(name)
                net.rates[name] = check_kbit(kbit)
            for a, b in data['pairs']:
                _pair(net.topology, a, b)
                net.pairs.add(frozenset((a, b)))
        except (KeyError, TypeError, ValueError) as e:
            raise TopologyError('bad hosts record: %s' % e)
        return net

    def describe(self):
        """Lines for a person: each host, its address, namespace, state and limit."""
        lines = ['run %s, network %s, switch namespace %s (bridge %s)'
                 % (self.topology.prefix, self.topology.network, self.topology.switch_ns, self.topology.bridge)]
        for name, h in self.topology.hosts.items():
            extra = ' rate %d kbit/s' % self.rates[name] if name in self.rates else ''
            lines.append('  %-10s %-15s %-22s %s%s' % (name, h.ip, h.namespace, self.state[name].value, extra))
        for pair in sorted(sorted(p) for p in self.pairs):
            lines.append('  pair partition: %s | %s' % tuple(pair))
        return lines
