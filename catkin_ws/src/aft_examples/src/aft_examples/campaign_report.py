"""The campaign's output: the table of faults by kind (outcomes, unavailability median / p99 / max),
the violations with the command that replays them, and the timeline plot. No ROS."""
import collections

from .history import percentile


def table(records):
    """Rows (kind, faults, outcomes in words, median, p99, max unavailability in ms, then the medians of
    its two shares: the fault's, until the runner's first repair action, and the repair's, a
    relaunched site's re-join) and a total row."""
    by_kind = collections.OrderedDict()
    for record in sorted(records, key=row_kind):
        by_kind.setdefault(row_kind(record), []).append(record)
    rows = []
    for kind, group in list(by_kind.items()) + [('all', list(records))]:
        outcomes = collections.Counter(r['outcome'].split(':')[0] for r in group)
        waits = [r.get('unavailable', 0.0) * 1e3 for r in group]
        fault = [r.get('unavailable_fault', r.get('unavailable', 0.0)) * 1e3 for r in group]
        repair = [r.get('unavailable_repair', 0.0) * 1e3 for r in group]
        rows.append((kind, len(group), ', '.join('%d %s' % (n, o) for o, n in sorted(outcomes.items())),
                     percentile(waits, 50), percentile(waits, 99), max(waits) if waits else None,
                     percentile(fault, 50), percentile(repair, 50)))
    return rows


def row_kind(record):
    """The table's row of a record: its kind; an adaptation's by what it is (adapt switch, ...)."""
    return record['kind'] + (' ' + record['target'] if record['kind'] == 'adapt' else '')


def format_table(rows):
    head = ('fault kind', 'faults', 'outcomes', 'unavail. median ms', 'p99 ms', 'max ms', 'fault median ms',
            'repair median ms')
    cells = [head] + [(k, str(n), o) + tuple(_ms(v) for v in values) for k, n, o, *values in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(head))]
    lines = []
    for i, row in enumerate(cells):
        lines.append('| ' + ' | '.join(c.ljust(w) if j in (0, 2) else c.rjust(w)
                                       for j, (c, w) in enumerate(zip(row, widths))) + ' |')
        if i == 0:
            lines.append('|' + '|'.join('-' * (w + 2) for w in widths) + '|')
    return '\n'.join(lines)


def _ms(value):
    return '-' if value is None else '%.0f' % value


def replay_command(faults, seed, segment, per_segment, clients, extra=''):
    return ('scripts/campaign --faults %d --seed %d --per-segment %d --clients %d --segment %d%s'
            % (faults, seed, per_segment, clients, segment, extra))


def plot(path, segments, t0):
    """The timeline: each client's answered calls (time, latency), failed calls, faults as bands."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    colours = {}
    palette = plt.get_cmap('tab20')
    fig, ax = plt.subplots(figsize=(14, 5))
    clients = sorted({op.client for seg in segments for op in seg.ops})
    for i, client in enumerate(clients):
        ok = [(op.complete - t0, (op.complete - op.invoke) * 1e3) for seg in segments for op in seg.ops
              if op.client == client and op.outcome == 'ok']
        if ok:
            ax.scatter(*zip(*ok), s=2, label='%s answered' % client, color=plt.get_cmap('Dark2')(i))
    failed = [(op.complete - t0, (op.complete - op.invoke) * 1e3) for seg in segments for op in seg.ops
              if op.outcome != 'ok' and op.complete is not None]
    if failed:
        ax.scatter(*zip(*failed), s=8, marker='x', color='red', label='failed calls')
    for seg in segments:
        for record in seg.records:
            colour = colours.setdefault(record['kind'], palette(len(colours) % 20))
            ax.axvspan(record['start'] - t0, record.get('healed_at', record['end']) - t0, color=colour, alpha=0.25,
                       label=record['kind'] if record['kind'] not in ax.get_legend_handles_labels()[1] else None)
    ax.set_yscale('log')
    ax.set_xlabel('time since the campaign started (s)')
    ax.set_ylabel('call duration (ms)')
    ax.set_title('Campaign timeline: calls and faults (bands: fault until healed)')
    ax.legend(loc='upper left', fontsize='x-small', ncol=4, markerscale=3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
