"""The campaign's fault schedule: a seeded draw from a catalogue of faults, with the rules that keep a
run meaningful. No ROS.

The catalogue (CATALOGUE) names every fault of issue 15's campaign: SIGKILL of any single node,
freeze of a node or a site (50 ms to 3 s), site power loss, partitions of a host or a pair of hosts
and their healing, bandwidth drops, adaptations, the ROS master's death. Each entry says what a
backend must offer to inject it (``needs``): ``process`` (signals to a site's processes: one host
suffices), ``hosts`` (emulated hosts: links and rates, aft_ftm.hosts_exec), ``master`` (a ROS master
that can be restarted under running nodes), ``adapt`` (adaptable sites and the adaptation engine:
an update of the primary's After, which a re-joining site undoes by coming back with its own),
``adapt_mechanism`` (switches and compositions: they change both sites' mechanism, so a failed site
must come back with the mechanism its peer runs now). A schedule is drawn only from what the
backend offers.

Rules (each checked by tests/unit/test_schedule.py):
- every entry of the catalogue the backend offers takes its turn: faults are dealt from a shuffled
  deck of the whole catalogue, reshuffled once dealt, so N faults cover it N // len times over;
- one fault at a time, each followed by its healing: the runner heals it (SIGCONT, link up, the
  failed site re-joined, the Proxy or the witness restarted) and waits until the pair is whole again
  before the next: at most one replica is ever down, and a re-join is never itself interrupted;
- targets are roles (the primary, the backup), resolved by the runner when the fault comes;
- the run is cut in segments, one deployment each, taking the mechanisms (PBR, LFR, ...) in turn,
  so that every mechanism runs its share of the faults;
- the same seed gives the same schedule.
"""
import collections
import random

REPLICA_NODES = ('protocol', 'before', 'proceed', 'after', 'bank_server', 'crash_detector', 'recovery')
ROLES = ('primary', 'backup')
HOSTS = ('primary', 'backup', 'client', 'witness')
PAIRS = (('primary', 'backup'), ('primary', 'witness'), ('backup', 'witness'), ('client', 'primary'),
         ('client', 'backup'), ('client', 'witness'))
FREEZE_RANGE = (0.05, 3.0)
PARTITION_RANGE = (0.1, 3.0)
BANDWIDTH_RANGE = (1.0, 5.0)   # seconds the rate limit holds
MASTER_DOWN_RANGE = (0.1, 3.0)   # seconds the killed ROS master stays down before its restart
GAP_RANGE = (0.2, 0.8)         # seconds of undisturbed load before each fault

Entry = collections.namedtuple('Entry', 'kind target needs')


def _catalogue():
    entries = []
    for role in ROLES:
        for node in REPLICA_NODES:
            entries.append(Entry('kill', '%s/%s' % (role, node), 'process'))
            entries.append(Entry('freeze_node', '%s/%s' % (role, node), 'process'))
        entries.append(Entry('freeze_site', role, 'process'))
        entries.append(Entry('power_loss', role, 'process'))
    entries += [Entry('kill', 'proxy', 'process'), Entry('freeze_node', 'proxy', 'process'),
                Entry('kill', 'witness', 'process'), Entry('freeze_node', 'witness', 'process'),
                Entry('kill', 'ros_master', 'master')]
    entries += [Entry('partition', host, 'hosts') for host in HOSTS]
    entries += [Entry('partition_pair', '%s-%s' % pair, 'hosts') for pair in PAIRS]
    entries += [Entry('bandwidth', host, 'hosts') for host in ('primary', 'backup')]
    entries += [Entry('adapt', 'update', 'adapt')]
    entries += [Entry('adapt', name, 'adapt_mechanism') for name in ('switch', 'compose')]
    return tuple(entries)


CATALOGUE = _catalogue()
NEEDS = ('process', 'hosts', 'master', 'adapt', 'adapt_mechanism')


class ScheduleError(ValueError):
    """A schedule that cannot be made as asked (named)."""


Fault = collections.namedtuple('Fault', 'index segment mechanism kind target duration gap')
Fault.__doc__ = """One fault: index (0..N-1), segment (its deployment), mechanism (of that deployment),
kind and target (a catalogue entry), duration (s: a freeze, a partition or a rate limit held that long,
the time a killed ROS master stays down; 0 otherwise), gap (s of undisturbed load before it)."""


def catalogue(offered):
    """The catalogue entries a backend offering `offered` (a set of NEEDS) can inject."""
    unknown = set(offered) - set(NEEDS)
    if unknown:
        raise ScheduleError('unknown capabilities %s (known: %s)' % (sorted(unknown), ', '.join(NEEDS)))
    return [entry for entry in CATALOGUE if entry.needs in offered]


def _duration(rng, kind, target=None):
    if kind == 'freeze_node' or kind == 'freeze_site':
        low, high = FREEZE_RANGE
    elif kind in ('partition', 'partition_pair'):
        low, high = PARTITION_RANGE
    elif kind == 'bandwidth':
        low, high = BANDWIDTH_RANGE
    elif (kind, target) == ('kill', 'ros_master'):
        low, high = MASTER_DOWN_RANGE
    else:
        return 0.0
    # Log-uniform: short freezes (under detection) as often as long ones (past it).
    return round(low * (high / low) ** rng.random(), 3)


def make(faults, seed, offered=('process',), mechanisms=('pbr', 'lfr'), per_segment=25):
    """The schedule of `faults` faults for `seed`: a list of Fault.

    offered: what the backend can inject (see NEEDS); mechanisms: taken in turn, one per segment of
    per_segment faults. Raises ScheduleError on a bad request."""
    if not isinstance(faults, int) or faults < 0:
        raise ScheduleError('the number of faults must be an integer >= 0, got %r' % (faults,))
    if per_segment < 1:
        raise ScheduleError('per_segment must be >= 1, got %r' % (per_segment,))
    if not mechanisms:
        raise ScheduleError('at least one mechanism is needed')
    entries = catalogue(offered)
    if not entries:
        raise ScheduleError('the backend offers nothing of the catalogue (offered: %s)' % sorted(offered))
    rng = random.Random(seed)
    deck, schedule = [], []
    for index in range(faults):
        if not deck:
            deck = list(entries)
            rng.shuffle(deck)
        entry = deck.pop()
        segment = index // per_segment
        schedule.append(Fault(index, segment, mechanisms[segment % len(mechanisms)], entry.kind, entry.target,
                              _duration(rng, entry.kind, entry.target), round(rng.uniform(*GAP_RANGE), 3)))
    return schedule


def describe(fault):
    """A fault in a few words, e.g. 'freeze_node primary/after 0.42 s'."""
    return '%s %s%s' % (fault.kind, fault.target, ' %.2f s' % fault.duration if fault.duration else '')


def resolve_role(target, primary, backup):
    """A target's role ('primary/after', 'backup', ...) as the site serving it now ('master/after').
    Targets without a role are returned unchanged."""
    role, _, rest = target.partition('/')
    site = {'primary': primary, 'backup': backup}.get(role)
    if site is None:
        return target
    return site + ('/' + rest if rest else '')
