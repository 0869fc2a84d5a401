"""The change model (F, A, R) and the selection of a consistent composition of mechanisms.

Section 4.2 of the paper: at any time the mechanisms attached to a server must be consistent
with the current fault model F, application characteristics A and resources R; when a change
makes the running composition inconsistent, a new one is selected, the fault model first,
then A, then R, with a cost on R to choose among the solutions left. The needs of each
mechanism come only from :data:`aft_ftm.mechanisms.TABLE` (Table I): nothing here is
special-cased by mechanism name, except the nesting order of a composition.

Pure logic: no rospy, no clock.
"""
import collections
import itertools
import math
import numbers

from . import mechanisms
from .errors import ConfigError
from .mechanisms import CRASH, EAVESDROPPING, SAFETY_VIOLATION, TAMPERING, TRANSIENT_VALUE

FAULT_KINDS = frozenset([CRASH, TRANSIENT_VALUE, SAFETY_VIOLATION, EAVESDROPPING, TAMPERING])

# Bandwidth levels of Table I, from least to most demanding.
BANDWIDTH_RANK = {'nil': 0, 'low': 1, 'high': 2}
DEFAULT_HIGH = 1e6   # bytes/s a link needs to carry a 'high' mechanism (PBR's checkpoints)
DEFAULT_LOW = 1e4    # bytes/s a link needs to carry a 'low' mechanism (LFR's notifications, SEC)

# Composition slots, outermost first: a candidate takes at most one mechanism per slot.
# SEC is only considered when F contains an attack it counters.
_SEC_FAULTS = frozenset([EAVESDROPPING, TAMPERING])
_SLOTS = (('sec',), ('pbr', 'lfr'), ('tr',), ('ad',))

NO_MECHANISM = 'none'   # name of the empty composition

# Alarm kinds (aft_msgs/Alarm.kind) -> fault kind they show has happened.
ALARM_FAULTS = {
    'value_fault_masked': TRANSIENT_VALUE,   # TR: one execution disagreed with the majority
    'no_majority': TRANSIENT_VALUE,          # TR: executions disagreed, no majority
    'assertion_violated': SAFETY_VIOLATION,  # A&D
    'replay': TAMPERING,                     # SEC
    'tampered': TAMPERING,
    'bad_signature': TAMPERING,
    'unsigned': TAMPERING,
    'forged': TAMPERING,
    'unknown_party': TAMPERING,
}


SEC_UNAVAILABLE = ('ca_silent', 'ca_unreachable')
# A request an earlier run of a gate let through, sent after the gate started again: an honest Proxy's
# re-send of a call in flight at the restart looks the same as a replay of it. Refused either way. A
# replay log that cannot be written is a fault of this host's disk. A peer gate's floors not learned at a
# join (its site gone, slow) is an availability fault. An origin that has not answered a gate's freshness
# challenge may be an attacker's replays, or an honest client whose request another gate answered first.
SEC_NOT_ATTACKS = SEC_UNAVAILABLE + ('earlier_run', 'replay_log', 'floors_unavailable', 'unanswered_challenge')


def observed_fault(mechanism, kind):
    """The fault kind an alarm (mechanism, kind) shows has happened, or None if it shows none.
    Every alarm raised by SEC is an attack on the messages (tampering), but those that say the
    certification authority is silent or does not answer (an unavailable CA is no attack), and a
    request refused as let through before the gate started again (SEC_NOT_ATTACKS)."""
    if mechanism == 'sec':
        return None if kind in SEC_NOT_ATTACKS else TAMPERING
    return ALARM_FAULTS.get(kind)


# -- the model --------------------------------------------------------------------------------------

class Application(collections.namedtuple('Application', ['deterministic', 'state_access'])):
    """A: the server's characteristics (a black box: declared, never inferred)."""
    __slots__ = ()

    def __new__(cls, deterministic, state_access):
        for field, value in (('deterministic', deterministic), ('state_access', state_access)):
            if not isinstance(value, bool):
                raise ConfigError('application %s must be true or false, got %r' % (field, value))
        return super(Application, cls).__new__(cls, deterministic, state_access)

    def to_dict(self):
        return {'deterministic': self.deterministic, 'state_access': self.state_access}


class Resources(collections.namedtuple('Resources', ['cpus', 'bandwidth'])):
    """R: ``cpus`` independent sites (processing units) alive; ``bandwidth`` bytes/s available
    between sites, None when unknown (treated as unlimited)."""
    __slots__ = ()

    def __new__(cls, cpus, bandwidth=None):
        if isinstance(cpus, bool) or not isinstance(cpus, numbers.Integral) or cpus < 0:
            raise ConfigError('resources cpus must be an integer >= 0, got %r' % (cpus,))
        return super(Resources, cls).__new__(cls, int(cpus), _check_bandwidth(bandwidth))

    def to_dict(self):
        return {'cpus': self.cpus, 'bandwidth': self.bandwidth}


class ChangeModel(collections.namedtuple('ChangeModel', ['faults', 'application', 'resources'])):
    """(F, A, R): the fault kinds to tolerate, the application characteristics, the resources."""
    __slots__ = ()

    def __new__(cls, faults, application, resources):
        faults = check_faults(faults)
        if not isinstance(application, Application):
            raise ConfigError('change model application must be an Application, got %r' % (application,))
        if not isinstance(resources, Resources):
            raise ConfigError('change model resources must be a Resources, got %r' % (resources,))
        return super(ChangeModel, cls).__new__(cls, faults, application, resources)

    def to_dict(self):
        return {'faults': sorted(self.faults), 'application': self.application.to_dict(),
                'resources': self.resources.to_dict()}


def check_faults(faults):
    """Return faults as a frozenset of known fault kinds, or raise ConfigError naming the unknown."""
    if isinstance(faults, str):
        raise ConfigError('faults must be a collection of fault kinds, got the string %r' % (faults,))
    try:
        faults = frozenset(faults)
    except TypeError:
        raise ConfigError('faults must be a collection of fault kinds, got %r' % (faults,))
    unknown = faults - FAULT_KINDS
    if unknown:
        raise ConfigError('unknown fault kind(s) %s (known: %s)'
                          % (', '.join(sorted(map(repr, unknown))), ', '.join(sorted(FAULT_KINDS))))
    return faults


def _check_bandwidth(bandwidth):
    if bandwidth is None:
        return None
    if (isinstance(bandwidth, bool) or not isinstance(bandwidth, numbers.Real)
            or math.isnan(bandwidth) or bandwidth < 0):
        raise ConfigError('bandwidth must be a number of bytes/s >= 0 or None (unknown), got %r'
                          % (bandwidth,))
    return float(bandwidth)


def _check_thresholds(high, low):
    for name, value in (('high', high), ('low', low)):
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not value > 0:
            raise ConfigError('bandwidth threshold %s must be a number > 0, got %r' % (name, value))
    if low > high:
        raise ConfigError('bandwidth threshold low (%r) must not exceed high (%r)' % (low, high))


def bandwidth_level(bytes_per_s, high=DEFAULT_HIGH, low=DEFAULT_LOW):
    """The most demanding Table I bandwidth level a link of bytes_per_s can carry:
    'high' (>= high), 'low' (>= low) or 'nil'. None (unknown) counts as unlimited: 'high'."""
    _check_thresholds(high, low)
    bytes_per_s = _check_bandwidth(bytes_per_s)
    if bytes_per_s is None or bytes_per_s >= high:
        return 'high'
    if bytes_per_s >= low:
        return 'low'
    return 'nil'


def bandwidth_text(bytes_per_s):
    return 'unknown (unlimited)' if bytes_per_s is None else '%g B/s' % bytes_per_s


# -- needs of a composition against the model -------------------------------------------------------

def _unmet_needs(names, model, high, low):
    """Why the composition's A and R needs are not met by the model: a list of phrases."""
    why, short = [], []
    app, res = model.application, model.resources
    level = bandwidth_level(res.bandwidth, high, low)
    for m in (mechanisms.mechanism(n) for n in names):
        if m.deterministic and not app.deterministic:
            why.append('%s needs a deterministic server and this one is declared non-deterministic' % m.name)
        if m.state_access and not app.state_access:
            why.append('%s needs access to the server state (getState/setState) and this server '
                       'declares none' % m.name)
        if m.cpus > res.cpus:
            why.append('%s needs %d CPUs and %s alive' % (m.name, m.cpus, _sites_text(res.cpus)))
        if BANDWIDTH_RANK[m.bandwidth] > BANDWIDTH_RANK[level]:
            short.append('%s needs %s' % (m.name, m.bandwidth))
    if short:
        why.append("bandwidth between sites %s supports only '%s' mechanisms: %s"
                   % (bandwidth_text(res.bandwidth), level, ', '.join(short)))
    return why


def _sites_text(count):
    return '%d site%s %s' % (count, '' if count == 1 else 's', 'is' if count == 1 else 'are')


def _faults_of(names):
    return mechanisms.compose(names).faults if names else frozenset()


def _cost(names):
    """(cpus, bandwidth rank, number of mechanisms, name): the lower the cheaper."""
    if not names:
        return (0, 0, 0, NO_MECHANISM)
    c = mechanisms.compose(names)
    return (c.cpus, BANDWIDTH_RANK[c.bandwidth], len(names), c.name)


def _needs_text(names):
    if not names:
        return 'no resources'
    c = mechanisms.compose(names)
    return '%d CPU%s, %s bandwidth' % (c.cpus, '' if c.cpus == 1 else 's', c.bandwidth)


def kinds_text(faults):
    return ', '.join(sorted(faults)) or 'nothing'


def composition_name(names):
    return '+'.join(names) if names else NO_MECHANISM


def consistent(running, model, high=DEFAULT_HIGH, low=DEFAULT_LOW):
    """(ok, reason): does the running composition (names, outermost first) still cover F, with
    its A and R needs met? Being more expensive than another choice does not make it inconsistent."""
    running = tuple(running)
    for n in running:
        mechanisms.mechanism(n)   # ConfigError on an unknown name
    _check_thresholds(high, low)
    name = composition_name(running)
    why = []
    missing = model.faults - _faults_of(running)
    if missing:
        why.append('%s does not cover %s' % (name, kinds_text(missing)))
    why.extend(_unmet_needs(running, model, high, low))
    if why:
        return False, '; '.join(why)
    return True, '%s covers %s and its needs (%s) are met' % (name, kinds_text(model.faults), _needs_text(running))


# -- selection --------------------------------------------------------------------------------------

class Selection(collections.namedtuple('Selection', ['mechanisms', 'name', 'covered', 'uncovered',
                                                     'degraded', 'reason'])):
    """The chosen composition, outermost first. ``covered``: the fault kinds of F it tolerates
    (after a degradation, the kinds it was chosen for instead); ``uncovered``: the kinds of the
    model's F it does not tolerate; ``degraded``: something of F is left uncovered."""
    __slots__ = ()

    def to_dict(self):
        return {'mechanisms': list(self.mechanisms), 'name': self.name, 'covered': sorted(self.covered),
                'uncovered': sorted(self.uncovered), 'degraded': self.degraded, 'reason': self.reason}


def candidates(faults):
    """Every non-empty composition in the nesting order sec, replication, tr, ad."""
    slots = [s for s in _SLOTS if s != ('sec',) or faults & _SEC_FAULTS]
    result = []
    for choice in itertools.product(*[(None,) + s for s in slots]):
        names = tuple(n for n in choice if n is not None)
        if names:
            result.append(names)
    return result


def _minimal(names, faults):
    """True if no mechanism can be removed from names while still covering the same part of faults."""
    covered = _faults_of(names) & faults
    return all(_faults_of(names[:i] + names[i + 1:]) & faults != covered for i in range(len(names)))


def _keeps(names, keep):
    """True if names keeps the composition keep (a tuple, or None) as its outermost part: keep itself,
    or keep with more composed inside."""
    return bool(keep) and tuple(names[:len(keep)]) == keep


def _best(model, faults, high, low, allowed=None, keep=None):
    """(names, covered, reason) for the given F: the cheapest feasible composition covering faults,
    else the feasible one covering most of it (the empty composition when none covers anything).
    ``allowed``: when given, only the compositions it accepts are candidates; ``keep``: among those
    covering as much, the ones keeping it (see :func:`select`) come before the cheaper ones."""
    pool = candidates(faults)
    if keep and keep not in pool:
        pool.append(keep)   # e.g. a running sec when F holds no attack: judged like the others
    feasible = [c for c in pool if not _unmet_needs(c, model, high, low) and (allowed is None or allowed(c))]
    helpful = tuple(n for n, m in mechanisms.TABLE.items() if m.faults & faults)
    excluded = _unmet_needs(helpful, model, high, low)   # why the mechanisms that would help are ruled out
    prefix = '; '.join(excluded) + '; ' if excluded else ''
    covering = sorted((c for c in feasible if faults <= _faults_of(c)), key=lambda c: (not _keeps(c, keep), _cost(c)))
    if covering:
        best = covering[0]
        options = [c for c in covering if _minimal(c, faults)]
        choice = 'cheapest consistent choice'
        if _keeps(best, keep) and best != keep:
            choice += ' keeping %s:' % composition_name(keep)
        if len(options) > 1:
            listed = ', '.join('%s (%s)' % (composition_name(c), _needs_text(c)) for c in options)
            text = 'covering %s: %s; %s %s' % (kinds_text(faults), listed, choice, composition_name(best))
        else:
            text = '%s covers %s: %s %s (%s)' % (
                composition_name(best), kinds_text(faults), choice, composition_name(best), _needs_text(best))
        return best, faults, prefix + text
    # The empty composition stays a candidate here whatever ``allowed`` says: it stands for "nothing
    # considered covers any of it" (the caller tells whether it can get there).
    partial = sorted([()] + feasible, key=lambda c: (-len(_faults_of(c) & faults), not _keeps(c, keep), _cost(c)))
    best = partial[0]
    covered = _faults_of(best) & faults
    among = '' if allowed is None else ' among those allowed'
    text = 'no consistent composition%s covers %s' % (among, kinds_text(faults))
    if covered:
        text += '; best partial choice %s covers %s, leaves %s uncovered' % (
            composition_name(best), kinds_text(covered), kinds_text(faults - covered))
    elif best:
        text += '; none%s covers any of it: %s is kept' % (among, composition_name(best))
    else:
        text += '; no consistent mechanism%s covers any of it: none runs' % among
    return best, covered, prefix + text


def select(model, high=DEFAULT_HIGH, low=DEFAULT_LOW, allowed=None, keep=None):
    """The cheapest composition consistent with model.

    Candidates: every composition in the nesting order sec, replication (pbr | lfr), tr, ad (sec
    only when F holds eavesdropping or tampering) whose faults cover F and whose A and R needs
    are met; cheapest by (cpus, bandwidth nil < low < high, number of mechanisms, name).
    With fewer CPUs than replication needs, crash is replaced by transient_value (the survivor
    masks its own transient faults) and the selection is marked degraded. If nothing covers F,
    the consistent composition covering most of it (cheapest on ties; none when it covers
    nothing) is chosen, degraded, with the uncovered kinds named.

    ``allowed`` (optional): a predicate on compositions (tuples of names); only those it accepts
    are candidates (the monitor passes the running one and those a shipped adaptation reaches
    from it). The empty composition is still returned when none of them covers any of F.
    ``keep`` (optional): the running composition; among candidates covering as much of F, those
    keeping it as their outermost part (it, or it with more composed inside, e.g. pbr+tr for pbr)
    come first, before the cheaper ones: a mechanism is not changed merely because another is
    cheaper."""
    if not isinstance(model, ChangeModel):
        raise ConfigError('select needs a ChangeModel, got %r' % (model,))
    _check_thresholds(high, low)
    keep = tuple(keep) if keep else None
    faults = model.faults
    if not faults:
        return Selection((), NO_MECHANISM, frozenset(), frozenset(), False,
                         'the fault model is empty: no mechanism is needed')
    prefix = ''
    crash_cpus = min(m.cpus for m in mechanisms.TABLE.values() if CRASH in m.faults)
    if CRASH in faults and model.resources.cpus < crash_cpus:
        # Crash cannot be tolerated without a second site: what is left is masking the transient
        # faults of the remaining processor (time redundancy on the survivor).
        faults = (faults - {CRASH}) | {TRANSIENT_VALUE}
        prefix = ('only %s alive: crash cannot be tolerated (replication needs %d CPUs), degraded '
                  'to masking the transient value faults of the remaining processor; '
                  % (_sites_text(model.resources.cpus), crash_cpus))
    names, covered, reason = _best(model, faults, high, low, allowed, keep)
    uncovered = model.faults - _faults_of(names)
    return Selection(names, composition_name(names), frozenset(covered), frozenset(uncovered),
                     bool(uncovered), prefix + reason)
