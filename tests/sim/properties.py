"""The properties a user of PBR relies on, checked after every step of a simulation.

The fault model: any process or site may crash or be arbitrarily slow, messages may be delayed
and reordered across connections, a site may come back after any time.

- P1 exactly once: the state of the replica that serves (the witness's primary, promoted) holds
  every request a client saw answered, each once, and no request applied twice.
- P2 definite outcomes: an error a client accepts says "not executed", and that request is then
  in no serving state, ever; a request is never answered with two different results.
- P3 one server per epoch: two sites never answer new (not cached) requests in one epoch; a
  Proxy never accepts a reply of an epoch older than one it accepted; the witness's epochs only
  grow, and only the backup of a configuration is ever promoted.
- P4 nothing degrades silently: each primary going on without its backup, each checkpoint a
  backup refuses (a gap, a stray or stale one, one after it was fenced), each backup that stops
  mirroring and each fail-stop comes with an alarm of its site (alarms of one kind about one
  sender are raised once: a flood raises one).

The transitions of P4 are observed on the real pure objects (sim.replica.ObservedSender and
ObservedReceiver), independently of the adapter models that raise the alarms.
"""
import collections

from aft_ftm.protocol import key

from .world import Violation

# transition -> the alarm kinds that report it
REPORTED_BY = {
    'alone': ('alone',),
    'promoted_alone': ('took_over',),
    'gap': ('backup_invalid',),
    'stray': ('stray_checkpoint',),
    'stale': ('stale_checkpoint',),
    'fenced': ('stale_checkpoint',),
    'stops_mirroring': ('backup_invalid', 'excluded'),
    'fail_stop': ('fail_stop',),
}


class Checker(object):
    def __init__(self):
        self.env = None
        self.answered = {}               # request key -> the value clients accepted
        self.not_executed = set()        # request keys a client accepted "not executed" for
        self.new_answers = {}            # epoch -> the site that answered new requests in it
        self.accepted_epoch = {}         # Proxy -> the newest epoch it accepted a reply of
        self.transitions = []            # (incarnation, node, transition, key)
        self.transition_counts = collections.Counter()
        self._checked = 0
        self._alarms_seen = 0
        self._alarm_keys = set()
        self._configurations = 0
        self._stopped = set()            # incarnations whose fail-stop was counted

    def attach(self, env):
        self.env = env

    # -- events from the models ------------------------------------------------------------------
    def new_answer(self, protocol, reply):
        site = protocol.site.name
        first = self.new_answers.setdefault(reply.epoch, site)
        if first != site:
            raise Violation('P3 one server per epoch', '%s and %s both answered new requests in epoch %d (%s/%d)'
                            % (first, site, reply.epoch, reply.origin, reply.id))

    def accepted(self, proxy, reply, first):
        newest = self.accepted_epoch.get(proxy.name, 0)
        if reply.epoch < newest:
            raise Violation('P3 one server per epoch', '%s accepted a reply of epoch %d after one of epoch %d'
                            % (proxy.name, reply.epoch, newest))
        self.accepted_epoch[proxy.name] = reply.epoch
        k = key(reply)
        if reply.ok:
            if k in self.not_executed:
                raise Violation('P2 definite outcome', '%s/%d answered %r after "not executed"'
                                % (k[0], k[1], reply.value))
            if k in self.answered and self.answered[k] != reply.value:
                raise Violation('P2 definite outcome', '%s/%d answered %r, then %r'
                                % (k[0], k[1], self.answered[k], reply.value))
            self.answered[k] = reply.value
        else:
            if not reply.error.startswith('not executed'):
                raise Violation('P2 definite outcome', '%s/%d failed with an outcome that is not definite: %s'
                                % (k[0], k[1], reply.error))
            if k in self.answered:
                raise Violation('P2 definite outcome', '%s/%d "not executed" after it was answered %r'
                                % (k[0], k[1], self.answered[k]))
            self.not_executed.add(k)

    def transition(self, node, kind, sender):
        self.transitions.append((node.site.incarnation_id, node.name, kind, sender))
        self.transition_counts[kind] += 1

    def configuration(self, witness):
        """A new configuration: one epoch more; a new primary only if it was the backup."""
        history = witness.history
        for index in range(self._configurations, len(history)):
            epoch, primary, _, reason = history[index]
            previous = history[index - 1] if index else (0, '', '', '')
            if epoch != previous[0] + 1 or not primary:
                raise Violation('P3 one server per epoch', 'configuration %r after %r' % (history[index], previous))
            if previous[1] and primary != previous[1] and primary != previous[2]:
                raise Violation('P3 one server per epoch', '%s became primary in epoch %d without being the backup '
                                'of epoch %d %r' % (primary, epoch, previous[0], previous))
        self._configurations = len(history)

    # -- after every step ------------------------------------------------------------------------
    def after_step(self):
        env = self.env
        site = env.serving()
        if site is not None:
            self.check_state(site)
        alarms = env.alarms
        while self._alarms_seen < len(alarms):
            _, incarnation, _, kind, alarm_key, _ = alarms[self._alarms_seen]
            self._alarm_keys.add((incarnation, kind, alarm_key))
            self._alarms_seen += 1
        for s in env.sites.values():
            detector = s.node('detector')
            if detector is not None and detector.stopped is not None and s.incarnation_id not in self._stopped:
                self._stopped.add(s.incarnation_id)
                self.transition(detector, 'fail_stop', None)
        while self._checked < len(self.transitions):
            incarnation, node, kind, sender = self.transitions[self._checked]
            if not any((incarnation, k, sender) in self._alarm_keys or (incarnation, k, None) in self._alarm_keys
                       for k in REPORTED_BY[kind]):
                raise Violation('P4 no silent degradation', '%s: %s%s raised no alarm (expected %s)'
                                % (node, kind, ' from %s' % sender if sender else '', ' or '.join(REPORTED_BY[kind])))
            self._checked += 1

    def check_state(self, site):
        log = site.server.log
        applied = set(log)
        if len(applied) != len(log):
            twice = sorted(k for k, n in collections.Counter(log).items() if n > 1)
            raise Violation('P1 exactly once', 'the serving replica %s applied %s twice' % (site.incarnation_id, twice))
        missing = [k for k in self.answered if k not in applied]
        if missing:
            raise Violation('P1 exactly once', 'the serving replica %s lacks %s, answered to clients'
                            % (site.incarnation_id, sorted(missing)))
        moved = [(k, v) for k, v in self.answered.items() if v > len(log) or log[v - 1] != k]
        if moved:
            raise Violation('P1 exactly once', 'the serving replica %s applied %s elsewhere than answered (%s)'
                            % (site.incarnation_id, moved, log))
        executed = [k for k in self.not_executed if k in applied]
        if executed:
            raise Violation('P2 definite outcome', 'the serving replica %s applied %s, answered "not executed"'
                            % (site.incarnation_id, sorted(executed)))

    def alarm_counts(self):
        return collections.Counter(a[3] for a in self.env.alarms)
