"""Scenario files of the car case study: the road, the faults and what must hold, without rospy.

A scenario (YAML, ``catkin_ws/src/tjp_sim/scenarios/``) has these keys (defaults in brackets):

- ``name`` (the file's name), ``description`` ['']
- ``duration``: simulated seconds; ``seed`` [1]: every random draw derives from it;
  ``rate`` [2.0]: how many times faster than real time the simulation runs
- ``profile``: the leader's driving profile, a built-in name (:data:`PROFILES`) or [[time, speed], ...]
  (speeds up to 35 km/h); ``initial_speed`` [the profile's first speed]; ``initial_gap``
  [the safety distance at that speed]
- ``mechanisms`` [all of :data:`MECHANISMS`]: the fault tolerance mechanisms attached
- ``faults`` [[]]: each one a mapping with ``kind`` and ``at`` (sim s, or [low, high] for a time
  drawn from the seed); sensor faults (:mod:`tjp_sim.faults`) name a ``sensor`` of :data:`SENSORS`
  and (except crash) an ``until``; ``power_loss`` and ``board_back`` (the board started again, as
  a backup: it re-joins the primary) name a ``board``, board_a or board_b (or ``primary`` and
  ``backup``, the boards' roles at the start: board_a and board_b); a board's power losses and
  returns alternate, a power loss first; ``board_hang`` (a ``board``, and an ``until`` if the node
  resumes, or a ``pause``: resumed that long after, a number or [low, high]) stops that board's
  controllerPid (or the ``node`` of :data:`BOARD_NODES` named) without killing it (SIGSTOP, then
  SIGCONT): its board, and its crash detector, live on; ``node: board`` freezes the whole board
  (every process of its launch, its crash detector included), as a host frozen and resumed;
  ``simulator_crash`` and ``master_crash`` take nothing more; ``node_crash`` and ``node_hang``
  (SIGKILL, SIGSTOP) name a ``node`` of :data:`MANAGED_NODES`; ``intrusion`` takes nothing more:
  an intruder on the car's network (aft_ftm's ``intruder``, once in clear and, under TLS, once with
  a certificate the policy trusts with nothing) forges a message on every topic and calls every
  service
- ``managed_tjp`` [false]: those TJP nodes run under aft_ftm's service manager
- ``boards_remote`` [false]: each board runs as a host of its own (its nodes bound to and known by an
  address of their own on the loopback, :data:`BOARD_HOSTS`): the watchdog has no power switch for it
  and cannot fence it, as with two boards on machines of their own and no switch wired in
- ``events`` [[]]: ``pedestrian`` (``at``, ``ahead`` m in front of the bumper [3.0], ``leaves`` sim s
  [never]); ``adapt`` (``script``: an adaptation script of tjp_sim or aft_ftm, ``args`` [{}], and
  either ``at`` a time or ``on_alarm``: the first alarm of that kind, e.g. implausible_gap)
- ``expect`` [{}]: ``min_gap_fraction`` [0.5]: the gap never goes below this fraction of the safety
  distance; ``stop_within`` [none]: after a safe stop the car stands still within this many seconds
- ``control`` [none]: the control experiment, ``disable`` (a mechanism) and ``hazard`` (one of
  :data:`HAZARDS`): with that mechanism removed, the same faults must cause that hazard

:func:`parse` raises ScenarioError naming the key and the value at the first problem.
"""
import math
import os
import random

import yaml
from aft_ftm.config import load_yaml

from . import resources
from .control import SafetyDistance
from .errors import TjpConfigError
from .faults import VALUE_KINDS
from .world import check_profile


class ScenarioError(TjpConfigError):
    pass


MECHANISMS = ('pbr', 'tr_imu', 'tr_ultrasonic', 'triplication_vote', 'alarm_and_stop')
SENSORS = ('imu', 'laser_0', 'laser_1', 'laser_2', 'ultrasonic')
# The boards of controllerPid, and the names that designate them (the roles are those at the start).
BOARDS = {'board_a': 'board_a', 'board_b': 'board_b', 'primary': 'board_a', 'backup': 'board_b'}
PROCESS_FAULTS = ('power_loss', 'board_back', 'board_hang', 'simulator_crash', 'master_crash', 'node_crash',
                  'node_hang', 'intrusion')
BOARD_NODES = ('controller_pid', 'cycle_after', 'board')   # what a board_hang may stop (board: all of it)
MANAGED_NODES = ('measure_manager', 'distance_security_calculator', 'command_manager', 'emergency_braking')
HAZARDS = ('collision', 'gap_violation', 'unjustified_emergency', 'service_lost', 'no_stop')
PROFILES = {
    # Stop-and-go: cruising, hard braking to a standstill (4 m/s^2), waiting, starting again.
    'stop_and_go': [[0, 8.0], [8, 8.0], [10, 0.0], [14, 0.0], [20, 8.0], [28, 8.0], [30, 0.0], [34, 0.0],
                    [40, 9.0], [48, 9.0], [50, 2.0], [54, 2.0], [60, 9.0]],
    'steady': [[0, 6.0]],
    'slow_creep': [[0, 3.0], [10, 3.0], [12, 0.0], [16, 0.0], [20, 4.0]],
}
KEYS = {'name', 'description', 'duration', 'seed', 'rate', 'profile', 'initial_speed', 'initial_gap',
        'mechanisms', 'faults', 'events', 'expect', 'control', 'managed_tjp', 'boards_remote'}
# The boards' own addresses under boards_remote (the loopback answers every 127/8 address).
BOARD_HOSTS = {'board_a': '127.0.0.2', 'board_b': '127.0.0.3'}


def _number(where, value, low=None, high=None, positive=False):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        # (NaN passed every range check: a fault at .nan never came, a min_gap_fraction of .nan passed any
        # gap; review of session 48)
        raise ScenarioError('%s must be a finite number, got %r' % (where, value))
    if positive and not value > 0:
        raise ScenarioError('%s must be > 0, got %r' % (where, value))
    if low is not None and value < low or high is not None and value > high:
        raise ScenarioError('%s must be within %s .. %s, got %r' % (where, low, high, value))
    return float(value)


def _keys(where, item, required, optional):
    if not isinstance(item, dict):
        raise ScenarioError('%s must be a mapping, got %r' % (where, item))
    unknown = sorted((str(k) for k in set(item) - set(required) - set(optional)))
    if unknown:
        raise ScenarioError('%s: unknown key %s (allowed: %s)' % (where, ', '.join(unknown),
                                                                 ', '.join(sorted(set(required) | set(optional)))))
    missing = [k for k in required if k not in item]
    if missing:
        raise ScenarioError('%s: missing key %s' % (where, ', '.join(missing)))


def _time(where, value, duration, rng):
    """A time in the run: a number, or [low, high] drawn from the scenario's seed."""
    if isinstance(value, list):
        if len(value) != 2:
            raise ScenarioError('%s must be a time or [low, high], got %r' % (where, value))
        low, high = (_number(where, v, 0, duration) for v in value)
        if low > high:
            raise ScenarioError('%s: low %g is after high %g' % (where, low, high))
        return rng.uniform(low, high)
    return _number(where, value, 0, duration)


def _fault(where, item, duration, rng):
    kind = item.get('kind') if isinstance(item, dict) else None
    extra = {'stuck': ['value'], 'offset': ['offset'], 'noise': ['sigma'], 'spikes': ['probability', 'magnitude'],
             'false_detection': ['distance'], 'crash': [], 'power_loss': ['board'], 'board_back': ['board'],
             'board_hang': ['board'], 'simulator_crash': [],
             'master_crash': [], 'node_crash': ['node'], 'node_hang': ['node'], 'intrusion': []}
    if kind not in extra:
        raise ScenarioError('%s: kind must be one of %s, got %r' % (where, ', '.join(extra), kind))
    sensor = kind in VALUE_KINDS or kind == 'crash'
    required = ['kind', 'at'] + extra[kind] + (['sensor'] if sensor else []) + (['until'] if kind in VALUE_KINDS else [])
    _keys(where, item, required, {'spikes': ['direction'], 'board_hang': ['until', 'pause', 'node']}.get(kind, []))
    if item.get('direction', 'both') not in ('both', 'up', 'down'):
        raise ScenarioError('%s: direction must be both, up or down, got %r' % (where, item['direction']))
    fault = dict(item, at=_time(where + '.at', item['at'], duration, rng))
    if sensor and item['sensor'] not in SENSORS:
        raise ScenarioError('%s: sensor must be one of %s, got %r' % (where, ', '.join(SENSORS), item['sensor']))
    if kind == 'false_detection' and item['sensor'] != 'ultrasonic':
        raise ScenarioError('%s: a false detection is a fault of the ultrasonic sensor, not %s' % (where, item['sensor']))
    if 'pause' in item:   # board_hang: resumed this long after (a number, or [low, high] drawn from the seed)
        if 'until' in item:
            raise ScenarioError('%s: give until or pause, not both' % where)
        pause = _time(where + '.pause', item['pause'], duration, rng)
        if not pause > 0:
            raise ScenarioError('%s.pause must be > 0, got %r' % (where, item['pause']))
        del fault['pause']
        fault['until'] = min(duration, fault['at'] + pause)
    if 'until' in item:
        fault['until'] = _number(where + '.until', item['until'], 0, duration)
        if fault['until'] <= fault['at']:
            raise ScenarioError('%s: until %g must come after at %g' % (where, fault['until'], fault['at']))
    for key in ('value', 'offset'):
        if key in item:
            fault[key] = _number('%s.%s' % (where, key), item[key])
    for key in ('sigma', 'magnitude', 'distance'):
        if key in item:
            fault[key] = _number('%s.%s' % (where, key), item[key], positive=True)
    if 'probability' in item:
        fault['probability'] = _number(where + '.probability', item['probability'], 0, 1)
    if kind in ('node_crash', 'node_hang') and item['node'] not in MANAGED_NODES:
        raise ScenarioError('%s: node must be one of %s, got %r' % (where, ', '.join(MANAGED_NODES), item['node']))
    if kind in ('power_loss', 'board_back', 'board_hang'):
        if not isinstance(item['board'], str) or item['board'] not in BOARDS:
            raise ScenarioError('%s: board must be one of %s, got %r' % (where, ', '.join(BOARDS), item['board']))
        fault['board'] = BOARDS[item['board']]
    if kind == 'board_hang':
        fault['node'] = item.get('node', 'controller_pid')
        if fault['node'] not in BOARD_NODES:
            raise ScenarioError('%s: node must be one of %s, got %r' % (where, ', '.join(BOARD_NODES), fault['node']))
    return fault


def _check_boards(source, faults, mechanisms):
    """Each board's power losses and returns alternate, a power loss first; board_b exists with pbr only (its
    power losses, returns and hangs need it)."""
    for board in sorted(set(BOARDS.values())):
        steps = sorted(((f['at'], f['kind']) for f in faults if f['kind'] in ('power_loss', 'board_back')
                        and f['board'] == board), key=lambda step: (step[0], step[1] != 'power_loss'))
        steps_or_hangs = steps + [(f['at'], f['kind']) for f in faults
                                  if f['kind'] == 'board_hang' and f['board'] == board]
        if steps_or_hangs and board != 'board_a' and 'pbr' not in mechanisms:
            raise ScenarioError('%s: a %s of %s needs the pbr mechanism (without it there is no backup board)'
                                % (source, steps_or_hangs[0][1], board))
        off = None
        for at, kind in steps:
            if kind == 'power_loss' and off is not None:
                raise ScenarioError('%s: power_loss of %s at %g s: it is off since %g s (bring it back first with '
                                    'board_back)' % (source, board, at, off))
            if kind == 'board_back' and off is None:
                raise ScenarioError('%s: board_back of %s at %g s: it was not powered off before (a power_loss of it '
                                    'must come first)' % (source, board, at))
            if kind == 'board_back' and at <= off:
                raise ScenarioError('%s: board_back of %s at %g s must come after its power_loss at %g s'
                                    % (source, board, at, off))
            off = at if kind == 'power_loss' else None


def _event(where, item, duration, rng):
    kind = item.get('kind') if isinstance(item, dict) else None
    if kind == 'pedestrian':
        _keys(where, item, ['kind', 'at'], ['ahead', 'leaves'])
        event = {'kind': kind, 'at': _time(where + '.at', item['at'], duration, rng),
                 'ahead': _number(where + '.ahead', item.get('ahead', 3.0), positive=True), 'leaves': None}
        if item.get('leaves') is not None:
            event['leaves'] = _number(where + '.leaves', item['leaves'], 0, duration)
            if event['leaves'] <= event['at']:
                raise ScenarioError('%s: leaves %g must come after at %g' % (where, event['leaves'], event['at']))
        return event
    if kind == 'adapt':
        _keys(where, item, ['kind', 'script'], ['args', 'at', 'on_alarm'])
        if ('at' in item) == ('on_alarm' in item):
            raise ScenarioError('%s: an adaptation runs either at a time (at) or on an alarm (on_alarm), not %s'
                                % (where, 'both' if 'at' in item else 'neither'))
        if 'on_alarm' in item and (not isinstance(item['on_alarm'], str) or not item['on_alarm']):
            raise ScenarioError('%s.on_alarm must be the kind of an alarm (e.g. implausible_gap), got %r'
                                % (where, item['on_alarm']))
        args = item.get('args', {})
        if not isinstance(item['script'], str) or not item['script']:
            raise ScenarioError('%s.script must be the name of an adaptation script, got %r' % (where, item['script']))
        if not isinstance(args, dict) or not all(isinstance(k, str) for k in args):
            raise ScenarioError('%s.args must be a mapping of names to values, got %r' % (where, args))
        return {'kind': kind, 'at': _time(where + '.at', item['at'], duration, rng) if 'at' in item else None,
                'on_alarm': item.get('on_alarm'), 'script': item['script'], 'args': {k: str(v) for k, v in args.items()}}
    raise ScenarioError('%s: kind must be pedestrian or adapt, got %r' % (where, kind))


def parse(text, source='scenario'):
    """The scenario of a YAML text, as a dict with every default filled in."""
    try:
        data = load_yaml(text)
    except yaml.YAMLError as e:
        raise ScenarioError('%s: not valid YAML: %s' % (source, e))
    _keys(source, data, ['duration', 'profile'], KEYS)
    duration = _number(source + ': duration', data['duration'], positive=True)
    seed = data.get('seed', 1)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ScenarioError('%s: seed must be an integer, got %r' % (source, seed))
    rng = random.Random('%d/scenario' % seed)
    profile = data['profile']
    if isinstance(profile, str):
        if profile not in PROFILES:
            raise ScenarioError('%s: profile must be one of %s or a list of [time, speed], got %r'
                                % (source, ', '.join(PROFILES), profile))
        profile = PROFILES[profile]
    try:
        profile = check_profile(profile)
    except TjpConfigError as e:
        raise ScenarioError('%s: profile: %s' % (source, e))
    mechanisms = data.get('mechanisms', list(MECHANISMS))
    if not isinstance(mechanisms, list) or any(m not in MECHANISMS for m in mechanisms):
        raise ScenarioError('%s: mechanisms must be a list of %s, got %r' % (source, ', '.join(MECHANISMS), mechanisms))
    scenario = {
        'name': str(data.get('name', os.path.splitext(os.path.basename(source))[0])),
        'description': str(data.get('description', '')),
        'duration': duration, 'seed': seed,
        'rate': _number(source + ': rate', data.get('rate', 2.0), 0.1, 20),
        'profile': [list(p) for p in profile],
        'initial_speed': _number(source + ': initial_speed', data.get('initial_speed', profile[0][1]), 0, 35 / 3.6),
        'mechanisms': list(mechanisms),
        'managed_tjp': data.get('managed_tjp', False),
        'boards_remote': data.get('boards_remote', False),
    }
    for key in ('managed_tjp', 'boards_remote'):
        if not isinstance(scenario[key], bool):
            raise ScenarioError('%s: %s must be true or false, got %r' % (source, key, scenario[key]))
    _check_managed(source, scenario)
    scenario['initial_gap'] = _number(source + ': initial_gap',
                                      data.get('initial_gap', SafetyDistance()(scenario['initial_speed'])), positive=True)
    for key, check in (('faults', _fault), ('events', _event)):
        items = data.get(key, [])
        if not isinstance(items, list):
            raise ScenarioError('%s: %s must be a list, got %r' % (source, key, items))
        scenario[key] = [check('%s: %s[%d]' % (source, key, i), item, duration, rng) for i, item in enumerate(items)]
    _check_boards(source, scenario['faults'], mechanisms)
    expect = data.get('expect', {})
    _keys(source + ': expect', expect, [], ['min_gap_fraction', 'stop_within'])
    scenario['expect'] = {
        'min_gap_fraction': _number(source + ': expect.min_gap_fraction', expect.get('min_gap_fraction', 0.5), 0, 1),
        'stop_within': (None if expect.get('stop_within') is None else
                        _number(source + ': expect.stop_within', expect['stop_within'], positive=True)),
    }
    control = data.get('control')
    if control is not None:
        _keys(source + ': control', control, ['disable', 'hazard'], [])
        if control['disable'] not in mechanisms:
            raise ScenarioError('%s: control.disable must be one of the scenario\'s mechanisms (%s), got %r'
                                % (source, ', '.join(mechanisms), control['disable']))
        if control['hazard'] not in HAZARDS:
            raise ScenarioError('%s: control.hazard must be one of %s, got %r' % (source, ', '.join(HAZARDS),
                                                                                 control['hazard']))
        control = dict(control)
    scenario['control'] = control
    return scenario


def path_of(name):
    """A scenario's file: a path, or the name of one shipped in the package."""
    if os.path.sep in name or name.endswith('.yaml'):
        return name
    return resources.path('scenarios', name + '.yaml')


def load(name):
    path = path_of(name)
    try:
        with open(path) as f:
            text = f.read()
    except OSError as e:
        folder = resources.path('scenarios')
        shipped = sorted(n[:-5] for n in os.listdir(folder) if n.endswith('.yaml')) if os.path.isdir(folder) else []
        raise ScenarioError('cannot read scenario %s (%s); shipped scenarios: %s' % (path, e.strerror, ', '.join(shipped)))
    return parse(text, source=os.path.basename(path))


# The managed TJP's nodes (config/tjp_services.yaml) read the outputs of these mechanisms:
# measureManager the IMU's time redundancy, distanceSecurityCalculator the lasers' vote.
MANAGED_NEEDS = ('tr_imu', 'triplication_vote')


def _check_managed(source, scenario):
    missing = [m for m in MANAGED_NEEDS if m not in scenario['mechanisms']]
    if scenario['managed_tjp'] and missing:
        raise ScenarioError('%s: managed_tjp needs the mechanisms %s (the managed nodes read their outputs: '
                            'config/tjp_services.yaml); %s missing, the car would never drive'
                            % (source, ', '.join(MANAGED_NEEDS), ', '.join(missing)))


def without(scenario, mechanism):
    """The control experiment's scenario: the same one with a mechanism removed."""
    if mechanism not in scenario['mechanisms']:
        raise ScenarioError('scenario %s has no mechanism %s to remove (it has %s)'
                            % (scenario['name'], mechanism, ', '.join(scenario['mechanisms'])))
    control = dict(scenario, mechanisms=[m for m in scenario['mechanisms'] if m != mechanism],
                   name='%s-without-%s' % (scenario['name'], mechanism))
    _check_managed('scenario %s without %s' % (scenario['name'], mechanism), control)
    return control
