"""What happened in one run of the car simulation, in numbers, without rospy.

A run is a dict of plain lists recorded during the run (sim time ``t`` in seconds, each list sorted
by ``t``):

- ``states``: ``(t, gap, follower_speed, leader_speed, accel, obstacle, collided)``, the ground truth
  every 0.02 s; ``obstacle`` is the true distance to the nearest thing ahead (the leader or a
  pedestrian);
  ``collided`` stays True once set. Required, and not empty.
- ``commands``: ``(t, accel, mode, source)``, what commandManager sent to the car; ``mode`` is a
  :class:`tjp_sim.control.Mode` (0 TJP, 1 EMERGENCY, 2 SAFE_STOP, 3 HOLD); in TJP and HOLD, ``source``
  is the node whose command of controllerPid commandManager took last (the board's After).
- ``pid_commands``: ``(t, source)``, each command of controllerPid and the node that published it.
- ``alarms``: ``(t, source, mechanism, kind, detail)``.
- ``events``: dicts with at least ``t`` and ``kind``; the kinds read here are ``fault``,
  ``injected``, ``failover``, ``rejoin`` (a board brought back re-joined as the backup),
  ``adaptation`` and ``pedestrian`` (others are ignored).

The lists other than ``states`` may be missing or empty: nothing of that kind happened.

- :func:`summarize`: the metrics of a run (a JSON-serialisable dict), and a verdict against the
  scenario's ``expect``.
- :func:`hazards`: which of the scenario hazards (:data:`HAZARDS`) a summary shows.
- :func:`shown_so_far`: the hazards a run still going on shows for good (a control experiment can
  end there).
- :func:`text`: the summary for a human, one aligned ``label: value`` line per metric.
"""
import bisect
import os

from .world import ULTRASONIC_RANGE
from .control import Mode, SafetyDistance
from .errors import TjpConfigError, TjpError


class RunDataError(TjpError, ValueError):
    """A recorded run cannot be summarised (no state, wrong row, rows out of order)."""


# The same names as tjp_sim.scenario.HAZARDS (a scenario's control experiment names one).
HAZARDS = ('collision', 'gap_violation', 'unjustified_emergency', 'service_lost', 'no_stop')
SERVICE_LOST_AFTER = 1.0   # s without a command of controllerPid: the TJP is no longer served
STOPPED_BELOW = 0.05       # m/s: the car stands still
STATE_FIELDS = 7
COMMAND_FIELDS = 4


def rows_of(run, key, width=None):
    """run[key] as a list ([] if missing), checked: each row has ``width`` fields (if given) and the
    rows are sorted by t. RunDataError names the first bad row."""
    rows = run.get(key)
    if rows is None:
        return []
    rows = list(rows)
    for i, row in enumerate(rows):
        if width is not None and len(row) != width:
            raise RunDataError('%s[%d] has %d fields, expected %d: %r' % (key, i, len(row), width, row))
        if i and row[0] < rows[i - 1][0]:
            raise RunDataError('%s is not sorted by t: %s[%d] at t=%r comes after t=%r'
                               % (key, key, i, row[0], rows[i - 1][0]))
    return rows


def states_of(run):
    """The run's states, checked; RunDataError if there are none."""
    if 'states' not in run:
        raise RunDataError('no car state recorded: the run has no "states" list (keys: %s)'
                           % (', '.join(sorted(run)) or 'none'))
    states = rows_of(run, 'states', STATE_FIELDS)
    if not states:
        raise RunDataError('no car state recorded: run["states"] is empty (did the simulator run?)')
    return states


def _events(run, kind):
    """Copies of the run's events of this kind, in order."""
    return [dict(event) for event in run.get('events') or () if event.get('kind') == kind]


def _emergency_starts(commands):
    """The commands that switch into EMERGENCY (the first command counts if it is one)."""
    starts, previous = [], None
    for command in commands:
        if command[2] == Mode.EMERGENCY and previous != Mode.EMERGENCY:
            starts.append(command)
        previous = command[2]
    return starts


def _state_at(states, times, t):
    """The last state recorded at or before t (the first state if t precedes them all)."""
    return states[max(0, bisect.bisect_right(times, t) - 1)]


def _longest_silence(pid_commands, end):
    """The longest time between consecutive pid commands, or from the last one to the end of the
    run. Without any pid command the whole run was silent: None is returned then."""
    if not pid_commands:
        return None
    times = [row[0] for row in pid_commands]
    gaps = [b - a for a, b in zip(times, times[1:])]
    gaps.append(max(0.0, end - times[-1]))
    return max(gaps)


def _handovers(pid_commands):
    """[t, source] each time controllerPid's commands come from another node (the first included)."""
    changes = []
    for row in pid_commands:
        if not changes or changes[-1][1] != row[1]:
            changes.append([row[0], row[1]])
    return changes


def _drivers(commands):
    """[t, source] each time the commands of controllerPid the car got (modes TJP and HOLD) come from
    another node than the last such command's (the first included)."""
    return _handovers([(c[0], c[3]) for c in commands if c[2] in (Mode.TJP, Mode.HOLD)])


def _number(name, value):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
        raise TjpConfigError('expect.%s must be a number >= 0, got %r' % (name, value))
    return float(value)


def _check_expect(expect):
    """(min_gap_fraction, stop_within or None) from a scenario's expect; TjpConfigError naming a bad value."""
    if not isinstance(expect, dict) or 'min_gap_fraction' not in expect:
        raise TjpConfigError('expect must be a mapping with min_gap_fraction, got %r' % (expect,))
    stop_within = expect.get('stop_within')
    return (_number('min_gap_fraction', expect['min_gap_fraction']),
            None if stop_within is None else _number('stop_within', stop_within))


def _verdict(summary, expect):
    """Whether the run met the scenario's expectations, and each problem in words."""
    fraction, stop_within = _check_expect(expect)
    problems = []
    if summary['collision']:
        problems.append('collision at t=%.2f s' % summary['collision_at'])
    if summary['min_gap_ratio'] < fraction:
        problems.append('min gap ratio %.3f is below the expected min_gap_fraction %.3f'
                        % (summary['min_gap_ratio'], fraction))
    if stop_within is not None:
        if summary['safe_stop_at'] is None:
            problems.append('no safe stop was commanded (expected a stop within %.2f s)' % stop_within)
        elif summary['stopped_at'] is None:
            problems.append('the car never stopped after the safe stop at t=%.2f s (expected within %.2f s)'
                            % (summary['safe_stop_at'], stop_within))
        elif summary['stopped_at'] - summary['safe_stop_at'] > stop_within:
            problems.append('the car stopped %.2f s after the safe stop at t=%.2f s, more than stop_within %.2f s'
                            % (summary['stopped_at'] - summary['safe_stop_at'], summary['safe_stop_at'],
                               stop_within))
    return {'ok': not problems, 'problems': problems}


def summarize(run, expect=None):
    """The metrics of a recorded run as a JSON-serialisable dict (see the module docstring for the
    run's lists). With ``expect`` (``min_gap_fraction``, ``stop_within`` or None), also a
    ``verdict``: ``{'ok': bool, 'problems': [str, ...]}``.

    Time-weighted metrics treat each state as holding until the next one (the last state holds for
    no time). A run without any command of controllerPid has its whole duration as the longest
    pid silence. Raises RunDataError (a ValueError) if the run has no state or a list is malformed,
    TjpConfigError if ``expect`` is.
    """
    states = states_of(run)
    commands = rows_of(run, 'commands', COMMAND_FIELDS)
    pid_commands = rows_of(run, 'pid_commands')
    alarms = rows_of(run, 'alarms')
    safety = SafetyDistance()
    times = [s[0] for s in states]
    start, end = times[0], times[-1]

    ratios = [gap / safety(speed) for _, gap, speed, _, _, _, _ in states]
    below = sum(b[0] - a[0] for a, b in zip(states, states[1:]) if a[1] < safety(a[2]))
    collided = [s[0] for s in states if s[6]]
    starts = _emergency_starts(commands)
    # Unjustified: nothing was within the ultrasonic sensor's range, so the detection was false.
    unjustified = [c for c in starts if _state_at(states, times, c[0])[5] > ULTRASONIC_RANGE]
    safe_stop_at = next((c[0] for c in commands if c[2] == Mode.SAFE_STOP), None)
    stopped_at = None
    if safe_stop_at is not None:
        stopped_at = next((s[0] for s in states if s[0] >= safe_stop_at and s[2] < STOPPED_BELOW), None)
    silence = _longest_silence(pid_commands, end)
    injected = _events(run, 'injected')
    counts = dict(injected[-1].get('counts') or {}) if injected else {}
    counts['total'] = sum(counts.values())

    summary = {
        'duration': end - start,
        'min_gap': min(s[1] for s in states),
        'min_gap_ratio': min(ratios),
        'time_below_safety': below,
        'collision': bool(collided),
        'collision_at': collided[0] if collided else None,
        # Braking the car did (a comfort and safety figure), not the crash that stopped it.
        'peak_decel': max([0.0] + [-s[4] for s in states if not collided or s[0] < collided[0]]),
        'emergency_activations': len(starts),
        'unjustified_emergencies': len(unjustified),
        'safe_stop_at': safe_stop_at,
        'stopped_at': stopped_at,
        'holds': sum(1 for c in commands if c[2] == Mode.HOLD),
        'longest_pid_silence': end - start if silence is None else silence,
        'pid_sources': sorted({row[1] for row in pid_commands}),
        'pid_handovers': _handovers(pid_commands),
        'drivers': _drivers(commands),
        'failovers': _events(run, 'failover'),
        'rejoins': _events(run, 'rejoin'),
        'faults': _events(run, 'fault'),
        'faults_injected': counts,
        'faults_masked': sum(1 for a in alarms if a[3].endswith('_masked') or a[3] == 'laser_disagrees'),
        'alarms': sorted({'%s/%s' % (a[2], a[3]) for a in alarms}),
        # road time from the start of the run of each alarm kind's first occurrence
        'alarm_first_at': {kind: min(a[0] for a in alarms if a[3] == kind) - start for kind in {a[3] for a in alarms}},
        'adaptations': _events(run, 'adaptation'),
    }
    if expect is not None:
        summary['verdict'] = _verdict(summary, expect)
    return summary


def hazards(summary, min_gap_fraction, stop_expected=True):
    """The sorted names (of :data:`HAZARDS`) of the hazards a summary shows. ``no_stop`` is one only
    where a controlled stop is expected (a failure the TJP cannot survive happened)."""
    present = {
        'collision': summary['collision'],
        'gap_violation': summary['min_gap_ratio'] < min_gap_fraction,
        'unjustified_emergency': summary['unjustified_emergencies'] > 0,
        # The TJP no longer drives: controllerPid silent, or the car stopped for good by an alarm.
        'service_lost': summary['longest_pid_silence'] > SERVICE_LOST_AFTER or summary['safe_stop_at'] is not None,
        # A failure the TJP cannot survive went unanswered: no controlled stop was even commanded.
        'no_stop': stop_expected and summary['safe_stop_at'] is None,
    }
    return sorted(name for name, shown in present.items() if shown)


def _time_of(key, row):
    return row['t'] if key == 'events' else row[0]


def shown_so_far(run, expect, stop_expected=True):
    """The hazards a run still going on shows already, such that every longer run (the same records
    and more after them) shows them too: a control experiment may end once its hazard is here.

    The records are read up to the last car state (a command received before the state of its time
    would be judged against an older state). ``no_stop`` (no controlled stop commanded) is known
    only at the end and is never returned; nor is a ``service_lost`` that rests only on controllerPid
    having said nothing yet (the silence before its first command does not count once it speaks).
    ``service_events`` (dated on the wall clock) are left out. Returns [] while no state is recorded.
    """
    states = run.get('states') or []
    if not states:
        return []
    until = states[-1][0]
    cut = {key: [row for row in rows if _time_of(key, row) <= until] for key, rows in run.items()
           if key != 'service_events'}
    summary = summarize(cut, expect)
    shown = set(hazards(summary, expect['min_gap_fraction'], stop_expected)) - {'no_stop'}
    if not cut.get('pid_commands') and summary['safe_stop_at'] is None:
        shown.discard('service_lost')
    return sorted(shown)


def _ms(seconds):
    return '?' if seconds is None else '%.0f ms' % (seconds * 1000.0)


def _at(t):
    return 'never' if t is None else 't=%.2f s' % t


def text(summary):
    """The summary for a human: aligned ``label: value`` lines, details indented below them."""
    s = summary
    lines = []   # (label, value, [detail lines])
    lines.append(('duration', '%.2f s' % s['duration'], []))
    lines.append(('min gap', '%.2f m (%.2f of the safety distance)' % (s['min_gap'], s['min_gap_ratio']), []))
    lines.append(('time below safety', '%.2f s' % s['time_below_safety'], []))
    lines.append(('collision', 'yes, at %s' % _at(s['collision_at']) if s['collision'] else 'no', []))
    lines.append(('peak deceleration', '%.2f m/s^2' % s['peak_decel'], []))
    lines.append(('emergency braking', '%d activation(s), %d unjustified'
                  % (s['emergency_activations'], s['unjustified_emergencies']), []))
    if s['safe_stop_at'] is None:
        stop = 'none'
    elif s['stopped_at'] is None:
        stop = 'commanded at %s, the car never stopped' % _at(s['safe_stop_at'])
    else:
        stop = 'commanded at %s, stopped at %s (%.2f s later)' % (
            _at(s['safe_stop_at']), _at(s['stopped_at']), s['stopped_at'] - s['safe_stop_at'])
    lines.append(('safe stop', stop, []))
    lines.append(('held commands', '%d' % s['holds'], []))
    lines.append(('longest pid silence', '%.3f s' % s['longest_pid_silence'], []))
    lines.append(('pid sources', ', '.join(s['pid_sources']) or 'none', []))
    drivers = s.get('drivers') or []
    lines.append(('car driven by', ' then '.join('%s from %s' % (d, _at(t)) for t, d in drivers) or 'nobody', []))
    lines.append(('failovers', '%d' % len(s['failovers']), [
        '%s, board %s failed: detected in %s, %s' % (
            _at(f.get('t')), f.get('board', '?'), _ms(f.get('silence')),
            'switched in %s' % _ms(f.get('switch')) if f.get('ok', True) else
            'SWITCH FAILED: %s' % '; '.join(f.get('problems') or ['?']))
        for f in s['failovers']]))
    lines.append(('re-joins', '%d' % len(s['rejoins']), [
        '%s, board %s re-joined (the backup of %s), %s after it came back' % (
            _at(r.get('t')), r.get('board', '?'), r.get('primary', '?'), _ms(r.get('since_back')))
        for r in s['rejoins']]))
    lines.append(('faults', '%d' % len(s['faults']), [
        '%s: %s on %s' % (_at(f.get('t')), f.get('fault', '?'), f.get('target', '-')) for f in s['faults']]))
    injected = s['faults_injected']
    lines.append(('faulty readings', '%d injected, %d masked' % (injected.get('total', 0), s['faults_masked']), [
        '%s: %d' % (sensor, count) for sensor, count in sorted(injected.items()) if sensor != 'total']))
    lines.append(('alarms', ', '.join(s['alarms']) or 'none', []))
    lines.append(('adaptations', '%d' % len(s['adaptations']), [
        '%s: %s, paused %s, %s' % (_at(a.get('t')), a.get('script', '?'), _ms(a.get('pause')),
                                   'ok' if a.get('ok') else 'FAILED')
        for a in s['adaptations']]))
    if 'tls' in s:
        lines.append(('mutual TLS', 'on (%s): %d TLS alarm(s), %d refusal(s) of the car\'s own nodes' % (
            os.path.basename(s['tls']['policy']), s['tls']['alarms'], len(s['tls']['policy_gaps'])),
            s['tls']['policy_gaps'][:3]))
    if s.get('intrusions'):
        lines.append(('intruders', '%d' % len(s['intrusions']), [
            '%s: %s' % (i['party'], i['error'] if i.get('error') else
                        '%d topics forged, heard on %d; %d services called, %d refused, %d served'
                        % (len(i['topics']), len(i['connected']), i['services'], i['refused'], len(i['served'])))
            for i in s['intrusions']]))
    if 'verdict' in s:
        verdict = s['verdict']
        lines.append(('verdict', 'OK' if verdict['ok'] else 'FAILED', ['- ' + p for p in verdict['problems']]))

    width = max(len(label) for label, _, _ in lines)
    out = []
    for label, value, details in lines:
        out.append('%-*s : %s' % (width, label, value))
        out.extend(' ' * (width + 3) + detail for detail in details)
    return '\n'.join(out)
