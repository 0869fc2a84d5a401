"""The crash detectors' verdicts heard during a campaign, judged against the faults injected. No ROS.

A verdict (a replica's crash detector declaring its peer site failed) is *explained* when it falls
inside the window of a fault that touched the site it names: from the fault's start until the
deployment was whole again (``healed_at``). Any other verdict is a **false suspicion**: a site that
nothing touched was declared failed (while nodes started, during an adaptation, during a fault of
another site, after a healing). A false suspicion costs a failover, fences a correct replica and
leaves the pair alone until it re-joins, so the campaign counts them; issue 15's target is none over
1000 faults.

The detection time of a fault is the time from its start to the first verdict about the site it
touched (faults of one site only: a partition of the pair has no single victim).
"""
import collections

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


def judge(verdicts, records):
    """(explained, false, detections): the verdicts inside the window of a fault that touched the
    site they name, the others, and per fault of one site the seconds from its start to its first
    verdict ({record index: s}). records: the campaign's fault records (start, healed_at or end,
    sites)."""
    explained, false, detections = [], [], {}
    for verdict in sorted(verdicts):
        cause = None
        for record in records:
            stop = record.get('healed_at') or record.get('end') or record['start']
            if record['start'] <= verdict.time <= stop and verdict.failed in record.get('sites', ()):
                cause = record
                break
        if cause is None:
            false.append(verdict)
            continue
        explained.append(verdict)
        if len(cause.get('sites', ())) == 1 and cause['index'] not in detections:
            detections[cause['index']] = verdict.time - cause['start']
    return explained, false, detections


def summary(verdicts, records):
    """The campaign's detection figures, for its report and campaign.json."""
    explained, false, detections = judge(verdicts, records)
    failovers = [r.get('unavailable', 0.0) * 1e3 for r in records if r['outcome'] == 'failover']
    by_kind = collections.OrderedDict()
    for record in sorted(records, key=lambda r: r['kind']):
        if record['index'] in detections:
            by_kind.setdefault(record['kind'], []).append(detections[record['index']] * 1e3)
    return {
        'verdicts': len(verdicts), 'explained': len(explained), 'false_suspicions': len(false),
        'false': [dict(v._asdict()) for v in false],
        'detection_ms_median': percentile([d * 1e3 for d in detections.values()], 50),
        'detection_ms_by_kind': {k: percentile(v, 50) for k, v in by_kind.items()},
        'failover_unavailable_ms_median': percentile(failovers, 50), 'failovers': len(failovers),
    }


def format_summary(s, timeout):
    """The report's lines on detection."""
    def ms(value):
        return '-' if value is None else '%.1f ms' % value
    lines = ['detection (crash detector timeout %.0f ms): %d verdicts, %d explained by a fault, %d false suspicions; '
             'detection median %s (%s); failovers %d, unavailability median %s'
             % (timeout * 1e3, s['verdicts'], s['explained'], s['false_suspicions'], ms(s['detection_ms_median']),
                ', '.join('%s %s' % (k, ms(v)) for k, v in s['detection_ms_by_kind'].items()) or 'none detected',
                s['failovers'], ms(s['failover_unavailable_ms_median']))]
    for v in s['false']:
        lines.append('  false suspicion at %.3f: %s declared %s failed (%s)' % (v['time'], v['reporter'], v['failed'],
                                                                         v['reason']))
    return lines
