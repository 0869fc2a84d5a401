"""The crash detectors' verdicts heard during a campaign, judged against the faults injected. No ROS.

A verdict (a replica's crash detector declaring its peer site failed) is *explained* when it falls
inside the window of a fault that touched the site it names, or blinded the site that judged it
(a partitioned, rate-limited or frozen site declares its peer failed): from the fault's start until the
deployment was whole again (``healed_at``), and before that site re-joined (its peer's
``peer_watched`` alarm). Any other verdict is a **false suspicion**: a site that nothing touched was
declared failed (while nodes started, during an adaptation, during a fault of another site, after a
healing, or a relaunched site declared failed again once it had re-joined, before the runner saw the
pair whole). A false suspicion costs a failover, fences a correct replica and
leaves the pair alone until it re-joins, so the campaign counts them; issue 15's target is none over
1000 faults.

The detection time of a fault is the time from its start to the first verdict about the site it
touched (faults of one site only: a partition of the pair has no single victim).
"""
import collections
import re

from .history import percentile

Verdict = collections.namedtuple('Verdict', 'time reporter failed reason')
Verdict.__doc__ = """time (wall clock, s: the detector's stamp), reporter (the site whose detector spoke),
failed (the site it declared failed), reason (the detector's words)."""


def sites_touched(target, primary, backup):
    """The replica sites a fault on `target` touches, given the sites serving as primary and backup
    when it came: 'primary/after' -> {primary}; 'primary-backup' (a pair) -> both; 'client-backup' ->
    {backup}; 'proxy', 'witness', 'ros_master', an adaptation's name -> none."""
    touched = set()
    for end in target.split('-'):
        role = end.partition('/')[0]
        site = {'primary': primary, 'backup': backup}.get(role)
        if site:
            touched.add(site)
    return touched


BLINDING = ('partition', 'partition_pair', 'bandwidth', 'freeze_site')


def blinds(record):
    """Whether the fault can make the site it touched stop hearing its peer (its link cut or
    throttled, the whole site or its crash detector frozen)."""
    return record['kind'] in BLINDING or (record['kind'] == 'freeze_node'
                                          and str(record.get('target', '')).endswith('crash_detector'))


def judge(verdicts, records, rejoins=()):
    """(explained, false, detections): the verdicts inside the window of a fault that touched the
    site they name, the others, and per fault of one site the seconds from its start to its first
    verdict ({record index: s}). records: the campaign's fault records (start, healed_at or end,
    sites); rejoins: (time, site) of each re-join heard, which ends that site's window early."""
    explained, false, detections = [], [], {}
    for verdict in sorted(verdicts):
        cause = None
        for record in records:
            stop = record.get('healed_at') or record.get('end') or record['start']
            touched = record.get('sites', ())
            # The fault touched the site declared failed, or blinded the one that judged it (a
            # partitioned, rate-limited or frozen site, or its frozen crash detector, declares its peer
            # failed: the fault's doing, not a suspicion of a sound pair).
            named = verdict.failed if verdict.failed in touched else \
                verdict.reporter if verdict.reporter in touched and blinds(record) else None
            if named is None:
                continue
            # A re-join ends the window: the site was whole again. Only one after the repair began (a
            # relaunch): before it, the site the fault hit may still be re-admitted on its way down.
            since = max(record['start'], record.get('repaired_from') or record['start'])
            stop = min([stop] + [t for t, site in rejoins if site == named and since < t])
            if record['start'] <= verdict.time <= stop:
                cause = record
                break
        if cause is None:
            false.append(verdict)
            continue
        explained.append(verdict)
        if len(cause.get('sites', ())) == 1 and verdict.failed in cause['sites'] and cause['index'] not in detections:
            detections[cause['index']] = verdict.time - cause['start']
    return explained, false, detections


def heard_again_of(kind, detail):
    """The site a crash detector's 'peer_back' alarm says is heard again ('site NAME, declared failed, is
    heard again ...'), or None."""
    words = detail.split()
    if kind == 'peer_back' and len(words) > 1 and words[0] == 'site':
        return words[1].rstrip(',')
    return None


def then_heard(verdict, heard_again, within=60.0):
    """What the detector said when the site it declared failed was first heard again after the verdict
    (its peer_back alarm: whether the site's beats were sent late, arrived late, were lost, or it started
    again), or None. heard_again: (time, site, detail) of each peer_back alarm."""
    after = sorted((t, detail) for t, site, detail in heard_again
                   if site == verdict.failed and verdict.time <= t <= verdict.time + within)
    return after[0][1] if after else None


def summary(verdicts, records, rejoins=(), heard_again=()):
    """The campaign's detection figures, for its report and campaign.json. A false suspicion carries
    ('then') what its detector said when it heard that site again."""
    explained, false, detections = judge(verdicts, records, rejoins)
    # A failover as the clients see it: the longest wait from the fault to the runner's first repair
    # action (the failed site's relaunch); the re-join that follows holds requests too, reported apart.
    ended = [r for r in records if r['outcome'] == 'failover']
    failovers = [r.get('unavailable_fault', r.get('unavailable', 0.0)) * 1e3 for r in ended]
    rejoins = [r.get('unavailable_repair', 0.0) * 1e3 for r in ended]
    by_kind = collections.OrderedDict()
    for record in sorted(records, key=lambda r: r['kind']):
        if record['index'] in detections:
            by_kind.setdefault(record['kind'], []).append(detections[record['index']] * 1e3)
    return {
        'verdicts': len(verdicts), 'explained': len(explained), 'false_suspicions': len(false),
        'false': [dict(v._asdict(), then=then_heard(v, heard_again)) for v in false],
        'detection_ms_median': percentile([d * 1e3 for d in detections.values()], 50),
        'detection_ms_by_kind': {k: percentile(v, 50) for k, v in by_kind.items()},
        'failover_unavailable_ms_median': percentile(failovers, 50), 'failovers': len(failovers),
        'failover_unavailable_ms_p99': percentile(failovers, 99),
        'failover_rejoin_ms_median': percentile(rejoins, 50),
    }


_LOGGED = re.compile(r'\[(?:WARN|INFO|ERROR)\] \[(\d+\.\d+)\]: /(\w+)/crash_detector: site (\w+) failed: (.*)')


def logged_verdicts(lines):
    """The verdicts the crash detectors logged (the sites' own logs): what the runner could not hear
    (a partitioned site's verdict does not reach it) is there."""
    found = []
    for line in lines:
        m = _LOGGED.search(line)
        if m:
            found.append(Verdict(float(m.group(1)), m.group(2), m.group(3), m.group(4).strip()))
    return found


def merge(heard, logged, tolerance=0.05, same_words_within=2.0):
    """The verdicts heard, and those logged that no heard one matches: same reporter and site, within
    tolerance seconds, or in the very same words within same_words_within seconds (the log line is
    stamped before the report is: a detector stalled in between, on a loaded machine, stamped one
    verdict 131 ms apart, and it was counted twice)."""
    def same(v, verdict):
        if v.reporter != verdict.reporter or v.failed != verdict.failed:
            return False
        apart = abs(v.time - verdict.time)
        return apart <= tolerance or (v.reason == verdict.reason and apart <= same_words_within)
    merged, matched = list(heard), set()
    for verdict in sorted(logged):   # one logged verdict per heard one: a second verdict in the same words stays
        match = next((i for i, v in enumerate(heard) if i not in matched and same(v, verdict)), None)
        if match is None:
            merged.append(verdict)
        else:
            matched.add(match)
    return sorted(merged)


def rejoin_of(kind, detail):
    """The site a crash detector's alarm says re-joined ('peer_watched': 'site NAME re-joined (epoch
    E): watched again'), or None."""
    words = detail.split()
    if kind == 'peer_watched' and len(words) > 2 and words[0] == 'site' and words[2] == 're-joined':
        return words[1]
    return None


def format_summary(s, timeout):
    """The report's lines on detection."""
    def ms(value):
        return '-' if value is None else '%.1f ms' % value
    lines = ['detection (crash detector timeout %.0f ms): %d verdicts, %d explained by a fault, %d false suspicions; '
             'detection median %s (%s); failovers %d, the clients\' longest wait median %s (p99 %s) until the '
             'failed site is relaunched, then %s during its re-join'
             % (timeout * 1e3, s['verdicts'], s['explained'], s['false_suspicions'], ms(s['detection_ms_median']),
                ', '.join('%s %s' % (k, ms(v)) for k, v in s['detection_ms_by_kind'].items()) or 'none detected',
                s['failovers'], ms(s['failover_unavailable_ms_median']), ms(s.get('failover_unavailable_ms_p99')),
                ms(s.get('failover_rejoin_ms_median')))]
    for v in s['false']:
        lines.append('  false suspicion at %.3f: %s declared %s failed (%s)%s' % (
            v['time'], v['reporter'], v['failed'], v['reason'],
            '; heard again: %s' % v['then'] if v.get('then') else ''))
    return lines
