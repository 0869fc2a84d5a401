"""The benchmark report's plots (PNG, matplotlib without a display), each from the figures dict.

Each function draws one plot into path and returns path, or None when its figures are missing.
"""
import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (the backend is chosen first)
from matplotlib.ticker import MaxNLocator  # noqa: E402

from aft_bench.report import get  # noqa: E402


def _save(fig, path):
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches='tight')
    plt.close(fig)
    return path


def latency(figures, path):
    """Median and p99 latency per mechanism, with the relay chain of the same length beside each."""
    configs = get(figures, 'mechanisms.configs')
    if not configs:
        return None
    order = get(figures, 'mechanisms.order') or sorted(configs)
    names = [n for n in order if n in configs]
    med = [configs[n]['median_s'] * 1e3 for n in names]
    p99 = [configs[n]['p99_s'] * 1e3 for n in names]
    # the chain's median scaled to this row's median by the interleaved ratio
    chain = [configs[n]['median_s'] / configs[n]['chain']['ratio'] if configs[n].get('chain') else None
             for n in names]
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(names) + 1.5))
    ys = range(len(names))
    ax.barh(ys, p99, color='#c6dbef', label='p99')
    ax.barh(ys, med, color='#2171b5', label='median')
    cx = [(y, c * 1e3) for y, c in zip(ys, chain) if c]
    if cx:
        ax.scatter([c for _, c in cx], [y for y, _ in cx], marker='|', s=300, color='#e6550d', zorder=3,
                   label='relay chain, same messages (median)')
    ax.set_yticks(list(ys))
    ax.set_yticklabels(['%s (%s msg)' % (n, configs[n].get('hops') or 0) for n in names])
    ax.invert_yaxis()
    ax.set_xlabel('latency of one call (ms)')
    ax.set_title('Latency per mechanism and composition')
    ax.legend(loc='upper center', bbox_to_anchor=(0.5, -0.22 - 0.6 / (len(names) + 3)), ncol=3, fontsize=8)
    return _save(fig, path)


def failover(figures, path):
    """The distribution of failover and detection times over the injected power losses."""
    samples = get(figures, 'pbr.failover_samples')
    if not samples:
        return None
    fail = [s['failover_s'] * 1e3 for s in samples if s['failover_s'] is not None]
    det = [s['detection_s'] * 1e3 for s in samples if s['detection_s'] is not None]
    fig, ax = plt.subplots(figsize=(7, 3.5))
    bins = max(5, min(20, len(fail)))
    ax.hist([det, fail], bins=bins, label=['detection', 'failover (client wait)'], color=['#9ecae1', '#08519c'])
    timeout = get(figures, 'pbr.timeout_s')
    if timeout:
        ax.axvline(timeout * 1e3, color='grey', ls='--', lw=1, label='detection timeout')
    ax.set_xlabel('ms after the power loss')
    ax.set_ylabel('power losses')
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_title('PBR failover over %d power losses of the primary' % len(samples))
    ax.legend(fontsize=8)
    return _save(fig, path)


def adaptation(figures, path, label=None):
    """Each request's wait against its sending time across one adaptation, paper order and prepared."""
    runs = [r for r in get(figures, 'adaptation.runs') or [] if r.get('timeline')]
    if not runs:
        return None
    label = label or runs[0]['adaptation']
    chosen = {}
    for r in runs:
        if r['adaptation'] == label and r['mode'] not in chosen:
            chosen[r['mode']] = r
    fig, axes = plt.subplots(len(chosen), 1, figsize=(8, 2.6 * len(chosen)), sharex=False, squeeze=False)
    for ax, (mode, run) in zip(axes[:, 0], sorted(chosen.items())):
        t = [p[0] for p in run['timeline']]
        wait = [p[1] * 1e3 for p in run['timeline']]
        bad = [(p[0], p[1] * 1e3) for p in run['timeline'] if not p[2]]
        ax.plot(t, wait, '.', ms=3, color='#08519c', label='request (wait)')
        if bad:
            ax.plot([b[0] for b in bad], [b[1] for b in bad], 'x', color='red', label='wrong or lost')
        end = run.get('adaptation_end_s')
        ax.axvspan(0, end if end else 0.01, color='#fdae6b', alpha=0.4, label='adaptation running')
        ax.set_yscale('log')
        ax.set_ylabel('wait (ms)')
        ax.set_title('%s, %s order: %d requests, %d lost, client pause %.0f ms' % (
            label, mode, run['requests'], run['lost'], (run.get('client_pause_s') or 0) * 1e3), fontsize=9)
        ax.legend(fontsize=7, loc='upper left')
    axes[-1, 0].set_xlabel('request sent at (s from the adaptation\'s start)')
    return _save(fig, path)


def car(figures, path):
    """Gap and safety distance over time in one car scenario, with and without its mechanism."""
    series = get(figures, 'car.series')
    if not series:
        return None
    scenario = series['scenario']
    fig, ax = plt.subplots(figsize=(8, 3.8))
    styles = {'with': ('#08519c', 'with the mechanism'), 'without': ('#cb181d', 'without it')}
    for side in ('with', 'without'):
        points = series.get(side)
        if not points:
            continue
        color, text = styles[side]
        ax.plot([p[0] for p in points], [p[1] for p in points], color=color, label='gap, ' + text)
        ax.plot([p[0] for p in points], [p[2] for p in points], color=color, ls=':', lw=1,
                label='safety distance, ' + text)
        hit = series.get('collision_at', {}).get(side)
        if hit is not None:
            ax.axvline(hit, color=color, lw=1, ls='--', label='collision, ' + text)
    ax.set_xlabel('simulated time (s)')
    ax.set_ylabel('m')
    ax.set_ylim(bottom=0)
    ax.set_title('Car scenario %s: gap to the leader' % scenario)
    ax.legend(fontsize=7)
    return _save(fig, path)


def clients(figures, path):
    """Throughput and p99 latency against the number of concurrent clients, per configuration."""
    rows = get(figures, 'clients.rows')
    if not rows:
        return None
    counts = sorted({r['clients'] for r in rows})
    names = sorted({r['configuration'] for r in rows}, key=lambda n: (not n.startswith('direct'), n))
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for name in names:
        mine = sorted((r for r in rows if r['configuration'] == name), key=lambda r: r['clients'])
        xs = [r['clients'] for r in mine]
        ax1.plot(xs, [r['throughput_per_s'] for r in mine], marker='o', label=name)
        ax2.plot(xs, [(r['latency_p99_s'] or 0) * 1e3 for r in mine], marker='o', label=name)
    for ax, label in ((ax1, 'throughput (calls/s, log)'), (ax2, 'latency p99 (ms)')):
        ax.set_xscale('log', base=2)
        ax.set_xticks(counts)
        ax.set_xticklabels([str(n) for n in counts])
        ax.set_xlabel('concurrent clients')
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    ax1.set_yscale('log')
    ax1.legend(fontsize=8)
    ax1.set_title('Throughput')
    ax2.set_title('Latency p99')
    return _save(fig, path)


PLOTS = (('latency', latency), ('failover', failover), ('adaptation', adaptation), ('car', car), ('clients', clients))


def draw_all(figures, folder):
    """Draw every plot whose figures exist into folder; returns {name: file name}."""
    import os
    drawn = {}
    for name, draw in PLOTS:
        try:
            if draw(figures, os.path.join(folder, name + '.png')):
                drawn[name] = name + '.png'
        except (KeyError, TypeError, ValueError, IndexError) as e:   # partial figures: no plot, not no report
            plt.close('all')
            drawn[name + '_error'] = '%s: %s' % (type(e).__name__, e)
    return drawn
