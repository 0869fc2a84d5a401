"""The summary and the plot of a car simulation run, without a master, on small synthetic runs."""
import json

import pytest

from tjp_sim import scenario
from tjp_sim.control import Mode
from tjp_sim.errors import TjpConfigError
from tjp_sim.plot import plot
from tjp_sim.summary import HAZARDS, RunDataError, hazards, summarize, text

INF = float('inf')
TJP, EMERGENCY, SAFE_STOP, HOLD = int(Mode.TJP), int(Mode.EMERGENCY), int(Mode.SAFE_STOP), int(Mode.HOLD)
BOARD_A, BOARD_B = '/board_a/cycle_after', '/board_b/cycle_after'


def state(t, gap=20.0, speed=5.0, leader=5.0, accel=0.0, obstacle=INF, collided=False):
    return (t, gap, speed, leader, accel, obstacle, collided)


def steady_run(seconds=4.0, dt=0.5, **fields):
    """A follower cruising far behind its leader, controllerPid answering every 0.1 s from board a."""
    n = int(round(seconds / dt))
    return {
        'states': [state(i * dt) for i in range(n + 1)],
        'commands': [(i * dt, 0.0, TJP, '/command_manager') for i in range(n + 1)],
        'pid_commands': [(round(i * 0.1, 3), BOARD_A) for i in range(int(round(seconds / 0.1)) + 1)],
        'alarms': [],
        'events': [],
        **fields,
    }


def test_the_gap_is_measured_against_the_safety_distance_of_the_true_speed():
    # safety distance 2 + 1.5 v: 2.0 at rest, 8.0 at 4 m/s
    run = steady_run(states=[
        state(0.0, gap=3.0, speed=0.0),     # ratio 1.5
        state(1.0, gap=1.5, speed=0.0),     # below for 1 s, ratio 0.75
        state(2.0, gap=6.0, speed=4.0),     # below (8.0) for 0.5 s, ratio 0.75
        state(2.5, gap=9.0, speed=4.0),     # above for 1.5 s
        state(4.0, gap=1.2, speed=0.0),     # below, but the run ends here: no time
    ])
    s = summarize(run)
    assert s['duration'] == pytest.approx(4.0)
    assert s['min_gap'] == pytest.approx(1.2)
    assert s['min_gap_ratio'] == pytest.approx(0.6)
    assert s['time_below_safety'] == pytest.approx(1.5)


def test_a_run_that_always_keeps_its_distance_spends_no_time_below_it():
    s = summarize(steady_run())
    assert s['time_below_safety'] == 0.0
    assert s['min_gap_ratio'] == pytest.approx(20.0 / 9.5)
    assert not s['collision'] and s['collision_at'] is None
    assert s['peak_decel'] == 0.0


def test_the_collision_is_dated_by_the_first_state_that_collided():
    states = [state(t, gap=max(0.0, 4.0 - t), accel=-2.0 if t < 2 else -5.5, collided=t >= 3.0)
              for t in (0.0, 1.0, 2.0, 3.0, 3.5)]
    s = summarize(steady_run(states=states))
    assert s['collision'] is True
    assert s['collision_at'] == 3.0
    assert s['peak_decel'] == pytest.approx(5.5)


def test_only_an_emergency_braking_without_any_pedestrian_is_unjustified():
    states = [state(t, obstacle=2.5 if 3.0 <= t < 5.0 else INF) for t in (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0)]
    commands = [(0.5, -6.0, EMERGENCY, 'cm'),   # the first command counts; no pedestrian: unjustified
                (1.0, -6.0, EMERGENCY, 'cm'),   # the same activation
                (1.5, 0.0, TJP, 'cm'),
                (3.2, -6.0, EMERGENCY, 'cm'),   # the pedestrian is there (state at 3.0): justified
                (4.0, -6.0, EMERGENCY, 'cm'),
                (5.5, 0.0, HOLD, 'cm'),
                (5.6, -6.0, EMERGENCY, 'cm')]   # pedestrian gone (state at 5.0): unjustified
    s = summarize(steady_run(states=states, commands=commands))
    assert s['emergency_activations'] == 3
    assert s['unjustified_emergencies'] == 2
    assert s['holds'] == 1
    assert 'unjustified_emergency' in hazards(s, 0.5)


def pid(source, first, last):
    """controllerPid's commands every 0.1 s from first to last (s), published by source."""
    return [(round(first + i * 0.1, 3), source) for i in range(int(round((last - first) / 0.1)) + 1)]


@pytest.mark.parametrize('pid_commands,silence', [
    (pid(BOARD_A, 0.0, 2.0) + pid(BOARD_B, 2.7, 4.0), 2.0),                   # 4.0 until the end at 6.0
    (pid(BOARD_A, 0.0, 2.0) + pid(BOARD_B, 2.7, 4.0) + [(5.9, BOARD_B)], 1.9),  # 4.0 -> 5.9
    (pid(BOARD_A, 0.0, 2.0) + pid(BOARD_B, 3.5, 6.0), 1.5),                   # the failover took 1.5 s
    (pid(BOARD_A, 0.0, 2.0) + pid(BOARD_B, 2.7, 6.0), 0.7),                   # the failover took 0.7 s
])
def test_the_longest_pid_silence_spans_the_failover_and_the_end_of_the_run(pid_commands, silence):
    s = summarize(steady_run(seconds=6.0, pid_commands=pid_commands))
    assert s['longest_pid_silence'] == pytest.approx(silence)
    assert s['pid_sources'] == [BOARD_A, BOARD_B]
    assert ('service_lost' in hazards(s, 0.5)) is (silence > 1.0)


def test_a_run_without_any_pid_command_was_silent_throughout():
    s = summarize(steady_run(seconds=4.0, pid_commands=[]))
    assert s['longest_pid_silence'] == pytest.approx(4.0)
    assert s['pid_sources'] == []
    assert 'service_lost' in hazards(s, 0.5)


def stopping_run(stop_at, stopped_at):
    """Safe stop commanded at stop_at (None: never); the car stands still from stopped_at (None: never)."""
    times = [i * 0.5 for i in range(13)]     # 0 .. 6 s
    states = [state(t, speed=0.0 if stopped_at is not None and t >= stopped_at else 5.0) for t in times]
    commands = [(t, -3.0 if stop_at is not None and t >= stop_at else 0.0,
                 SAFE_STOP if stop_at is not None and t >= stop_at else TJP, 'cm') for t in times]
    return steady_run(seconds=6.0, states=states, commands=commands)


def test_the_stop_is_dated_after_the_safe_stop():
    s = summarize(stopping_run(2.0, 3.5))
    assert (s['safe_stop_at'], s['stopped_at']) == (2.0, 3.5)
    # standing still before the safe stop does not count as having stopped
    s = summarize(stopping_run(2.0, None))
    assert (s['safe_stop_at'], s['stopped_at']) == (2.0, None)


@pytest.mark.parametrize('stop_at,stopped_at,stop_within,problem', [
    (2.0, 3.5, 2.0, None),
    (2.0, 3.5, None, None),
    (None, None, None, None),
    (None, None, 2.0, 'no safe stop was commanded'),
    (2.0, None, 2.0, 'never stopped after the safe stop at t=2.00 s'),
    (2.0, 5.0, 2.0, 'stopped 3.00 s after the safe stop at t=2.00 s, more than stop_within 2.00 s'),
])
def test_the_verdict_names_a_stop_that_came_too_late_or_never(stop_at, stopped_at, stop_within, problem):
    verdict = summarize(stopping_run(stop_at, stopped_at),
                        expect={'min_gap_fraction': 0.5, 'stop_within': stop_within})['verdict']
    if problem is None:
        assert verdict == {'ok': True, 'problems': []}
    else:
        assert verdict['ok'] is False
        assert len(verdict['problems']) == 1 and problem in verdict['problems'][0]


def test_the_verdict_names_a_collision_and_the_gap_ratio_against_the_expected_fraction():
    states = [state(0.0, gap=9.5), state(1.0, gap=3.8), state(2.0, gap=0.0, collided=True)]
    verdict = summarize(steady_run(states=states), expect={'min_gap_fraction': 0.5, 'stop_within': None})['verdict']
    assert verdict['ok'] is False
    assert len(verdict['problems']) == 2
    assert 'collision at t=2.00 s' in verdict['problems'][0]
    assert '0.000' in verdict['problems'][1] and '0.500' in verdict['problems'][1]

    states = [state(0.0, gap=9.5), state(1.0, gap=3.8)]   # 3.8 / 9.5 = 0.4
    verdict = summarize(steady_run(states=states), expect={'min_gap_fraction': 0.5})['verdict']
    assert verdict == {'ok': False, 'problems': [
        'min gap ratio 0.400 is below the expected min_gap_fraction 0.500']}
    assert summarize(steady_run(states=states), expect={'min_gap_fraction': 0.39})['verdict']['ok'] is True


@pytest.mark.parametrize('expect', [{}, {'min_gap_fraction': 'half'}, {'min_gap_fraction': 0.5, 'stop_within': -1},
                                    [0.5]])
def test_a_bad_expectation_is_named(expect):
    with pytest.raises(TjpConfigError, match='expect'):
        summarize(steady_run(), expect=expect)


@pytest.mark.parametrize('changes,expected', [
    ({}, []),
    ({'collision': True, 'collision_at': 3.0}, ['collision']),
    ({'min_gap_ratio': 0.49}, ['gap_violation']),
    ({'min_gap_ratio': 0.5}, []),
    ({'unjustified_emergencies': 1}, ['unjustified_emergency']),
    ({'longest_pid_silence': 1.0}, []),
    ({'longest_pid_silence': 1.01}, ['service_lost']),
    ({'safe_stop_at': 2.0}, ['service_lost']),
    ({'safe_stop_at': 2.0, 'stopped_at': None}, ['service_lost']),
    ({'collision': True, 'min_gap_ratio': 0.0, 'longest_pid_silence': 3.0},
     ['collision', 'gap_violation', 'service_lost']),
])
def test_hazards_are_read_off_the_summary(changes, expected):
    # A run without a controlled stop: 'no_stop' is shown unless one was commanded.
    s = summarize(steady_run())
    s.update(changes)
    assert hazards(s, 0.5) == sorted(expected + (['no_stop'] if s['safe_stop_at'] is None else []))


def test_the_hazard_names_are_those_a_scenario_can_name():
    assert HAZARDS == scenario.HAZARDS


def test_fault_injection_masking_failovers_and_adaptations_are_reported():
    failover = {'t': 2.3, 'kind': 'failover', 'silence': 0.25, 'switch': 0.04, 'board': 'backup'}
    fault = {'t': 2.0, 'kind': 'fault', 'fault': 'power_loss', 'target': 'primary'}
    adaptation = {'t': 3.0, 'kind': 'adaptation', 'script': 'add_tr', 'pause': 0.12, 'ok': True}
    events = [
        {'t': 1.0, 'kind': 'fault', 'fault': 'spikes', 'target': 'laser_1'},
        {'t': 1.5, 'kind': 'injected', 'counts': {'laser_1': 3}},
        fault,
        {'t': 2.2, 'kind': 'injected', 'counts': {'laser_1': 10, 'ultrasonic': 2}},
        failover,
        adaptation,
        {'t': 3.5, 'kind': 'pedestrian', 'action': 'in'},
    ]
    alarms = [(1.1, '/vote', 'vote', 'laser_disagrees', 'laser_1'),
              (1.2, '/vote', 'vote', 'laser_disagrees', 'laser_1'),
              (1.3, '/tr', 'tr', 'false_detection_masked', ''),
              (2.1, '/ftm/alarm_manager', 'alarm_and_stop', 'imu_silent', '')]
    s = summarize(steady_run(events=events, alarms=alarms))
    assert s['faults_injected'] == {'laser_1': 10, 'ultrasonic': 2, 'total': 12}
    assert s['faults_masked'] == 3
    assert s['alarms'] == ['alarm_and_stop/imu_silent', 'tr/false_detection_masked', 'vote/laser_disagrees']
    assert [f['fault'] for f in s['faults']] == ['spikes', 'power_loss']
    assert s['faults'][1] == fault
    assert s['failovers'] == [failover]
    assert s['adaptations'] == [adaptation]
    json.dumps(s, allow_nan=False)   # the summary is stored as JSON

    lines = text(s).splitlines()
    assert len({line.index(' : ') for line in lines if ' : ' in line}) == 1   # labels aligned
    assert any('t=2.30 s, board backup failed: detected in 250 ms, switched in 40 ms' in line for line in lines)
    failed = dict(failover, ok=False, problems=['/board_b/cycle_after: unable to contact master'])
    assert any('SWITCH FAILED: /board_b/cycle_after: unable to contact master' in line
               for line in text(summarize(steady_run(events=[failed]))).splitlines())
    assert any('12 injected, 3 masked' in line for line in lines)
    assert any('ultrasonic: 2' in line for line in lines)


def test_a_run_without_injection_reports_none():
    s = summarize(steady_run())
    assert s['faults_injected'] == {'total': 0}
    assert (s['faults'], s['failovers'], s['adaptations'], s['alarms'], s['faults_masked']) == ([], [], [], [], 0)


def test_the_text_ends_with_the_verdict_and_its_problems():
    states = [state(0.0, gap=9.5), state(1.0, gap=0.0, collided=True)]
    lines = text(summarize(steady_run(states=states), expect={'min_gap_fraction': 0.5})).splitlines()
    assert lines[-3].split(' : ') == ['verdict'.ljust(len(lines[-3].split(' : ')[0])), 'FAILED']
    assert lines[-2].strip() == '- collision at t=1.00 s'
    assert 'yes, at t=1.00 s' in text(summarize(steady_run(states=states)))


@pytest.mark.parametrize('run', [{}, {'states': []}, {'states': [], 'commands': [(0.0, 0.0, TJP, 'cm')]}])
def test_a_run_without_any_car_state_is_refused_clearly(run):
    with pytest.raises(ValueError, match='no car state recorded'):
        summarize(run)
    with pytest.raises(ValueError, match='no car state recorded'):
        plot(run, '/nonexistent/never_written.png')


def test_malformed_rows_are_named():
    with pytest.raises(RunDataError, match=r'states\[1\] has 3 fields'):
        summarize({'states': [state(0.0), (1.0, 2.0, 3.0)]})
    with pytest.raises(RunDataError, match='pid_commands is not sorted'):
        summarize(steady_run(pid_commands=[(1.0, BOARD_A), (0.5, BOARD_A)]))


def test_the_plot_is_a_png_even_with_faults_a_failover_a_collision_and_no_command(tmp_path):
    dt = 0.02
    states = [state(i * dt, gap=max(0.0, 12.0 - 0.1 * i), speed=5.0, leader=max(0.0, 5.0 - 0.02 * i),
                    accel=-3.0 if i > 200 else 0.0, obstacle=2.0 if 150 <= i < 200 else INF, collided=i >= 120)
              for i in range(250)]
    commands = [(i * 0.1, 0.5, TJP, 'cm') for i in range(20)] + [
        (2.0, 0.5, HOLD, 'cm'), (2.2, -6.0, EMERGENCY, 'cm'),
        (3.0, -3.0, SAFE_STOP, 'cm'), (4.0, -3.0, SAFE_STOP, 'cm')]
    events = [{'t': 1.0, 'kind': 'fault', 'fault': 'stuck', 'target': 'laser_0'},
              {'t': 1.9, 'kind': 'fault', 'fault': 'power_loss', 'target': 'primary'},
              {'t': 2.2, 'kind': 'failover', 'silence': 0.25, 'switch': 0.04, 'board': 'backup'},
              {'t': 2.5, 'kind': 'adaptation', 'script': 'add_tr', 'pause': 0.1, 'ok': True},
              {'t': 3.0, 'kind': 'pedestrian', 'action': 'in'},
              {'t': 4.0, 'kind': 'pedestrian', 'action': 'out'}]
    run = {'states': states, 'commands': commands, 'pid_commands': [], 'alarms': [], 'events': events}
    for name, the_run, fraction in (('full.png', run, 0.5), ('bare.png', {'states': states}, None)):
        path = str(tmp_path / name)
        assert plot(the_run, path, title=name, min_gap_fraction=fraction) == path
        with open(path, 'rb') as f:
            data = f.read()
        assert data[:8] == b'\x89PNG\r\n\x1a\n'
        assert len(data) > 10000


def test_no_stop_is_a_hazard_only_where_a_controlled_stop_is_expected():
    s = summarize(steady_run())
    assert 'no_stop' in hazards(s, 0.5, stop_expected=True)
    assert 'no_stop' not in hazards(s, 0.5, stop_expected=False)


def test_the_peak_deceleration_is_the_braking_not_the_crash():
    states = [(0.0, 5.0, 5.0, 5.0, -2.5, 5.0, False), (0.02, 1.0, 5.0, 0.0, -3.0, 1.0, False),
              (0.04, 0.0, 0.0, 0.0, -250.0, 0.0, True), (0.06, 0.0, 0.0, 0.0, 0.0, 0.0, True)]
    s = summarize(steady_run(states=states))
    assert s['collision'] and s['collision_at'] == 0.04 and s['peak_decel'] == 3.0


def test_who_drove_when_and_the_rejoins_are_reported():
    pid_commands = [(round(i * 0.1, 3), BOARD_A if i < 10 or i >= 30 else BOARD_B) for i in range(40)]
    rejoin = {'t': 2.5, 'kind': 'rejoin', 'board': 'board_a', 'primary': 'board_b', 'since_back': 0.27}
    events = [{'t': 1.0, 'kind': 'failover', 'silence': 0.05, 'switch': 0.004, 'board': 'board_a'},
              {'t': 1.5, 'kind': 'fault', 'fault': 'board_back', 'target': 'board_a'},
              {'t': 2.0, 'kind': 'board_back', 'board': 'board_a'}, rejoin,
              {'t': 3.0, 'kind': 'failover', 'silence': 0.05, 'switch': 0.004, 'board': 'board_b'}]
    s = summarize(steady_run(pid_commands=pid_commands, events=events))
    assert s['pid_handovers'] == [[0.0, BOARD_A], [1.0, BOARD_B], [3.0, BOARD_A]]
    assert s['rejoins'] == [rejoin] and len(s['failovers']) == 2
    assert any('t=2.50 s, board board_a re-joined (the backup of board_b), 270 ms after it came back' in line
               for line in text(s).splitlines())
    assert summarize(steady_run())['rejoins'] == []


def random_run(rng, seconds=6.0):
    """A run with gaps closing and opening, a collision maybe, emergency, hold and safe-stop
    commands, controllerPid silent at times (or throughout), and alarms and events."""
    dt = 0.1
    n = int(seconds / dt)
    gap, speed, collided, states = rng.uniform(3, 20), rng.uniform(0, 8), False, []
    for i in range(n + 1):
        gap = max(0.0, gap + rng.uniform(-1.5, 1.0))
        speed = max(0.0, speed + rng.uniform(-1.0, 1.0))
        collided = collided or (gap == 0.0 and rng.random() < 0.5)
        states.append(state(round(i * dt, 3), gap=gap, speed=speed, obstacle=rng.choice([INF, INF, 2.0, gap]),
                            collided=collided))
    modes = [TJP] * 6 + [EMERGENCY, HOLD, SAFE_STOP]
    commands = sorted((round(rng.uniform(0, seconds), 3), -1.0, rng.choice(modes), 'cm') for _ in range(rng.randint(0, 30)))
    pids, t = [], rng.choice([0.0, 0.0, 1.6])   # controllerPid heard from the start, or late
    while rng.random() > 0.05 and t < seconds:
        t += rng.choice([0.1] * 40 + [0.5, 1.3])
        pids.append((round(t, 3), BOARD_A))
    alarms = [(round(rng.uniform(0, seconds), 3), 'x', 'pbr', 'k', '') for _ in range(rng.randint(0, 3))]
    return {'states': states, 'commands': commands, 'pid_commands': pids, 'alarms': sorted(alarms),
            'events': [], 'service_events': [{'wall': 1.0, 'event': 'fault'}]}


def test_a_hazard_shown_so_far_is_shown_by_every_longer_run():
    """What lets a control experiment end at its hazard: each hazard shown_so_far reports for a part
    of a run is a hazard of the whole run, whatever comes after (seeded; the seed is printed)."""
    import os
    import random
    from tjp_sim.summary import shown_so_far
    seed = int(os.environ.get('AFT_SIM_SEED', random.randrange(1 << 30)))
    rng = random.Random(seed)
    seen = set()
    for case in range(500):
        run = random_run(rng)
        expect = {'min_gap_fraction': rng.choice([0.3, 0.5, 0.8]), 'stop_within': None}
        stop = rng.random() < 0.5
        whole = set(hazards(summarize(run, expect), expect['min_gap_fraction'], stop))
        for until in sorted(rng.uniform(0, 6) for _ in range(5)):
            # The part received so far: every list up to until, commands and pid commands a little
            # ahead of the states (they arrive on other topics).
            ahead = until + rng.uniform(0, 0.3)
            part = {'states': [s for s in run['states'] if s[0] <= until],
                    'commands': [c for c in run['commands'] if c[0] <= ahead],
                    'pid_commands': [p for p in run['pid_commands'] if p[0] <= ahead],
                    'alarms': [a for a in run['alarms'] if a[0] <= ahead], 'events': [],
                    'service_events': run['service_events']}
            shown = shown_so_far(part, expect, stop)
            seen.update(shown)
            assert 'no_stop' not in shown
            assert set(shown) <= whole, 'seed %d case %d until %.2f: %s shown, the whole run shows %s' % (
                seed, case, until, shown, sorted(whole))
    assert {'collision', 'gap_violation', 'unjustified_emergency', 'service_lost'} <= seen, (seed, seen)
    assert shown_so_far({'states': []}, {'min_gap_fraction': 0.5, 'stop_within': None}) == []


def test_the_car_s_drivers_are_the_senders_of_the_commands_of_controllerpid_it_got():
    """A deposed board whose commands were taken between the primary's shows as a driver again (what
    the car scenario board_freeze_unfenced checks never happens); emergencies and safe stops are not
    controllerPid's."""
    commands = [(0.0, 0.0, TJP, BOARD_A), (0.5, 0.0, HOLD, BOARD_A), (1.0, 0.0, TJP, BOARD_B),
                (1.5, -6.0, EMERGENCY, '/tjp/command_manager'), (2.0, 0.0, TJP, BOARD_A),
                (2.5, -3.0, SAFE_STOP, '/tjp/command_manager')]
    s = summarize(steady_run(seconds=3.0, commands=commands))
    assert s['drivers'] == [[0.0, BOARD_A], [1.0, BOARD_B], [2.0, BOARD_A]]
    assert 'car driven by       : %s from' % BOARD_A in text(s)
