"""The health an FTM node reports on /diagnostics, from its state (no rospy here).

Levels are diagnostic_msgs/DiagnosticStatus's: OK, WARN (degraded: the service is answered, but a
further fault would not be tolerated, or a replica cannot take over), ERROR (this node cannot serve:
deposed, fail-stopped, a request hangs). Every report carries the keys ``status`` prints: site,
mechanism, role, epoch; and what the node knows beside them.
"""
import enum

from .protocol import Role


class Level(enum.IntEnum):
    OK = 0
    WARN = 1
    ERROR = 2


class Report(object):
    """One node's health: level, a one-line message, and key/value pairs (values as strings)."""
    __slots__ = ('level', 'message', 'values')

    def __init__(self, level, message, values):
        self.level = level
        self.message = message
        self.values = [(k, str(v)) for k, v in values]

    def value(self, key, default=None):
        return next((v for k, v in self.values if k == key), default)

    def __repr__(self):
        return 'Report(%s, %r)' % (self.level.name, self.message)


def _common(site, mechanism, role, epoch):
    return [('site', site), ('mechanism', mechanism), ('role', role.name if isinstance(role, Role) else role),
            ('epoch', epoch)]


def replica_after(site, mechanism, role, epoch, peer, held=0, stopped=None, cannot_take_over=None, extra=()):
    """A PBR or LFR After. ``held``: replies waiting for the backup (checkpoint lag);
    ``stopped``: why it answers nothing any more (deposed, fail-stop); ``cannot_take_over``: why a
    backup may not be promoted (joining, excluded, a refused checkpoint)."""
    values = _common(site, mechanism, role, epoch) + [('peer', peer), ('held', held)] + list(extra)
    if stopped:
        return Report(Level.ERROR, 'serves nothing: %s' % stopped, values)
    if role == Role.BACKUP:
        if cannot_take_over:
            return Report(Level.WARN, 'cannot take over: %s' % cannot_take_over, values)
        return Report(Level.OK, 'backup of %s, may take over' % peer, values)
    if role == Role.ALONE:
        return Report(Level.WARN, 'alone: no backup, a further failure is not tolerated', values)
    return Report(Level.OK, 'primary, %s follows (%d held)' % (peer, held), values)


def protocol(site, role, epoch, cached, cache_bytes, bound_bytes, queued, hung=None, refused=0):
    """A replica's (or a mechanism's) Protocol."""
    values = _common(site, '', role, epoch) + [('cached_replies', cached), ('cache_bytes', cache_bytes),
                                               ('cache_bound_bytes', bound_bytes), ('queued', queued),
                                               ('refused', refused)]
    if hung is not None:
        return Report(Level.ERROR, 'a request hangs: %s' % hung, values)
    if bound_bytes and cache_bytes >= bound_bytes:
        return Report(Level.WARN, 'refusing new requests: the reply cache is at its bound', values)
    doing = 'backup' if role == Role.BACKUP else 'serving'   # the Protocol is ALONE on a primary too
    return Report(Level.OK, '%s, %d cached replies, %d queued' % (doing, cached, queued), values)


def detector(site, peer, peer_state, silence, stopped=None):
    """A crash detector: ``peer_state`` a detector.PeerState name (UNKNOWN, ALIVE, FAILED)."""
    values = [('site', site), ('peer', peer), ('peer_state', peer_state),
              ('silence_ms', '%.1f' % (silence * 1e3) if silence is not None else '')]
    if stopped:
        return Report(Level.ERROR, 'fail-stopped (no heartbeat sent): %s' % stopped, values)
    if peer_state == 'FAILED':
        return Report(Level.WARN, 'peer %s declared failed' % peer, values)
    if peer_state == 'UNKNOWN':
        return Report(Level.WARN, 'peer %s never heard' % peer, values)
    return Report(Level.OK, 'peer %s alive' % peer, values)


def recovery(site, role, epoch, last=None, master_unreachable_for=None):
    """A replica's Recovery: ``last`` is its last failover record (~events), None before any;
    ``master_unreachable_for``: seconds the ROS master has not answered (None: it answers)."""
    values = _common(site, '', role, epoch)
    values.append(('master', 'reachable' if master_unreachable_for is None
                   else 'unreachable for %.0f s' % master_unreachable_for))
    if last:
        values += [('last_failed_site', last.get('failed_site')), ('last_recovery_ms', '%.1f' % (last['seconds'] * 1e3)),
                   ('last_reason', last.get('reason'))]
    if last and not last.get('ok'):
        failed = [s for s in last['steps'] if not s['ok']]
        return Report(Level.ERROR, 'the recovery from the failure of %s failed: %s' % (
            last['failed_site'], '; '.join('%s: %s' % (s['step'], s['detail']) for s in failed)), values)
    if role is None:
        return Report(Level.WARN, 'in no configuration of the witness: neither serves nor takes over', values)
    if master_unreachable_for is not None:
        return Report(Level.WARN, 'master_unreachable: the ROS master has not answered for %.0f s (failovers still '
                      'work; no node can start, re-join or be adapted)' % master_unreachable_for, values)
    if not last:
        return Report(Level.OK, 'no failover yet', values)
    return Report(Level.OK, '%s failed (%s); recovered in %.1f ms: %s' % (
        last['failed_site'], last['reason'], last['seconds'] * 1e3,
        ', '.join('%s %.1f ms' % (s['step'], s['seconds'] * 1e3) for s in last['steps'])), values)


def proxy(service, pending, oldest_age, resends, refused, pending_bytes, bound_bytes, epoch, patience):
    """A Proxy: ``oldest_age`` the age of its oldest unanswered request (s, None if none);
    ``patience``: past this age a request is late (the replicas are not answering)."""
    values = [('site', service), ('role', 'PROXY'), ('epoch', epoch), ('pending', pending),
              ('oldest_pending_s', '%.3f' % oldest_age if oldest_age is not None else ''),
              ('resends', resends), ('refused', refused), ('pending_bytes', pending_bytes)]
    if bound_bytes and pending_bytes >= bound_bytes:
        return Report(Level.WARN, 'refusing calls: the requests waiting for replies are at their bound', values)
    if oldest_age is not None and oldest_age > patience:
        return Report(Level.WARN, 'a request unanswered for %.1f s: no replica answers it' % oldest_age, values)
    return Report(Level.OK, '%d pending, %d re-sent, %d refused' % (pending, resends, refused), values)


def stage(mechanism, stage, calling_for=None, patience=None, failed=None, calls_server=None):
    """A Before, Proceed or After without a report of its own. For a node that calls the server
    (``calls_server``, by default a Proceed): ``calling_for`` how long the call in progress has run
    (s, None if none), late past ``patience``; ``failed`` why the replica fail-stopped."""
    values = [('mechanism', mechanism), ('stage', stage)]
    if calls_server or (calls_server is None and stage == 'proceed'):
        values.append(('calling_for_s', '%.3f' % calling_for if calling_for is not None else ''))
    if failed:
        return Report(Level.ERROR, 'fail-stopped: %s' % failed, values)
    if calling_for is not None and patience is not None and calling_for > patience:
        return Report(Level.WARN, 'the server has not answered for %.1f s' % calling_for, values)
    if stage != 'proceed':
        return Report(Level.OK, 'passing requests on', values)
    if calling_for is None:
        return Report(Level.OK, 'idle: no call of the server in progress', values)
    return Report(Level.OK, 'calling the server (for %.3f s)' % calling_for, values)


def witness(epoch, primary, backup, reason, persistent, behind=0, unsaved=None):
    """The witness: the configuration it granted last. ``persistent``: it keeps its record in a
    state file (a restart forgets nothing); ``behind``: an epoch a caller has seen above the record;
    ``unsaved``: why its record could not be saved at the last change asked (nothing is granted then)."""
    values = [('site', 'witness'), ('role', 'WITNESS'), ('epoch', epoch), ('primary', primary), ('backup', backup),
              ('reason', reason), ('state_file', 'yes' if persistent else 'no')]
    if unsaved:
        return Report(Level.ERROR, 'epoch %d: its record cannot be saved (%s): it grants no change until it can'
                      % (epoch, unsaved), values + [('unsaved', unsaved)])
    if behind:
        return Report(Level.ERROR, 'record at epoch %d, behind epoch %d a site has seen (lost or rolled back): '
                                   'it grants nothing until restored' % (epoch, behind), values + [('behind', behind)])
    if not primary:
        # No replica has registered (a deployment without replication, or one still starting).
        return Report(Level.OK, 'epoch %d: no replica registered' % epoch, values)
    if not backup:
        return Report(Level.WARN, 'epoch %d: %s serves alone (no backup admitted): %s' % (epoch, primary, reason),
                      values)
    return Report(Level.OK, 'epoch %d: primary %s, backup %s' % (epoch, primary, backup), values)


def sec_gate(side, party, role, peers, awaiting, rejected, policy='', at_quota=()):
    """A SEC gate: ``peers`` parties whose certificates it holds, ``awaiting`` requests sealed and
    not answered (client side), ``rejected`` messages refused (forged, replayed, undecryptable);
    ``policy``: a server gate's policy file, None when it has none (each origin then bound to the
    first party using it: a WARN), '' on the client side; ``at_quota``: parties whose new requests
    are dropped at their quota (server side, security.PartyQuota): a WARN."""
    values = [('mechanism', 'sec'), ('side', side), ('party', party), ('role', role.name if isinstance(role, Role)
                                                                      else role),
              ('certified_peers', peers), ('awaiting_replies', awaiting), ('rejected', rejected),
              ('policy', policy or ''), ('at_quota', ', '.join(at_quota))]
    if at_quota:
        return Report(Level.WARN, 'at their quota of outstanding requests, new ones dropped: %s' % ', '.join(at_quota),
                      values)
    if rejected:
        return Report(Level.WARN, '%d message(s) rejected (see /aft/alarms)' % rejected, values)
    if policy is None:
        return Report(Level.WARN, 'no SEC policy: each origin is bound to the first party using it', values)
    return Report(Level.OK, '%s side of %s, %d certified peer(s)' % (side, party, peers), values)


def watchdog(primary, backup, failures, describe):
    """The car's watchdog: the board that drives, the one that may take over, failovers so far."""
    values = [('site', 'watchdog'), ('mechanism', 'pbr'), ('role', 'WATCHDOG'), ('primary', primary or ''),
              ('backup', backup or ''), ('failovers', failures), ('boards', describe)]
    if not primary:
        return Report(Level.ERROR, 'no board drives: %s' % describe, values)
    if not backup:
        return Report(Level.WARN, '%s drives with no backup able to take over: %s' % (primary, describe), values)
    return Report(Level.OK, '%s drives, %s may take over' % (primary, backup), values)


def with_suspension(report, gate_state, held):
    """report, with the node's suspension: a node suspended by an adaptation (its inputs held) is
    degraded (WARN at least) until it is resumed."""
    values = list(report.values) + [('suspension', gate_state), ('held_messages', held)]
    if gate_state == 'OPEN':
        return Report(report.level, report.message, values)
    return Report(max(report.level, Level.WARN), 'suspended (%s, %d message(s) held); %s' % (
        gate_state.lower(), held, report.message), values)


def _site_of(name, report):
    """A report's site; for a node that names none, the first name space of the node (/master/tr/x)."""
    parts = name.strip('/').split('/')
    return report.value('site') or (parts[0] if len(parts) > 1 else '?')


def summary(reports):
    """One line per site from the reports of its nodes ({node name: Report}): (site, level, text)."""
    sites = {}
    for name, report in sorted(reports.items()):
        sites.setdefault(_site_of(name, report), []).append((name, report))
    lines = []
    for site, entries in sorted(sites.items()):
        level = max(r.level for _, r in entries)
        mechanism = next((r.value('mechanism') for _, r in entries if r.value('mechanism')), '-')
        role = next((r.value('role') for n, r in entries if n.endswith('after') or 'after_' in n), None) \
            or next((r.value('role') for _, r in entries if r.value('role')), '-')
        epoch = max((int(r.value('epoch')) for _, r in entries if (r.value('epoch') or '').isdigit()), default=0)
        worst = [('%s: %s' % (n.rsplit('/', 1)[-1], r.message)) for n, r in entries if r.level == level]
        lines.append((site, level, '%-8s %-5s %-8s epoch %-4d %-5s %s' % (site, mechanism, role, epoch, level.name,
                                                                        '; '.join(worst))))
    return lines


def link_monitor(site, peer, estimate, last, failures, why=None):
    """A link monitor: the bandwidth to ``peer`` it reports (median of its last probes, bytes/s),
    the last probe's figure, and ``failures`` probes in a row that measured nothing (``why``)."""
    values = [('site', site), ('peer', peer), ('bandwidth_bytes_per_s', '%.0f' % estimate if estimate else 'unknown'),
              ('last_probe_bytes_per_s', '%.0f' % last if last else 'none'), ('failed_probes', failures)]
    if failures:
        return Report(Level.WARN, '%d probe(s) of %s in a row measured nothing: %s' % (failures, peer, why), values)
    if estimate is None:
        return Report(Level.OK, 'no probe of %s yet' % peer, values)
    return Report(Level.OK, '%.0f kB/s to %s' % (estimate / 1e3, peer), values)
