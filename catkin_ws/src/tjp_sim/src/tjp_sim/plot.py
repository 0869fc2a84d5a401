"""A picture of one run of the car simulation (a PNG), headless, without rospy.

:func:`plot` draws three panels over sim time, for a run as described in :mod:`tjp_sim.summary`:

1. the gap and the safety distance of the follower's true speed (m), optionally the smallest gap
   the scenario accepts (``min_gap_fraction`` of the safety distance), and a red X at a collision;
2. the follower's and the leader's speeds (m/s);
3. the acceleration commandManager sent to the car (m/s^2) as a step line, the background shaded
   by mode (EMERGENCY red, SAFE_STOP grey, HOLD yellow).

Each panel marks the events: faults (dashed), failovers (solid), adaptations (dash-dotted) and the
pedestrian stepping in or out (dotted); their labels are written once, in the top panel.
matplotlib is imported only when a plot is drawn.
"""
from .control import Mode, SafetyDistance
from .summary import COMMAND_FIELDS, rows_of, states_of

FIGSIZE = (12, 8)    # inches
DPI = 100
MODE_SHADES = {      # mode -> (colour, label); TJP is not shaded
    Mode.EMERGENCY: ('#f4a6a6', 'EMERGENCY'),
    Mode.SAFE_STOP: ('#c8c8c8', 'SAFE_STOP'),
    Mode.HOLD: ('#fbe79a', 'HOLD'),
}


def _markers(events):
    """(t, label, line style, colour) of each event to mark, in order."""
    marks = []
    for event in events:
        kind, t = event.get('kind'), event['t']
        if kind == 'fault':
            marks.append((t, '%s/%s' % (event.get('fault', '?'), event.get('target', '-')), '--', 'tab:red'))
        elif kind == 'failover':
            marks.append((t, 'failover', '-', 'tab:purple'))
        elif kind == 'adaptation':
            marks.append((t, 'adapt %s' % event.get('script', '?'), '-.', 'tab:green'))
        elif kind == 'pedestrian':
            marks.append((t, 'pedestrian %s' % event.get('action', '?'), ':', 'tab:brown'))
    return marks


def _mode_spans(commands, end):
    """(start, stop, mode) of each run of consecutive commands in one mode; the last lasts until
    ``end`` (or its own time, if later)."""
    spans = []
    for t, _, mode, _ in commands:
        if spans and spans[-1][2] == mode:
            continue
        if spans:
            spans[-1][1] = t
        spans.append([t, None, mode])
    if spans:
        spans[-1][1] = max(end, spans[-1][0])
    return [tuple(span) for span in spans]


def plot(run, path, title='', min_gap_fraction=None):
    """Draw the run into a PNG at ``path`` (about 12 x 8 inches at 100 dpi) and return ``path``.

    ``min_gap_fraction`` (e.g. the scenario's expect) adds the smallest accepted gap to the top
    panel. Lists other than ``states`` may be empty or missing; an empty ``states`` raises
    :class:`tjp_sim.summary.RunDataError` (a ValueError).
    """
    import matplotlib
    matplotlib.use('Agg')
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    states = states_of(run)
    commands = rows_of(run, 'commands', COMMAND_FIELDS)
    safety = SafetyDistance()
    t = [s[0] for s in states]
    start, end = t[0], t[-1]

    figure = Figure(figsize=FIGSIZE, dpi=DPI)
    gap_ax, speed_ax, command_ax = figure.subplots(3, 1, sharex=True)

    # (a) gap and safety distance
    gap_ax.plot(t, [s[1] for s in states], color='tab:blue', label='gap')
    distance = [safety(s[2]) for s in states]
    gap_ax.plot(t, distance, color='tab:orange', label='safety distance')
    if min_gap_fraction is not None:
        gap_ax.plot(t, [min_gap_fraction * d for d in distance], color='tab:orange', linestyle=':',
                    label='%.2f x safety distance' % min_gap_fraction)
    collision = next((s for s in states if s[6]), None)
    if collision is not None:
        gap_ax.plot([collision[0]], [collision[1]], linestyle='none', marker='x', markersize=14,
                    markeredgewidth=3, color='red', label='collision t=%.2f s' % collision[0], zorder=5)
    gap_ax.set_ylabel('gap (m)')

    # (b) speeds
    speed_ax.plot(t, [s[2] for s in states], color='tab:blue', label='follower')
    speed_ax.plot(t, [s[3] for s in states], color='tab:gray', label='leader')
    speed_ax.set_ylabel('speed (m/s)')

    # (c) the command sent to the car, over its mode
    shaded = set()
    for span_start, span_stop, mode in _mode_spans(commands, end):
        if mode in MODE_SHADES:
            command_ax.axvspan(span_start, span_stop, color=MODE_SHADES[mode][0], alpha=0.6, linewidth=0)
            shaded.add(Mode(mode))
    if commands:
        # the last command holds until the end of the run
        steps = [(c[0], c[1]) for c in commands] + [(max(end, commands[-1][0]), commands[-1][1])]
        command_ax.step([s[0] for s in steps], [s[1] for s in steps], where='post', color='black',
                        linewidth=1, label='command')
    else:
        command_ax.text(0.5, 0.5, 'no command recorded', transform=command_ax.transAxes, ha='center',
                        va='center', color='gray')
    command_ax.axhline(0.0, color='gray', linewidth=0.5)
    command_ax.set_ylabel('command (m/s^2)')
    command_ax.set_xlabel('sim time (s)')

    # events on every panel, labelled once at the top
    for when, label, style, colour in _markers(run.get('events') or ()):
        for ax in (gap_ax, speed_ax, command_ax):
            ax.axvline(when, linestyle=style, color=colour, linewidth=1)
        gap_ax.text(when, 0.98, ' ' + label, transform=gap_ax.get_xaxis_transform(), rotation=90,
                    ha='right', va='top', fontsize=7, color=colour)

    handles, labels = command_ax.get_legend_handles_labels()
    for mode in sorted(shaded):
        handles.append(Patch(color=MODE_SHADES[mode][0], label=MODE_SHADES[mode][1]))
        labels.append(MODE_SHADES[mode][1])
    # legends outside, on the right: they hide no data (a collision is often in a corner)
    if handles:
        command_ax.legend(handles, labels, loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8)
    for ax in (gap_ax, speed_ax):
        ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8)
    for ax in (gap_ax, speed_ax, command_ax):
        ax.grid(True, alpha=0.3)
    if end > start:
        command_ax.set_xlim(start, end)
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    figure.savefig(path, dpi=DPI)
    return path
