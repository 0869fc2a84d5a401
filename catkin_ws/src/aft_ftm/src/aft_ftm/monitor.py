"""The monitoring engine's logic: keeps the change model (F, A, R) up to date from events and
decides when the running composition must be adapted, and to what.

Pure logic: no rospy; ``now`` (seconds) is passed in with every event. The ROS adapter feeds
the events (operator declarations, heartbeats, bandwidth measurements, alarms, timer ticks),
asks :meth:`MonitorCore.decide` for a decision, carries it out and reports the outcome with
:meth:`MonitorCore.adapted` or :meth:`MonitorCore.adaptation_failed`.

The monitor adapts only when the running composition becomes inconsistent with the model
(F not covered, or an A or R need not met), never merely because a cheaper one exists. It then
selects among the compositions a shipped adaptation script reaches from the running one
(:func:`reachable`), those keeping the running one first (pbr -> pbr+tr rather than lfr+tr, which
no script reaches from pbr): a decision always names a target :func:`transition` can carry out.

A site is lost after ``lost_after`` seconds of silence observed while the monitor itself ran: a
gap between two ticks longer than ``stall_after`` is the monitor's own stall (its heartbeats may
still be unread), excused from the sites' silence, and the tick that ends it judges no site. A
site never heard is waiting for its first beat, not lost.

What the operator must hear of is returned as :class:`MonitorAlarm` by :meth:`MonitorCore.take_alarms`
(the node publishes them as aft_msgs/Alarm): an adaptation that failed or was refused, one whose
rollback failed, one that stands with an alarm, a running composition kept although inconsistent
(degraded) and an inconsistency no reachable composition fits. Each once per change of state, not
at every tick.
"""
import collections
import enum
import numbers

from . import change_model, mechanisms
from .change_model import ChangeModel, Resources
from .errors import AftError, ConfigError


class TransitionError(AftError):
    """An event the monitor's state machine does not allow in its current state (a caller bug)."""


class ForgedAlarm(AftError):
    """An alarm whose source is not the node that sent it."""


class MonitorState(enum.Enum):
    WATCHING = 0   # the running composition is consistent, or the selection keeps it anyway
    ADAPTING = 1   # a decision was handed out; waiting for adapted() or adaptation_failed()
    FAILED = 2     # the last adaptation failed: the old composition runs, retried on a model change


# Allowed edges, and why each exists.
_EDGES = {
    (MonitorState.WATCHING, MonitorState.ADAPTING),  # decide(): running composition inconsistent
    (MonitorState.ADAPTING, MonitorState.WATCHING),  # adapted(): the target runs now
    (MonitorState.ADAPTING, MonitorState.FAILED),    # adaptation_failed(): the old one still runs
    (MonitorState.FAILED, MonitorState.WATCHING),    # decide(): the model changed since the failure
}


# Alarm kinds the monitor raises (aft_msgs/Alarm.kind, mechanism 'monitor').
ADAPTATION_FAILED = 'adaptation_failed'          # refused or rolled back: the old composition still runs
ROLLBACK_FAILED = 'rollback_failed'              # and its rollback failed too: check by hand
ADAPTATION_INCOMPLETE = 'adaptation_incomplete'  # the adaptation stands, with an alarm (resumes that failed)
DEGRADED = 'degraded'                            # inconsistent, but kept: nothing reachable covers more of F
NO_MECHANISM_FITS = 'no_mechanism_fits'          # nothing reachable (the running one too) covers any of F or runs
BANDWIDTH_STALE = 'bandwidth_stale'              # no bandwidth measured for bandwidth_stale_after: R's figure is old
SITE_NEVER_HEARD = 'site_never_heard'            # a site not heard since the start, past never_heard_after
WITNESS_UNHEARD = 'witness_unheard'              # no configuration naming the sites, past never_heard_after


# The notes the monitor keeps (MonitorCore.history): the newest, at most this many. A site lost for good
# that goes on beating adds one at each heartbeat, for as long as the monitor runs: unbounded, its memory
# grew without end (review of session 48). Those dropped are counted (MonitorCore.notes_dropped).
HISTORY_MAX = 1000


class MonitorAlarm(collections.namedtuple('MonitorAlarm', ['kind', 'detail'])):
    """An alarm for the operator (the node publishes it with mechanism 'monitor')."""
    __slots__ = ()


class Decision(collections.namedtuple('Decision', ['from_', 'to', 'reason', 'model', 'selection'])):
    """Adapt from the running composition ``from_`` to ``to`` (tuples of names, outermost first)."""
    __slots__ = ()

    def to_dict(self):
        return {'from': list(self.from_), 'to': list(self.to), 'reason': self.reason,
                'model': self.model.to_dict(), 'selection': self.selection.to_dict()}


def _composition(value, what):
    if isinstance(value, str) or not isinstance(value, (tuple, list)):
        raise ConfigError('%s must be a tuple of mechanism names, got %r' % (what, value))
    for name in value:
        mechanisms.mechanism(name)
    return tuple(value)


def _time(now):
    if isinstance(now, bool) or not isinstance(now, numbers.Real):
        raise ConfigError('now must be a number of seconds, got %r' % (now,))
    return now


def _alarm_scope(sites, alarms_from):
    """The nodes whose alarms count for this service: every node of its sites (/SITE/...) and the
    nodes or namespaces ``alarms_from`` names (its Proxies, a client's SEC gate). None: every alarm
    counts (``alarms_from`` None, a unit's own calls)."""
    if alarms_from is None:
        return None
    names = list(alarms_from) if not isinstance(alarms_from, str) else [alarms_from]
    for name in names:
        if not isinstance(name, str) or not name.startswith('/') or name == '/' or name.endswith('/'):
            raise ConfigError('alarms_from must name nodes or namespaces by absolute names '
                              '(e.g. /proxy), got %r' % (name,))
    return tuple(['/' + s for s in sites] + [n for n in names if n not in ['/' + s for s in sites]])


def _in_scope(source, scope):
    return any(source == name or source.startswith(name + '/') for name in scope)


class MonitorCore(object):
    """The change model of one replicated server and the adaptation state machine.

    ``sites``: the replica sites' names; a site never heard counts as alive (it waits for its first
    beat: a monitor started before the sites does not lose them), and a site heard, then silent for
    longer than ``lost_after`` while the monitor ran, is lost (fail-silence: a later heartbeat does
    not bring it back) until it re-joins: the witness admits it again once it holds the primary's
    state (:meth:`rejoined`). R.cpus = sites alive. ``stall_after`` (default lost_after / 2): a gap
    between two ticks longer than this is the monitor's own stall; the part of it beyond
    stall_after is excused from the silence of every site, and the tick that ends it judges none
    (the beats that came meanwhile may still be unread). The next tick judges, late or not, so a
    monitor stalled at every tick still loses a dead site.
    """

    def __init__(self, declared_faults, application, sites, running, now, lost_after=2.0,
                 high=change_model.DEFAULT_HIGH, low=change_model.DEFAULT_LOW, stall_after=None,
                 bandwidth_stale_after=30.0, never_heard_after=30.0, retry_hold=2.0, retry_hold_max=120.0,
                 alarms_from=None, follows_witness=False):
        sites = list(sites) if not isinstance(sites, str) else [sites]
        for name, value in (('retry_hold', retry_hold), ('retry_hold_max', retry_hold_max)):
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not value >= 0:
                raise ConfigError('%s must be a number of seconds >= 0, got %r' % (name, value))
        if not sites or len(set(sites)) != len(sites) or not all(isinstance(s, str) and s for s in sites):
            raise ConfigError('sites must be distinct non-empty names, got %r' % (sites,))
        if isinstance(lost_after, bool) or not isinstance(lost_after, numbers.Real) or not lost_after > 0:
            raise ConfigError('lost_after must be a number of seconds > 0, got %r' % (lost_after,))
        if stall_after is None:
            stall_after = lost_after / 2.0
        if (isinstance(stall_after, bool) or not isinstance(stall_after, numbers.Real)
                or not 0 < stall_after <= lost_after):
            raise ConfigError('stall_after must be a number of seconds > 0 and <= lost_after (%r), got %r'
                              % (lost_after, stall_after))
        change_model.bandwidth_level(None, high, low)   # validates the thresholds
        now = _time(now)
        self.high, self.low = high, low
        self.lost_after = lost_after
        self.stall_after = stall_after
        self.sites = sites
        self.alarm_scope = _alarm_scope(sites, alarms_from)
        self.foreign = {}           # alarms of nodes outside this service, by source: F unchanged
        self.started_at = now
        self.last_tick = now
        self.deferred = False       # the last tick ended a stall of the monitor and judged no site
        self.stalls = 0             # ticks that found the monitor stalled
        self.declared = change_model.check_faults(declared_faults)
        self.observed = frozenset()
        self.application = application
        self.bytes_per_s = None
        self.bandwidth_at = None    # when the last bandwidth figure came (None: never: no link monitor)
        self.bandwidth_stale_after = bandwidth_stale_after
        self.bandwidth_stale_told = False
        self.never_heard_after = never_heard_after
        self.never_heard_told = set()
        # A witness followed: its configurations say a lost site re-joined. One never heard naming the
        # sites (a witness that does not run, another service's) left R low for good, silently (review
        # of session 40); said once, past never_heard_after.
        self.follows_witness = follows_witness
        self.witness_heard_at = None
        self.witness_unheard_told = False
        self.witness_primary, self.witness_epoch = None, -1   # whom its newest configuration names primary
        self.last_heard = dict((s, None) for s in sites)
        self.excused = dict((s, 0.0) for s in sites)   # the monitor's own stalls since the site was heard
        self.lost = set()
        self.running = _composition(running, 'running')
        self.state = MonitorState.WATCHING
        self.pending = None         # the Decision being carried out, while ADAPTING
        self.failed_model = None    # the model signature the last failed adaptation was decided on
        # Per model signature an adaptation failed on: (failures in a row, not retried before). A model
        # flapping across a threshold (a bandwidth measured around it) came back to it every few seconds,
        # and each time retried the adaptation that kept failing, each a pause and a rollback (review of
        # session 33). The hold doubles with each failure; a model never failed on (a site lost) is
        # decided on at once; a success forgets them all.
        self.retry_hold, self.retry_hold_max = retry_hold, retry_hold_max
        self.holds = {}
        self.hold_told = None       # the signature whose hold was noted last
        self.pending_signature = None   # the model signature of the decision under way
        self.history = collections.deque(maxlen=HISTORY_MAX)   # (now, description): the newest notes
        self.notes_dropped = 0      # the older notes dropped from history to keep it at HISTORY_MAX
        self.condition = None       # (alarm kind, running, model signature) of the inconsistency alarmed last
        self.outbox = []            # MonitorAlarms not yet taken by take_alarms()
        self.model()                # validates the application
        self._note(now, 'watching %s with %s' % (change_model.composition_name(self.running),
                                                self.model().to_dict()))

    # -- state machine ------------------------------------------------------------------------------
    def _change_state(self, new, why, now):
        if (self.state, new) not in _EDGES:
            raise TransitionError('monitor cannot go from %s to %s (%s)' % (self.state.name, new.name, why))
        self._note(now, '%s -> %s: %s' % (self.state.name, new.name, why))
        self.state = new

    def _note(self, now, text):
        if len(self.history) == self.history.maxlen:   # the oldest goes: said by the count
            self.notes_dropped += 1
        self.history.append((now, text))

    # -- the model ----------------------------------------------------------------------------------
    def alive_sites(self):
        """The sites not lost, the witness's primary first (a transition names alive[0] its primary),
        then in the configured order."""
        alive = [s for s in self.sites if s not in self.lost]
        if self.witness_primary in alive:
            alive.remove(self.witness_primary)
            alive.insert(0, self.witness_primary)
        return alive

    def model(self):
        return ChangeModel(self.declared | self.observed, self.application,
                           Resources(len(self.alive_sites()), self.bytes_per_s))

    def _signature(self):
        """The model as the selection sees it (bandwidth as a level, not a measurement), so that
        a failed adaptation is retried on a change that matters, not on every measurement."""
        m = self.model()
        return (m.faults, m.application, m.resources.cpus,
                change_model.bandwidth_level(m.resources.bandwidth, self.high, self.low))

    # -- events -------------------------------------------------------------------------------------
    def declare_faults(self, faults, now):
        """The operator declares the fault model (replaces the declared part; observed faults stay)."""
        faults = change_model.check_faults(faults)
        self.declared = faults
        self._note(_time(now), 'fault model declared: %s' % change_model.kinds_text(faults))

    def declare_application(self, application, now):
        if not isinstance(application, change_model.Application):
            raise ConfigError('application must be an Application, got %r' % (application,))
        self.application = application
        self._note(_time(now), 'application declared: %s' % application.to_dict())

    def heartbeat(self, site, now):
        """A heartbeat from site. Returns False if the site was already lost for good (ignored)."""
        now = _time(now)
        if site not in self.last_heard:
            raise ConfigError('heartbeat from unknown site %r (known: %s)' % (site, ', '.join(self.sites)))
        if site in self.lost:
            self._note(now, 'heartbeat from %s, lost for good: ignored (fail-silence broken)' % site)
            return False
        self.last_heard[site] = now
        self.excused[site] = 0.0
        return True

    def rejoined(self, site, now):
        """The witness admitted site again (it re-joined with a state transfer): it counts as alive,
        and R changes back. Returns True if it had been lost."""
        now = _time(now)
        if site not in self.last_heard:
            raise ConfigError('unknown site %r (known: %s)' % (site, ', '.join(self.sites)))
        if site not in self.lost:
            return False
        self.lost.discard(site)
        self.last_heard[site] = now
        self.excused[site] = 0.0
        self._note(now, 'site %s re-joined: %d sites alive again' % (site, len(self.alive_sites())))
        return True

    def witness_heard(self, now, primary=None, epoch=None):
        """A configuration of the witness naming one of the sites came: ``primary`` serves from
        ``epoch`` on (an older epoch's, late, changes nothing). A switch after a failover named the
        configured first site its primary, the backup by then (review of session 40). Returns whether it
        is the newest configuration heard (an older one re-published brings no lost site back)."""
        now = _time(now)
        if self.witness_heard_at is None and self.witness_unheard_told:
            self._note(now, 'the witness heard at last')
        self.witness_heard_at = now
        newest = epoch is None or epoch >= self.witness_epoch
        if epoch is not None and epoch > self.witness_epoch:
            self.witness_epoch = epoch
            if primary != self.witness_primary:
                self._note(now, 'the witness names %s the primary (epoch %d)' % (primary or 'no site', epoch))
            self.witness_primary = primary if primary in self.sites else None
        return newest

    def bandwidth(self, bytes_per_s, now):
        """A measurement of the bandwidth available between sites (None: unknown)."""
        now = _time(now)
        before = change_model.bandwidth_level(self.bytes_per_s, self.high, self.low)
        self.bytes_per_s = change_model.Resources(0, bytes_per_s).bandwidth   # validates
        self.bandwidth_at, self.bandwidth_stale_told = now, False
        after = change_model.bandwidth_level(self.bytes_per_s, self.high, self.low)
        if after != before:
            self._note(now, "bandwidth %s: now supports '%s' mechanisms (was '%s')"
                       % (change_model.bandwidth_text(self.bytes_per_s), after, before))

    def alarm(self, mechanism, kind, now, source=None, sender=None):
        """An alarm raised by a mechanism; returns the fault kind it shows (added to F) or None.
        ``source`` is the node the alarm names, ``sender`` the node it came from (the connection's
        caller id, bound to a TLS party by the policy's ``nodes``): an alarm in another node's name is
        refused (ForgedAlarm), F unchanged, since a forged alarm would choose the adaptation."""
        now = _time(now)
        if sender is not None and source != sender:
            self._note(now, 'alarm %s/%s in the name of %s came from %s: refused, F unchanged'
                       % (mechanism, kind, source, sender))
            raise ForgedAlarm('an alarm %s/%s in the name of %s came from %s' % (mechanism, kind, source, sender))
        if source is not None and self.alarm_scope is not None and not _in_scope(source, self.alarm_scope):
            # Another service's node on the same ROS master (/aft/alarms is shared): its faults are
            # not this service's, and must not choose this service's mechanisms (review of session 40:
            # a navigation service's A&D alarm composed A&D onto the bank).
            if source in self.foreign or len(self.foreign) < 1024:   # bounded: one count per node
                self.foreign[source] = self.foreign.get(source, 0) + 1
            if self.foreign.get(source) == 1:
                self._note(now, 'alarm %s/%s of %s, a node outside this service (%s): F unchanged'
                           % (mechanism, kind, source, ', '.join(self.alarm_scope)))
            return None
        fault = change_model.observed_fault(mechanism, kind)
        if fault is None:
            self._note(now, 'alarm %s/%s shows no fault kind: F unchanged' % (mechanism, kind))
        elif fault not in self.observed:
            self.observed = self.observed | {fault}
            self._note(now, 'alarm %s/%s: %s observed, added to F' % (mechanism, kind, fault))
        return fault

    def tick(self, now):
        """Declare lost the sites heard, then silent for longer than lost_after while the monitor ran
        (its own stalls excused; none judged by the tick that ends a stall). Returns the newly lost."""
        now = _time(now)
        stalled = self._note_stall(now)
        self.deferred = stalled and not self.deferred
        if self.deferred:
            return []
        if self.bandwidth_at is not None and not self.bandwidth_stale_told and \
                now - self.bandwidth_at > self.bandwidth_stale_after:
            # The link monitors fell silent, or their probes no longer finish (a link too slow for one
            # to drain): the figure R holds is old, and a drop below it is not seen (review of the
            # monitor, session 33). Said once until a figure comes again; the figure is kept.
            self.bandwidth_stale_told = True
            detail = 'no bandwidth measured for %.0f s: the selection goes on from %s, measured then (a link ' \
                     'monitor silent, or a link too slow for its probe to finish)' % (
                         now - self.bandwidth_at, change_model.bandwidth_text(self.bytes_per_s))
            self._say(now, BANDWIDTH_STALE, detail)
        if self.follows_witness and self.witness_heard_at is None and not self.witness_unheard_told and \
                now - self.started_at > self.never_heard_after:
            self.witness_unheard_told = True
            self._say(now, WITNESS_UNHEARD, 'no configuration of the witness naming %s in the %.0f s since the monitor '
                      'started: a lost site that re-joins is not seen, R stays without it (the witness not '
                      'running, or ~witness naming another service\'s)' % (', '.join(self.sites), now - self.started_at))
        newly = []
        for site in self.alive_sites():
            since = self.last_heard[site]
            if since is None:
                # never heard: waits for its first beat (sites may start after the monitor), counted
                # alive meanwhile; past never_heard_after that is said, once (dead before the monitor
                # started, or its heartbeat topic wired wrong: R may count a CPU that is not there)
                if site not in self.never_heard_told and now - self.started_at > self.never_heard_after:
                    self.never_heard_told.add(site)
                    detail = 'site %s not heard in the %.0f s since the monitor started: counted alive until ' \
                             'its first beat (dead before the start, or its heartbeats not reaching the ' \
                             'monitor)' % (site, now - self.started_at)
                    self._say(now, SITE_NEVER_HEARD, detail)
                continue
            silence = now - since - self.excused[site]
            if silence > self.lost_after:
                newly.append(site)
                self.lost.add(site)
                excused = ' (%.2fs more excused: the monitor stalled)' % self.excused[site] if self.excused[site] else ''
                self._note(now, 'site %s silent for %.2fs%s, more than %gs: lost for good'
                           % (site, silence, excused, self.lost_after))
        return newly

    def _note_stall(self, now):
        """Whether this tick comes late (the monitor stalled): add to each site's excused time the part
        of the gap beyond stall_after that follows its last beat (a stall before the site was last
        heard is no excuse for a later silence)."""
        previous, self.last_tick = self.last_tick, max(self.last_tick, now)
        if now - previous <= self.stall_after:
            return False
        stall_start = previous + self.stall_after
        for site in self.alive_sites():
            heard = self.last_heard[site]
            if heard is not None and now > max(stall_start, heard):
                self.excused[site] += now - max(stall_start, heard)
        self.stalls += 1
        self._note(now, 'the monitor stalled: %.2fs since its last tick (more than %gs): the silence of '
                        'the sites meanwhile is excused, none judged at this tick' % (now - previous, self.stall_after))
        return True

    # -- decisions ----------------------------------------------------------------------------------
    def selection(self):
        """The composition the monitor would adapt to now: the cheapest consistent with the model among
        the running one and those a shipped adaptation reaches from it (:func:`reachable`), those
        keeping the running one first. The empty composition when none of them covers any of F."""
        running, alive = self.running, self.alive_sites()
        return change_model.select(self.model(), self.high, self.low,
                                   allowed=lambda c: c == running or reachable(running, c, alive), keep=running)

    def decide(self, now):
        """None, or the Decision to adapt (handed out once; none while ADAPTING). Its target is always
        one :func:`transition` reaches from the running composition. An inconsistency it cannot act on
        is alarmed (:meth:`take_alarms`) once per change of the running composition or of the model."""
        now = _time(now)
        self.tick(now)
        if self.state == MonitorState.ADAPTING:
            return None
        if self.state == MonitorState.FAILED:
            if self._signature() == self.failed_model:
                return None
            self._change_state(MonitorState.WATCHING, 'the model changed since the failed adaptation', now)
        model = self.model()
        ok, why = change_model.consistent(self.running, model, self.high, self.low)
        if ok:
            self.condition = None
            return None
        running = change_model.composition_name(self.running)
        selection = self.selection()
        if selection.mechanisms == self.running:
            # degraded: it covers part of F at least; else nothing reachable fits, not even it
            self._alarm(now, DEGRADED if selection.covered else NO_MECHANISM_FITS,
                        '%s is inconsistent (%s) but remains the best choice among the compositions a shipped '
                        'adaptation reaches from it: %s%s' % (running, why, selection.reason, self._unreachable(model)))
            return None
        if not reachable(self.running, selection.mechanisms, self.alive_sites()):
            self._alarm(now, NO_MECHANISM_FITS, '%s is inconsistent (%s) and no composition a shipped adaptation '
                        'reaches from it does better: %s%s; %s keeps running' % (
                            running, why, selection.reason, self._unreachable(model), running))
            return None
        signature = self._signature()
        failures, not_before = self.holds.get(signature, (0, now))
        if now < not_before:
            if self.hold_told != signature:
                self.hold_told = signature
                self._note(now, 'an adaptation on this model failed %d time(s) in a row: not tried again before '
                                '%.1f s from now' % (failures, not_before - now))
            return None
        self.condition = None
        self.pending_signature = signature   # the model the decision was made on
        self.pending = Decision(self.running, selection.mechanisms,
                                '%s is inconsistent: %s; selected %s: %s' % (
                                    running, why, selection.name, selection.reason),
                                model, selection)
        self._change_state(MonitorState.ADAPTING, self.pending.reason, now)
        return self.pending

    def _unreachable(self, model):
        """What the selection over every composition would be, when no shipped adaptation reaches it."""
        anywhere = change_model.select(model, self.high, self.low)
        if anywhere.mechanisms in ((), self.running) or reachable(self.running, anywhere.mechanisms,
                                                                   self.alive_sites()):
            return ''
        return '; over every composition the selection would be %s, which no shipped adaptation reaches from %s' % (
            anywhere.name, change_model.composition_name(self.running))

    def _alarm(self, now, kind, detail):
        """Alarm an inconsistency left as it is, once per (kind, running composition, model signature)."""
        key = (kind, self.running, self._signature())
        if key == self.condition:
            return
        self.condition = key
        self._say(now, kind, detail)

    def _say(self, now, kind, detail):
        """An alarm for the node to publish (take_alarms), noted in the history."""
        self._note(now, 'alarm %s: %s' % (kind, detail))
        self.outbox.append(MonitorAlarm(kind, detail))

    def take_alarms(self):
        """The alarms raised since the last call (oldest first), for the node to publish."""
        alarms, self.outbox = self.outbox, []
        return alarms

    def adapted(self, target, now, alarm=''):
        """The adaptation is done: target runs now. ``alarm``: what the adaptation's report says went
        wrong although it stands (resumes that failed): raised as adaptation_incomplete."""
        target = _composition(target, 'target')
        now = _time(now)
        if self.state != MonitorState.ADAPTING:
            raise TransitionError('adapted(%r) while %s: no adaptation was under way' % (target, self.state.name))
        if target != self.pending.to:
            self._note(now, 'adapted to %s instead of the decided %s' % (
                change_model.composition_name(target), change_model.composition_name(self.pending.to)))
        before = change_model.composition_name(self.running)
        self.running = target
        self.pending = None
        self.holds.clear()
        self._change_state(MonitorState.WATCHING, 'running %s' % change_model.composition_name(target), now)
        if alarm:
            self.outbox.append(MonitorAlarm(ADAPTATION_INCOMPLETE, 'adaptation %s -> %s stands, but: %s' % (
                before, change_model.composition_name(target), alarm)))

    def adaptation_failed(self, error, now, rollback_failed=False):
        """The adaptation failed (refused, or rolled back): the old composition still runs; no retry until
        the model changes; on the model it failed on, not before a hold that doubles with each failure
        there (retry_hold, at most retry_hold_max seconds). ``rollback_failed``: its rollback could not undo everything (the report's
        state FAILED): the system may not be as before. Raises adaptation_failed or rollback_failed."""
        now = _time(now)
        if self.state != MonitorState.ADAPTING:
            raise TransitionError('adaptation_failed(%r) while %s: no adaptation was under way'
                                  % (error, self.state.name))
        # The model the decision was made on, not the one now: a change while it ran (a site lost, an
        # application that changed) is a reason to decide again; taken in here, it was never acted on
        # (review of the monitor, session 33).
        self.failed_model = self.pending_signature or self._signature()
        failures = self.holds.get(self.failed_model, (0, now))[0] + 1
        # (the exponent capped: at the 1025th failure on one model 2 ** 1024 overflowed a float, and the
        # monitor's adapter thread died with it, ADAPTING for good; review of session 48)
        hold = min(self.retry_hold_max, self.retry_hold * 2 ** min(failures - 1, 64))
        self.holds[self.failed_model], self.hold_told = (failures, now + hold), None
        retry = 'retried when the model changes, on this model not before %.0f s from now (%d failed in a row)' % (
            hold, failures)
        move = '%s -> %s' % (change_model.composition_name(self.pending.from_),
                             change_model.composition_name(self.pending.to))
        target = change_model.composition_name(self.pending.to)
        running = change_model.composition_name(self.running)
        self.pending = None
        self._change_state(MonitorState.FAILED, 'adaptation to %s failed: %s; still running %s' % (
            target, error, running), now)
        if rollback_failed:
            self.outbox.append(MonitorAlarm(ROLLBACK_FAILED, 'adaptation %s failed and its rollback did not undo '
                                            'everything: %s; the system may not be as before (check by hand); '
                                            '%s' % (move, error, retry)))
        else:
            self.outbox.append(MonitorAlarm(ADAPTATION_FAILED, 'adaptation %s failed: %s; still running %s, '
                                            '%s' % (move, error, running, retry)))


# -- from a decision to a shipped adaptation script ------------------------------------------------

class Transition(collections.namedtuple('Transition', ['script', 'overrides', 'suffix'])):
    """The script (shipped name) and arguments that carry out a decision; ``suffix`` is the one
    the replicas' Before and After carry afterwards (a switch starts them under new names)."""
    __slots__ = ()


def reachable(from_, to, alive_sites):
    """Whether a shipped adaptation script carries out from_ -> to (:func:`transition` has one)."""
    try:
        transition(tuple(from_), tuple(to), alive_sites)
    except ConfigError:
        return False
    return True


def transition(from_, to, alive_sites, suffix=''):
    """The adaptation script for from_ -> to, or raise ConfigError naming what is not supported.

    ``alive_sites``: the replica sites alive (the first one is the primary); ``suffix``: the suffix
    of the running Before and After (none as deployed).
    """
    names = (change_model.composition_name(from_), change_model.composition_name(to))
    if len(alive_sites) >= 2 and set(names) == {'pbr', 'lfr'}:
        new = '_' + to[0]
        return Transition('switch', ['to:=%s' % to[0], 'old:=%s' % suffix, 'new:=%s' % new,
                                     'primary:=%s' % alive_sites[0], 'backup:=%s' % alive_sites[1]], new)
    if from_ in (('pbr',), ('lfr',)) and to in (('tr',), ('ad',)) and len(alive_sites) == 1:
        # One site left: the replication shell goes on alone; the mechanism stands in for its Proceed.
        # (With both sites alive, compose makes pbr+tr, not tr: the monitor would then hold a wrong
        # view of what runs, from which no transition leads; review of session 33.)
        return Transition('compose', ['mechanism:=%s' % to[0], 'site:=%s' % ','.join(alive_sites)], suffix)
    if len(from_) == 1 and to[:1] == from_ and len(to) == 2 and to[1] in ('tr', 'ad'):
        return Transition('compose', ['mechanism:=%s' % to[1], 'site:=%s' % ','.join(alive_sites)], suffix)
    raise ConfigError('no shipped adaptation for %s -> %s (scripts: switch pbr <-> lfr, compose a '
                      'tr or ad into a replication)' % names)
