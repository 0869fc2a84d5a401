"""The mechanisms' assumptions, as data (paper Table I): fault model F, application
characteristics A, resources R. The adaptation work selects mechanisms from this table."""
import collections

from .errors import ConfigError

# Fault kinds, the vocabulary of F.
CRASH = 'crash'                      # a replica's machine or process stops (fail-silent)
TRANSIENT_VALUE = 'transient_value'  # one execution computes a wrong value (bit flip, radiation)
SAFETY_VIOLATION = 'safety_violation'  # a reply (or request) breaks a user-stated safety property
EAVESDROPPING = 'eavesdropping'      # a passive attacker reads messages
TAMPERING = 'tampering'              # an attacker alters, forges or replays messages

Mechanism = collections.namedtuple('Mechanism', [
    'name',            # short name used in launch files and scripts
    'title',
    'faults',          # F: the fault kinds it tolerates (or detects, for assertions)
    'deterministic',   # A: needs a deterministic server
    'state_access',    # A: needs getState/setState on the server
    'bandwidth',       # R: extra traffic between sites: 'nil', 'low', 'high'
    'cpus',            # R: independent processing units needed
])

TABLE = collections.OrderedDict((m.name, m) for m in [
    Mechanism('pbr', 'Primary-Backup Replication', frozenset([CRASH]), False, True, 'high', 2),
    Mechanism('lfr', 'Leader-Follower Replication', frozenset([CRASH]), True, False, 'low', 2),
    Mechanism('tr', 'Time Redundancy', frozenset([TRANSIENT_VALUE]), True, True, 'nil', 1),
    Mechanism('ad', 'Assertion & Duplex', frozenset([SAFETY_VIOLATION]), False, False, 'nil', 1),
    Mechanism('sec', 'Cipher and signature (SEC)', frozenset([EAVESDROPPING, TAMPERING]), False, False, 'low', 1),
])

_BANDWIDTH = {'nil': 0, 'low': 1, 'high': 2}


def mechanism(name):
    try:
        return TABLE[name]
    except KeyError:
        raise ConfigError('unknown mechanism %r (known: %s)' % (name, ', '.join(TABLE)))


def compose(names):
    """The assumptions of a composition, outermost first (e.g. ['pbr', 'tr']): the union of the
    fault models, the strictest application needs, and the largest resource needs."""
    parts = [mechanism(n) for n in names]
    if not parts:
        raise ConfigError('a composition needs at least one mechanism')
    return Mechanism('+'.join(m.name for m in parts), ' + '.join(m.title for m in parts),
                     frozenset().union(*(m.faults for m in parts)),
                     any(m.deterministic for m in parts), any(m.state_access for m in parts),
                     max((m.bandwidth for m in parts), key=_BANDWIDTH.get), max(m.cpus for m in parts))


def check_application(name, deterministic, state_access):
    """Raise ConfigError if the application's characteristics (A) do not meet mechanism name's needs."""
    m = mechanism(name)
    if m.deterministic and not deterministic:
        raise ConfigError('%s needs a deterministic server, and this one is declared non-deterministic: '
                          'its replicas would diverge (use pbr, which does not need determinism)' % m.title)
    if m.state_access and not state_access:
        raise ConfigError('%s needs access to the server state (getState/setState), and this server '
                          'declares none (use lfr)' % m.title)
    return m
