"""A service manager for loosely coupled services (third paper: fault detection and recovery in
critical real-time systems by loose coupling), without rospy and without processes.

- :func:`parse_config`: the configuration file (YAML), every key checked and defaulted
  (:data:`SERVICE_KEYS`, :data:`MANAGER_KEYS` document each one);
- :class:`Service`: one service's explicit state machine (:class:`State`, one ``_change()``,
  every edge in :data:`EDGES`) and its error counts;
- :func:`detect`: the faults a sample of a service shows (exit status, hang, heartbeat timeout,
  an error the service reported, CPU or memory over its limit);
- :class:`Supervisor`: the policies. Restart within a limit per time window, terminate, run a
  program or alert; dependants restarted or terminated with a service; escalation to a safe state
  (limit exhausted, or a critical service that cannot be recovered) that stays until an operator
  clears it.

The supervisor decides; the caller (aft_service_manager.ros.service_manager_node) acts: it spawns and kills
processes and reports what it observed. ``now`` is always passed in.
"""
import collections
import enum
import math
import re
import shlex

import yaml

from aft_ftm.config import load_yaml
from aft_ftm.errors import AftError


class ServiceConfigError(AftError):
    """The configuration is malformed; the message names the service, the key and the value."""


class State(enum.Enum):
    STOPPED = 0      # not running: never started, stopped by an operator, or terminated by a policy
    STARTING = 1     # spawned, not yet heard (heartbeat) or not yet past its start grace
    RUNNING = 2
    ERROR = 3        # a fault was detected; the failure action is being decided
    RESTARTING = 4   # being killed, to be spawned again
    FAILED = 5       # restart limit exhausted, or it cannot be started: stays until an operator starts it


EDGES = {
    (State.STOPPED, State.STARTING): 'started (by the manager at start, an operator, or with a dependency; or its '
                                     'spawn asked, and failed; or found ended at start, left by an earlier manager)',
    (State.FAILED, State.STARTING): 'an operator starts it again (error counts kept, restart allowance renewed)',
    (State.STARTING, State.RUNNING): 'heard from (or alive past its start grace, without heartbeats)',
    (State.STARTING, State.ERROR): 'a fault before it was running (exit, start timeout, ...)',
    (State.RUNNING, State.ERROR): 'a fault was detected',
    (State.ERROR, State.RESTARTING): 'failure action restart, within the restart limit',
    (State.ERROR, State.STOPPED): 'failure action terminate, run or alert; or terminated with a dependency',
    (State.ERROR, State.FAILED): 'restart limit exhausted',
    (State.ERROR, State.RUNNING): 'failure action alert on a service still running: it goes on',
    (State.ERROR, State.STARTING): 'failure action alert on a service still starting (memory over its limit): '
                                   'it goes on starting',
    (State.RESTARTING, State.STARTING): 'killed and spawned again (or its spawn asked, and failed)',
    (State.RESTARTING, State.STOPPED): 'terminated with a dependency while it was restarting',
    (State.STARTING, State.STOPPED): 'stopped by an operator or terminated with a dependency',
    (State.RUNNING, State.STOPPED): 'stopped by an operator or terminated with a dependency',
    (State.RUNNING, State.RESTARTING): 'restarted by an operator or with a dependency',
    (State.STARTING, State.RESTARTING): 'restarted by an operator or with a dependency',
    (State.STOPPED, State.RESTARTING): 'restarted by an operator or with a dependency',
    (State.FAILED, State.STOPPED): 'stopped by an operator',
}

ACTIONS = ('restart', 'terminate', 'run', 'alert')


# -- configuration -------------------------------------------------------------------------------
def _size(where, value):
    """Bytes: an integer, or a string like 200MB, 1.5GiB, 512k; or a percentage of the RAM: '10%'."""
    if isinstance(value, bool):
        raise ServiceConfigError('%s must be bytes or a percentage, got %r' % (where, value))
    if isinstance(value, (int, float)):
        if not _number(value) or value <= 0:
            raise ServiceConfigError('%s must be a finite number of bytes > 0, got %r' % (where, value))
        return ('bytes', float(value))
    match = re.match(r'^\s*([0-9.]+)\s*(%|[kKmMgG]i?[bB]?|[bB])?\s*$', str(value))
    if not match:
        raise ServiceConfigError('%s must be bytes (e.g. 200MB) or a percentage (e.g. 10%%), got %r' % (where, value))
    try:
        number, unit = float(match.group(1)), (match.group(2) or 'b').lower()
    except ValueError:   # digits and dots, but not a number: 1.2.3MB
        raise ServiceConfigError('%s must be bytes (e.g. 200MB) or a percentage (e.g. 10%%), got %r' % (where, value))
    if not number > 0 or not math.isfinite(number):   # 1e400 digits read as inf (review of session 34)
        raise ServiceConfigError('%s must be a finite number > 0, got %r' % (where, value))
    if unit == '%':
        if number > 100:
            raise ServiceConfigError('%s: a percentage of the RAM cannot exceed 100, got %r' % (where, value))
        return ('percent', number)
    scale = {'b': 1, 'k': 1e3, 'm': 1e6, 'g': 1e9, 'ki': 1024, 'mi': 1024 ** 2, 'gi': 1024 ** 3}[unit.rstrip('b') or 'b']
    return ('bytes', number * scale)


def _cpu(where, value):
    """Percent of one core (100 = one core busy), '80%' or 80."""
    if isinstance(value, bool):
        raise ServiceConfigError('%s must be a percentage of one core, got %r' % (where, value))
    text = str(value).strip()
    try:
        number = float(text[:-1] if text.endswith('%') else text)
    except ValueError:
        raise ServiceConfigError('%s must be a percentage of one core (e.g. 80%%), got %r' % (where, value))
    if not number > 0 or not math.isfinite(number):
        raise ServiceConfigError('%s must be a finite number > 0, got %r' % (where, value))
    return number


def _number(value):
    """Whether value is a finite number (not a flag: YAML's true is an int to Python; .inf, .nan refused:
    a kill timeout of .inf waited for ever, a period of .inf made the manager's wake time NaN). Nor is
    an int beyond a float's range: math.isfinite raised OverflowError, a traceback instead of a config
    error (review of session 34)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _positive(where, value):
    if not _number(value) or not value > 0:
        raise ServiceConfigError('%s must be a finite number > 0, got %r' % (where, value))
    return float(value)


def _cycle(where, value):
    """The manager's period: > 0 and at most an hour. Past about 24.8 days poll() raised OverflowError,
    outside the loop's handler: supervision ended while the node ran on (review of session 48)."""
    value = _positive(where, value)
    if value > 3600.0:
        raise ServiceConfigError('%s must be at most 3600 s (an hour), got %r' % (where, value))
    return value


def _non_negative(where, value):
    if not _number(value) or value < 0:
        raise ServiceConfigError('%s must be a finite number >= 0, got %r' % (where, value))
    return float(value)


def _count(where, value):
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ServiceConfigError('%s must be an integer >= 0, got %r' % (where, value))
    return value


def _flag(where, value):
    if not isinstance(value, bool):
        raise ServiceConfigError('%s must be true or false, got %r' % (where, value))
    return value


def _command(where, value):
    """A string is split as a shell would (quotes kept together: sh -c "echo hi" is 3 arguments, not 4),
    without running a shell; the program, the first argument, must not be empty (review of session 34)."""
    args = None
    if isinstance(value, str):
        try:
            args = shlex.split(value)
        except ValueError as e:   # an unbalanced quote
            raise ServiceConfigError('%s: the command %r cannot be split into arguments: %s' % (where, value, e))
    elif isinstance(value, list) and all(isinstance(a, (str, int, float)) and not isinstance(a, bool) for a in value):
        args = [str(a) for a in value]
    if not args:
        raise ServiceConfigError('%s must be a command: a string or a list of arguments, got %r' % (where, value))
    if not args[0].strip():
        raise ServiceConfigError('%s: the program (its first argument) is empty, got %r' % (where, value))
    return args


def _names(where, value):
    if not isinstance(value, list) or not all(isinstance(n, str) and n for n in value):
        raise ServiceConfigError('%s must be a list of service names, got %r' % (where, value))
    return list(value)


def _optional(convert):
    return lambda where, value: None if value is None else convert(where, value)


def _action(where, value):
    if value not in ACTIONS:
        raise ServiceConfigError('%s must be one of %s, got %r' % (where, ', '.join(ACTIONS), value))
    return value


def _channel(where, value):
    if value not in ('local', 'ros'):
        raise ServiceConfigError('%s must be local or ros, got %r' % (where, value))
    return value


def _arguments(where, value):
    if not isinstance(value, list) or not all(isinstance(a, str) and a for a in value):
        raise ServiceConfigError('%s must be a list of arguments, got %r' % (where, value))
    return list(value)


def _at_least_one(where, value):
    if not _number(value) or value < 1:
        raise ServiceConfigError('%s must be a finite number >= 1, got %r' % (where, value))
    return float(value)


def _text(where, value):
    if not isinstance(value, str):
        raise ServiceConfigError('%s must be a string, got %r' % (where, value))
    return value


# key: (default, converter, documentation). REQUIRED marks a key without default.
REQUIRED = object()
SERVICE_KEYS = collections.OrderedDict([
    ('command', (REQUIRED, _command, 'the start command, a string (split as a shell would, quotes kept; no shell '
                                     'runs) or a list of arguments')),
    ('period', (None, _optional(_positive), "the service's own period (s); informational, shown by ~status")),
    ('spare', (0.0, _non_negative, 'spare time (s) left from its previous period; informational, shown by ~status')),
    ('heartbeat_timeout', (None, _optional(_positive), 'silence (s) after which the service is declared hung; '
                                                      'null: the service sends no heartbeat')),
    ('start_timeout', (5.0, _positive, 'a service not heard (or, without heartbeats, not alive) this long (s) '
                                       'after its start has failed to start')),
    ('start_grace', (0.5, _non_negative, 'without heartbeats: alive this long (s) after its start counts as running '
                                         '(at most start_timeout)')),
    ('cpu_limit', (None, _optional(_cpu), 'CPU limit, percent of one core (e.g. 80%); null: none')),
    ('cpu_window', (1.0, _positive, 'the CPU use is averaged over this long (s) before it is compared to the limit')),
    ('memory_limit', (None, _optional(_size), 'memory limit: bytes (200MB, 1GiB) or a percentage of the RAM (10%); '
                                              'null: none')),
    ('on_failure', ('restart', _action, 'restart, terminate, run (terminate, then run ``program``) or alert '
                                        '(report it and let it be)')),
    ('program', (None, _optional(_command), 'the program on_failure: run runs (with AFT_SERVICE and AFT_FAULT in '
                                            'its environment)')),
    ('program_timeout', (30.0, _positive, 'a failure program still running after this long (s) is killed, with its '
                                          'whole session, and that is reported; so is one that exits non-zero')),
    ('restart_limit', (3, _count, 'restarts allowed within restart_window; one more fault escalates')),
    ('restart_window', (60.0, _positive, 'the window (s) of restart_limit; the back-off\'s holds are not counted in '
                                         'it')),
    ('restart_with', ([], _names, 'services restarted after this one is restarted (its dependants, and '
                                  'theirs); those stopped stay stopped')),
    ('terminate_with', ([], _names, 'services terminated when this one fails (before it restarts), and left '
                                    'stopped (e.g. the trajectory generator when the trajectory sender fails)')),
    ('critical', (False, _flag, 'a critical service that cannot be recovered puts the system in the safe state')),
    ('safe_state_on_failure', (False, _flag, 'any failure of it puts the system in the safe state, even one a '
                                             'restart recovers (the paper\'s "stop manipulator movement")')),
    ('restore_state', (False, _flag, 'pass its state file (AFT_STATE_FILE) on restart, to be restored after a '
                                     'sanity check; false: it starts clean')),
    ('state_file', (None, _optional(_text), 'where the service saves its state (default: <state_dir>/<name>.json)')),
    ('autostart', (True, _flag, 'started when the manager starts')),
    ('heartbeat_channel', ('local', _channel, 'local: beats through the manager\'s local channel (a memory write per '
                                              'beat; aft_service_manager.channel); ros: on the ROS heartbeat topic')),
    ('warm_spare', (False, _flag, 'keep a standby instance started, set up and idle beside the active one; a '
                                  'restart promotes it (its first output within milliseconds), and a new spare '
                                  'is started behind it')),
    ('spare_args', ([], _arguments, 'arguments added to a spare\'s command ({n}: its instance number), so that it '
                                    'does not clash with the active instance, e.g. [__name:=c4g_{n}, '
                                    '~output:=/c4g/output]; required with warm_spare')),
    ('restart_delay', (0.0, _non_negative, 'back-off: the delay (s) before the first restart after a fault; '
                                           'multiplied by restart_delay_factor at each consecutive one')),
    ('restart_delay_factor', (2.0, _at_least_one, 'back-off: the growth of the delay per consecutive fault')),
    ('restart_delay_max', (30.0, _positive, 'back-off: the delay never exceeds this (s)')),
    ('stable_after', (10.0, _positive, 'back-off: running this long (s) ends a run of consecutive faults (the '
                                       'next restart is again after restart_delay)')),
])
MANAGER_KEYS = collections.OrderedDict([
    ('period', (0.01, _cycle, "the manager's cycle (s): how often it checks every service (at most an hour)")),
    ('kill_timeout', (2.0, _positive, 'a service asked to stop (SIGTERM) is killed (SIGKILL) after this long (s)')),
    ('state_dir', (None, _optional(_text), 'directory of the services\' state files and the manager\'s pid file: '
                                           'made 0700, refused unless the manager owns it and no one else may '
                                           'write it (default: $ROS_HOME/aft_service_state)')),
])


def _fill(where, item, keys):
    if not isinstance(item, dict):
        raise ServiceConfigError('%s must be a mapping, got %r' % (where, item))
    unknown = sorted(str(k) for k in set(item) - set(keys))
    if unknown:
        raise ServiceConfigError('%s: unknown key %s (known: %s)' % (where, ', '.join(unknown), ', '.join(keys)))
    out = {}
    for key, (default, convert, _) in keys.items():
        if key in item:
            out[key] = convert('%s.%s' % (where, key), item[key])
        elif default is REQUIRED:
            raise ServiceConfigError('%s: missing key %s' % (where, key))
        else:
            out[key] = list(default) if isinstance(default, list) else default
    return out


def parse_config(text, source='config'):
    """The configuration of a YAML text: {'manager': {...}, 'services': OrderedDict(name -> {...})}."""
    try:
        data = load_yaml(text)
    except yaml.YAMLError as e:
        raise ServiceConfigError('%s: not valid YAML: %s' % (source, e))
    if not isinstance(data, dict) or 'services' not in data:
        raise ServiceConfigError('%s: must be a mapping with a services key' % source)
    unknown = sorted(str(k) for k in set(data) - {'manager', 'services'})
    if unknown:
        raise ServiceConfigError('%s: unknown key %s (known: manager, services)' % (source, ', '.join(unknown)))
    manager = _fill('%s: manager' % source, {} if data.get('manager') is None else data['manager'], MANAGER_KEYS)
    raw = data['services']
    if not isinstance(raw, dict) or not raw:
        raise ServiceConfigError('%s: services must be a non-empty mapping of names to services' % source)
    services = collections.OrderedDict()
    for name, item in raw.items():
        if not isinstance(name, str) or not re.match(r'^[A-Za-z][A-Za-z0-9_]*$', name):
            raise ServiceConfigError('%s: service name %r must be a letter then letters, digits or _' % (source, name))
        services[name] = _fill('%s: services.%s' % (source, name), item, SERVICE_KEYS)
    for name, s in services.items():
        if s['on_failure'] == 'run' and not s['program']:
            raise ServiceConfigError('%s: services.%s: on_failure run needs a program' % (source, name))
        # review of session 34: both were accepted and failed at run time, without a word
        if s['heartbeat_timeout'] is None and s['start_grace'] > s['start_timeout']:
            raise ServiceConfigError('%s: services.%s: start_grace %g s exceeds start_timeout %g s: without heartbeats '
                                     'every start would time out before it counts as running (make start_timeout '
                                     '>= start_grace)' % (source, name, s['start_grace'], s['start_timeout']))
        if s['warm_spare'] and not s['spare_args']:
            raise ServiceConfigError('%s: services.%s: warm_spare needs spare_args (e.g. [__name:=%s_{n}]): the spare '
                                     'would start with the active instance\'s own node name and clash with it'
                                     % (source, name, name.lower()))
        for key in ('restart_with', 'terminate_with'):
            for other in s[key]:
                if other not in services:
                    raise ServiceConfigError('%s: services.%s.%s names %r, which is not a service (services: %s)'
                                             % (source, name, key, other, ', '.join(services)))
                if other == name:
                    raise ServiceConfigError('%s: services.%s.%s names the service itself' % (source, name, key))
        both = set(s['restart_with']) & set(s['terminate_with'])
        if both:
            raise ServiceConfigError('%s: services.%s: %s both restarted and terminated with it'
                                     % (source, name, ', '.join(sorted(both))))
    cycle = _cycle(services)
    if cycle:
        raise ServiceConfigError('%s: restart_with makes a cycle: %s' % (source, ' -> '.join(cycle)))
    conflict = _restarted_then_terminated(services)
    if conflict:
        raise ServiceConfigError('%s: %s' % (source, conflict))
    return {'manager': manager, 'services': services}


def _restarted_then_terminated(services):
    """Why a restart of some service would restart a service and terminate it too, or None. A restart of
    X restarts X and its restart_with, followed transitively, and terminates the terminate_with of each
    of them: a service in both was spawned and then killed in the same plan, and stayed STARTING with
    no process, unwatched (tg restart_with [c4g], c4g terminate_with [tg])."""
    for name in services:
        restarted, path = [name], {name: name}
        for current in restarted:   # breadth first; restart_with has no cycle (checked before)
            for other in services[current]['restart_with']:
                if other not in path:
                    path[other] = '%s -> %s' % (path[current], other)
                    restarted.append(other)
        for current in restarted:
            # terminate_with is followed transitively, as the supervisor does (_terminate_with)
            terminated, via = list(services[current]['terminate_with']), {}
            for other in terminated:
                via.setdefault(other, current)
            for other in terminated:
                for further in services[other]['terminate_with']:
                    if further not in via:
                        via[further] = '%s -> %s' % (via[other], other) if via[other] != current else other
                        terminated.append(further)
            for other in terminated:
                if other in path:
                    through = via[other]
                    return ('a restart of %s would start and stop %s at once: it restarts %s (%s) and %s '
                            '(restart_with: %s), whose terminate_with names %s%s'
                            % (name, other, other, 'itself' if other == name else 'restart_with: ' + path[other],
                               current, path[current], other,
                               '' if through == current else ' (through %s)' % through))
    return None


def _cycle(services):
    """A cycle in the restart_with graph, as a list of names (first repeated last), or None."""
    colour = {}

    def visit(name, path):
        colour[name] = 'grey'
        for other in services[name]['restart_with']:
            if colour.get(other) == 'grey':
                return path[path.index(other):] + [other]
            if other not in colour:
                found = visit(other, path + [other])
                if found:
                    return found
        colour[name] = 'black'
        return None
    for name in services:
        if name not in colour:
            found = visit(name, [name])
            if found:
                return found
    return None


def dependency_order(services):
    """The service names, each before the services restarted with it (restart_with, acyclic), else in
    config order."""
    parents = {name: {other for other, s in services.items() if name in s['restart_with']} for name in services}
    order = []
    while len(order) < len(services):
        ready = [n for n in services if n not in order and parents[n] <= set(order)]
        order += ready[:1] or [n for n in services if n not in order]   # (a cycle: parse_config refuses it)
    return order


def documentation():
    """The configuration keys, their defaults and meaning, as a Markdown table (for the README)."""
    lines = ['| key | default | meaning |', '|---|---|---|']
    for section, keys in (('manager', MANAGER_KEYS), ('services.NAME', SERVICE_KEYS)):
        for key, (default, _, doc) in keys.items():
            shown = 'required' if default is REQUIRED else ('null' if default is None else repr(default))
            lines.append('| `%s.%s` | %s | %s |' % (section, key, shown, doc))
    return '\n'.join(lines)


# -- detection -----------------------------------------------------------------------------------
Sample = collections.namedtuple('Sample', 'alive exit_code stopped cpu_percent rss')
Sample.__doc__ = """What the manager observed of a service's process: alive (bool), exit_code (None while
alive), stopped (the process is stopped: SIGSTOP, a hang), cpu_percent (averaged over cpu_window, None
before a whole window), rss (bytes)."""


def detect(config, sample, now, last_heard, reported_error, started_at, total_memory):
    """The fault a service shows now, as (kind, detail), or None.

    ``last_heard``: when its last heartbeat came (None: never); ``reported_error``: the detail of an
    error it reported in a heartbeat (None: none)."""
    found = detect_all(config, sample, now, last_heard, reported_error, started_at, total_memory)
    return found[0] if found else None


def detect_all(config, sample, now, last_heard, reported_error, started_at, total_memory):
    """Every fault a service shows now, [(kind, detail)], the most severe first (an alerted one must
    not hide another behind it: a service that reported an error, alerted, then hung was never seen
    hung, review of stop 39)."""
    if not sample.alive:
        return [('exit', 'the process exited with status %s' % sample.exit_code)]
    found = []
    if sample.stopped:
        found.append(('hang', 'the process is stopped (not scheduled)'))
    if reported_error is not None:
        found.append(('reported_error', 'the service reported an error: %s' % reported_error))
    timeout = config['heartbeat_timeout']
    if timeout is not None and last_heard is not None and now - last_heard > timeout:
        found.append(('heartbeat_timeout', 'no heartbeat for %.0f ms (timeout %.0f ms)'
                      % ((now - last_heard) * 1e3, timeout * 1e3)))
    if config['cpu_limit'] is not None and sample.cpu_percent is not None and sample.cpu_percent > config['cpu_limit']:
        found.append(('cpu_limit', 'CPU %.0f%% of a core over %.1f s (limit %.0f%%)' % (
            sample.cpu_percent, config['cpu_window'], config['cpu_limit'])))
    memory = memory_over(config, sample, total_memory)
    if memory:
        found.append(('memory_limit', memory))
    return found


def memory_over(config, sample, total_memory):
    """Why the service's memory is over its limit, or None."""
    if config['memory_limit'] is None or sample.rss is None:
        return None
    kind, value = config['memory_limit']
    limit = value if kind == 'bytes' else value / 100.0 * total_memory
    if sample.rss > limit:
        return 'memory %.1f MB (limit %.1f MB)' % (sample.rss / 1e6, limit / 1e6)
    return None


# -- one service ---------------------------------------------------------------------------------
class ServiceStateError(AftError):
    pass


class Service(object):
    """A service's state and counts. Every state change goes through _change(), along EDGES."""

    def __init__(self, name, config):
        self.name, self.config = name, config
        self.state = State.STOPPED
        self.reason = 'not started'
        self.since = None
        self.started_at = None
        self.last_heard = None
        self.reported_error = None
        self.restarts = collections.deque()   # times of the restarts within the window
        self.errors = collections.Counter()    # fault kind -> count
        self.starts = 0
        self.history = []                      # (now, from, to, reason)
        self.alerted = set()                   # fault kinds alerted and still present (alerted once)
        self.consecutive = 0                   # faults since it last ran for stable_after (the back-off)
        self.spawn_at = None                   # a restart held back by the back-off: when to spawn
        self.held_from = None                  # when that hold began
        self.held = 0.0                        # the holds' time so far (s): not counted in restart_window
        self.held_down = False                 # down in a manager's earlier run, kept down until started
        self.failed_before = False             # FAILED in that run: an operator's start renews its allowance
        self.stamped_here = False              # its last beat is stamped when the manager handled it (ROS)
        self.stall_end = None                  # the end of the manager's last stall since its spawn

    def _change(self, state, now, reason):
        if state == self.state:
            return
        if (self.state, state) not in EDGES:
            raise ServiceStateError('%s: %s -> %s is not allowed (%s)' % (self.name, self.state.name, state.name, reason))
        self.history.append((now, self.state, state, reason))
        self.state, self.since, self.reason = state, now, reason

    def hold(self, now, delay):
        """Hold the restart for the back-off's delay (spawned by Supervisor.due)."""
        self.spawn_at, self.held_from = now + delay, now

    def end_hold(self, now):
        """The held restart is spawned or called off."""
        if self.held_from is not None:
            self.held += max(0.0, now - self.held_from)
        self.spawn_at = self.held_from = None

    def clock(self, now):
        """The time restart_window is measured on: the manager's, less the back-off's holds. Measured on
        the manager's, a back-off that spaced the faults beyond restart_window / restart_limit made the
        limit unreachable: a critical service looped for ever, never FAILED, no safe state (review of
        session 34). The back-off changes when a restart comes, never whether the limit is reached."""
        return now - self.held - (now - self.held_from if self.held_from is not None else 0.0)

    def spawned(self, now):
        """Its process was (re)started."""
        self.end_hold(now)
        self.held_down = self.failed_before = False
        self._change(State.STARTING, now, 'spawned')
        self.started_at, self.last_heard, self.reported_error = now, None, None
        self.stamped_here, self.stall_end = False, None
        # A new instance's faults are its own: one alerted on the instance before (on_failure: alert)
        # was never alerted again when the new one showed it (review of session 48).
        self.alerted = set()
        self.starts += 1

    def heard(self, now, status, detail='', stamped_here=False):
        """A heartbeat with the service's own status ('ok' or 'error'). ``stamped_here``: ``now`` is
        when the manager handled it (the ROS channel), not the service's own time (a beat slot's)."""
        if self.state not in (State.STARTING, State.RUNNING):
            return
        self.last_heard = now
        self.stamped_here = stamped_here
        if status == 'error':
            self.reported_error = detail or 'error'
            return
        self.reported_error = None     # an ok heartbeat: no error reported any more
        if self.state == State.STARTING:
            self._change(State.RUNNING, now, 'heard from')

    def beats_stamped_here(self):
        """Whether its beats are stamped when the manager handles them (the ROS channel), so that a
        stall of the manager's own delays them: configured so, or its last beat came so."""
        return self.config['heartbeat_timeout'] is not None and (
            self.config['heartbeat_channel'] == 'ros' or self.stamped_here)

    def stalled(self, now):
        """The manager stalled until now: this service (its beats stamped here) is not judged silent
        before one heartbeat_timeout from now. Its beats of the stall wait in the manager's sockets,
        and the loop ran its checks before rospy handled them: it was restarted, the restart counted
        (review of session 34)."""
        self.stall_end = now
        if self.state == State.RUNNING and self.last_heard is not None:
            self.last_heard = max(self.last_heard, now)

    def start_deadline(self):
        """When, not yet heard from, it has failed to start: start_timeout after its spawn, or one
        heartbeat_timeout after a stall of the manager's own, whichever is later (see stalled())."""
        deadline = self.started_at + self.config['start_timeout']
        if self.stall_end is not None and self.config['heartbeat_timeout'] is not None:
            deadline = max(deadline, self.stall_end + self.config['heartbeat_timeout'])
        return deadline

    def restart_delay(self):
        """The back-off before the restart after the current run of consecutive faults."""
        c = self.config
        if not c['restart_delay'] or self.consecutive < 1:
            return 0.0
        try:
            delay = c['restart_delay'] * c['restart_delay_factor'] ** (self.consecutive - 1)
        except OverflowError:   # (a long run of faults: the cap long reached)
            delay = float('inf')
        return min(c['restart_delay_max'], delay)

    def restarts_in_window(self, now):
        clock = self.clock(now)   # the restarts are recorded on this clock
        while self.restarts and clock - self.restarts[0] > self.config['restart_window']:
            self.restarts.popleft()
        return len(self.restarts)


# A wake of the manager's loop this late (s) is a stall of its own (SIGSTOP, swapped out, a debugger,
# its lock held by a long command): see stall_threshold().
STALL_MIN = 0.1
STALL_PERIODS = 10


# The run of consecutive faults a record carries at most (the back-off reached its cap long before).
MAX_CONSECUTIVE = 10 ** 6


def stall_threshold(period):
    """How late (s) the manager's loop must wake to have stalled. Lateness, not the time since the
    previous check: the loop sleeps until the deadline it chose, up to a second (the diagnostics), so
    that gap is no measure. A wake is late by the scheduler's jitter, milliseconds on a busy machine
    (a few tens at worst); 0.1 s, or 10 periods if longer, is beyond it, and shorter than most
    heartbeat timeouts over the network (review of session 34)."""
    return max(STALL_MIN, STALL_PERIODS * period)


HELD_DOWN = 'down in the manager\'s previous run'
HELD_SAFE = 'held from the manager\'s previous run'
SPAWN_RETRY = 1.0   # s: the least wait before a spawn that failed is tried again (as a warm spare's)

Decision = collections.namedtuple('Decision', 'service kind detail actions escalate')
Decision.__doc__ = """What the supervisor decided about a fault: ``actions`` is a list of
(verb, service) the caller must carry out in order: ('kill', name), ('spawn', name), ('run', name);
``escalate`` is the reason to enter the safe state, or None."""


class Supervisor(object):
    """The policies over every service of a configuration (see the module's docstring)."""

    def __init__(self, config):
        self.config = config
        self.services = collections.OrderedDict((n, Service(n, c)) for n, c in config['services'].items())
        self.order = dependency_order(config['services'])
        self._taken = {}   # lost instances taken as started (take_as_started): name -> its starts then
        self.safe_state = None      # the reason the system is in the safe state, None while it is not
        self.also_unsafe = []       # the reasons to enter it that came while it was in it already
        self.safe_since = None
        self.escalations = 0
        self.stalls = 0             # stalls of the manager's own (woke())

    def __getitem__(self, name):
        return self.services[name]

    # -- what the caller observed ----------------------------------------------------------------
    def check(self, name, sample, now, total_memory):
        """Check one service; returns a Decision when it has a fault, else None."""
        s = self.services[name]
        if s.state == State.STARTING:
            if not sample.alive:
                return self.fault(name, 'exit', 'exited while starting, status %s' % sample.exit_code, now)
            # Memory is judged while starting too: a start-up allocating without bound was let grow until
            # its start timeout (review of session 34). CPU is not: a start-up's burst is no fault, and the
            # start timeout bounds it.
            memory = memory_over(s.config, sample, total_memory)
            if memory and 'memory_limit' not in s.alerted:
                return self.fault(name, 'memory_limit', memory, now)
            if s.config['heartbeat_timeout'] is None and now - s.started_at >= s.config['start_grace']:
                s._change(State.RUNNING, now, 'alive past its start grace of %.2f s' % s.config['start_grace'])
            elif now > s.start_deadline():
                return self.fault(name, 'start_timeout', 'not heard within %.1f s of its start'
                                  % s.config['start_timeout'], now)
            elif s.reported_error is not None and 'reported_error' not in s.alerted:
                # (alerted already: not again at every wake until its start timeout; review of session 36)
                return self.fault(name, 'reported_error', 'the service reported an error: %s' % s.reported_error, now)
            if s.state == State.STARTING:
                return None
        if s.state != State.RUNNING:
            return None
        if s.consecutive and now - s.since >= s.config['stable_after']:
            s.consecutive = 0   # a stable run: the back-off starts again from restart_delay
        found = detect_all(s.config, sample, now, s.last_heard, s.reported_error, s.started_at, total_memory)
        cleared = s.alerted - {kind for kind, _ in found}
        if cleared:
            s.alerted -= cleared
            if not s.alerted:
                s.reason = 'running; the fault alerted (%s) has cleared' % ', '.join(sorted(cleared))
        for kind, detail in found:
            if kind not in s.alerted:   # alerted already: alerted again only once the condition has cleared
                return self.fault(name, kind, detail, now)
        return None

    def woke(self, now, meant):
        """The manager's loop woke at now, having meant to wake at ``meant`` (None: its first wake).
        Woken more than stall_threshold() late, the manager stalled: every service whose beats it
        stamps when it handles them (the ROS channel) is given one heartbeat_timeout from now before
        it is judged silent (Service.stalled). A service on the local channel is not: its slot carries
        its own time. A real hang that coincides with the stall is detected one timeout later.
        Returns how late it woke (s), or None."""
        if meant is None or now - meant <= stall_threshold(self.config['manager']['period']):
            return None
        self.stalls += 1
        for s in self.services.values():
            if s.beats_stamped_here():
                s.stalled(now)
        return now - meant

    def take_as_started(self, lost, now):
        """The instances an earlier manager left running that ended while no manager watched (lost:
        {name: detail}) are taken as started (their starts counted: a policy that leaves one stopped is
        kept in the record), all of them before any fault is decided, so that one stopped or restarted
        with another (terminate_with, restart_with) is seen running, as one manager would have seen it.
        Returns their names in dependency order, for ended_unwatched one by one."""
        names = [n for n in self.order if n in lost]
        self._taken = {}
        for name in names:
            s = self.services[name]
            s.end_hold(now)   # (a back-off hold resumed from the record: this fault decides anew)
            s._change(State.STARTING, now, 'left running by an earlier manager, found ended')
            s.starts += 1
            self._taken[name] = s.starts
        return names

    def ended_unwatched(self, name, detail, now):
        """name's instance ended while no manager watched it: an exit whose status nobody saw, counted
        and decided as one (before session 39 it was started again as if nothing had happened: a fresh
        allowance for a service dying with its manager each time). None if an earlier one's fault
        already stopped or restarted it (its kill, under one manager, is not counted). The caller
        acts on each Decision before the next is decided (reviews of session 39)."""
        s = self.services[name]
        # Not the instance taken as started any more: stopped, or restarted (and spawned again) with
        # an earlier one (review of session 39: a fresh instance was faulted a second time).
        if s.state != State.STARTING or self._taken.get(name) != s.starts:
            return None
        return self.fault(name, 'exit', detail, now)

    def replaced_unwatched(self, name, detail, now):
        """An instance of name ended while no manager watched it, and a newer one runs (adopted): its
        predecessor restarted it after the fault and died before the record counted either. Counted as
        that exit and that restart, nothing done (the running instance is the restart's); the newer
        one's own faults are judged as they come. It was forgotten (review of session 41)."""
        s = self.services[name]
        s.errors['exit'] += 1
        s.consecutive += 1
        s.restarts.append(s.clock(now))
        s.reason = 'exit: %s; restarted then (the instance running was adopted)' % detail
        return s

    def starts_after_lost(self, name, lost, now):
        """How service name, not found ended, starts once the lost ones' faults are decided and acted
        on (called in dependency order): (verb, why), verb 'spawn'; 'skip' (it must not run without a
        lost one, whose fault stopped it under one manager: terminate_with, followed transitively;
        left stopped, recorded so, the safe state escalated if it is critical); or 'held' (restarted
        with a lost one, or with one held so, being restarted: restart_with; spawned after it by
        due()). It was autostarted first, running for a moment without what it must not run without
        (review of session 39)."""
        s = self.services[name]
        blockers = [l for l in lost if name in self._closure(l, 'terminate_with')]
        if blockers:
            s.reason = ('terminated with %s, found ended at the manager\'s start: start it to run it again'
                        % ', '.join(blockers))
            s.held_down = True
            if s.config['critical']:
                self._escalate('%s (critical) %s' % (name, s.reason), now)
            return 'skip', s.reason
        if self.waits_for(name):
            s._change(State.RESTARTING, now, 'restarted with %s, found ended' % ', '.join(self.waits_for(name)))
            return ('spawn' if self.may_spawn(name, now) else 'held'), s.reason
        return 'spawn', ''

    def _closure(self, name, key):
        """The services reached from name through config[key] (terminate_with, restart_with), transitively."""
        seen, todo = set(), [name]
        while todo:
            for other in self.services[todo.pop()].config[key]:
                if other not in seen and other != name:
                    seen.add(other)
                    todo.append(other)
        return seen

    def fault(self, name, kind, detail, now):
        """A fault of service name: count it, decide and return what to do."""
        s = self.services[name]
        s.errors[kind] += 1
        s.consecutive += 1
        was = s.state
        s._change(State.ERROR, now, '%s: %s' % (kind, detail))
        action = s.config['on_failure']
        escalate = None
        actions = []
        if action == 'restart':
            if s.restarts_in_window(now) >= s.config['restart_limit']:
                s._change(State.FAILED, now, 'restart limit exhausted: %d restarts within %.0f s'
                          % (s.config['restart_limit'], s.config['restart_window']))
                actions += self._terminate_with(name, now) + [('kill', name)]
                escalate = '%s: restart limit exhausted after %s' % (name, kind)
            else:
                s.restarts.append(s.clock(now))
                delay = s.restart_delay()
                if kind == 'spawn':   # never at once: a spawn failing again at once used the whole allowance
                    delay = max(delay, SPAWN_RETRY)
                actions += self._restart(name, now, 'failure action restart after %s' % kind, delay=delay)
        elif action == 'alert':
            if kind in ('exit', 'start_timeout', 'spawn'):
                s._change(State.STOPPED, now, 'alerted; it is not running')
                actions += self._terminate_with(name, now) + [('kill', name)]
            else:
                s.alerted.add(kind)
                if was == State.STARTING:   # not yet heard from: still judged by its start timeout
                    s._change(State.STARTING, now, 'alerted (%s: %s); left starting' % (kind, detail))
                else:
                    s._change(State.RUNNING, now, 'alerted (%s: %s); left running' % (kind, detail))
            actions.append(('alert', name))
        else:   # terminate, or run: terminate then run the program
            s._change(State.STOPPED, now, 'failure action %s after %s' % (action, kind))
            actions += self._terminate_with(name, now) + [('kill', name)]
            if action == 'run':
                actions.append(('run', name))
        if escalate is None and s.config['critical'] and s.state in (State.STOPPED, State.FAILED):
            escalate = '%s (critical) cannot be recovered: %s' % (name, kind)
        if escalate is None and s.config['safe_state_on_failure']:
            escalate = '%s failed (%s): movement stopped while it recovers' % (name, kind)
        if escalate is None:
            stopped = [other for verb, other in actions if verb == 'kill' and other != name and
                       self.services[other].config['critical'] and self.services[other].state == State.STOPPED]
            if stopped:
                escalate = '%s (critical) terminated with %s after its %s' % (', '.join(stopped), name, kind)
        if escalate:
            self._escalate(escalate, now)
        return Decision(name, kind, detail, actions, escalate)

    def _terminate_with(self, name, now, seen=None):
        """Actions terminating the services that must not run without name (left stopped), and those
        that must not run without them, followed transitively (B terminated with A left C, which must
        not run without B, running; review of stop 39)."""
        seen = {name} if seen is None else seen
        actions = []
        for other in self.services[name].config['terminate_with']:
            if other in seen:
                continue
            seen.add(other)
            o = self.services[other]
            if o.state in (State.STARTING, State.RUNNING, State.ERROR, State.RESTARTING):
                o.end_hold(now)
                o._change(State.STOPPED, now, 'terminated with %s' % name)
                actions.append(('kill', other))
                actions += self._terminate_with(other, now, seen)
        return actions

    def _critical_stopped(self, name, actions, now, why):
        """Escalate when actions left a critical service stopped (an operator's stop or restart of a
        service it must not run without, or of itself): a critical service down is never left without
        the safe state (review of stop 39). Returns the reason, or None."""
        stopped = [other for verb, other in actions if verb == 'kill' and self.services[other].config['critical']
                   and self.services[other].state in (State.STOPPED, State.FAILED)]
        if not stopped:
            return None
        reason = '%s (critical) %s' % (', '.join(stopped), why)
        self._escalate(reason, now)
        return reason

    def _restart(self, name, now, why, seen=None, delay=0.0):
        """Actions restarting name: terminate its terminate_with first, restart it, then its dependants
        (restart_with, followed transitively) that are running or starting; stopped ones stay stopped.
        With a back-off delay, the spawn is held (``spawn_at``) and carried out by :meth:`due`."""
        seen = set() if seen is None else seen
        seen.add(name)
        s = self.services[name]
        actions = self._terminate_with(name, now)
        s._change(State.RESTARTING, now, why + (' (back-off %.2f s)' % delay if delay else ''))
        actions.append(('kill', name))
        if delay:
            s.hold(now, delay)
        else:
            actions.append(('spawn', name))
        for other in s.config['restart_with']:
            if other not in seen and self.services[other].state in (State.STARTING, State.RUNNING):
                # held as long as the service they depend on (then spawned after it, by due())
                actions += self._restart(other, now, 'restarted with %s' % name, seen, delay)
        return actions

    def due(self, now):
        """The spawns the back-off held that are due now: [('spawn', name)], a service before those
        restarted with it (in config order, a dependant listed first was spawned before the service it
        depends on; review of session 34)."""
        actions = []
        for name in self.order:
            s = self.services[name]
            if s.spawn_at is not None and now >= s.spawn_at:
                s.end_hold(now)
                if s.state == State.RESTARTING:
                    actions.append(('spawn', name))
        return actions

    def degraded(self):
        """{name: reason} of the services down after a fault (failed, stopped by a failure policy or
        with another service, held down from the manager's previous run): not an operator's stop. The
        summary said "normal" while one was (review of session 36)."""
        return {n: s.reason for n, s in self.services.items()
                if s.state == State.FAILED or (s.state == State.STOPPED and
                                               s.reason not in ('not started', 'stopped by an operator'))}

    def waits_for(self, name):
        """The services name is restarted with (they list it in restart_with: it runs against them)
        that are being restarted and not spawned yet."""
        return [other for other, o in self.services.items()
                if name in o.config['restart_with'] and o.state == State.RESTARTING]

    def may_spawn(self, name, now):
        """Whether name, being restarted, may be spawned now: not before a service it is restarted with
        whose own spawn failed and is retried, or is held longer (its back-off), or a dependant ran
        against a service not there and was not restarted after it (review of session 36). Held
        then until the latest of their spawns is due; due() spawns it after them."""
        s = self.services[name]
        waiting = self.waits_for(name) if s.state == State.RESTARTING else []
        if not waiting:
            return True
        at = max(self.services[o].spawn_at if self.services[o].spawn_at is not None else now + SPAWN_RETRY
                 for o in waiting)
        if s.spawn_at is None or s.spawn_at < at:
            s.end_hold(now)
            s.hold(now, max(0.0, at - now))
            s.reason = 'restarted after %s, which is being restarted' % ', '.join(waiting)
        return False

    def next_due(self):
        """When the earliest held spawn is due (None: none held)."""
        times = [s.spawn_at for s in self.services.values() if s.spawn_at is not None]
        return min(times) if times else None

    def _escalate(self, reason, now):
        """Enter the safe state for reason; in it already, the reason is kept beside the first
        (``also_unsafe``, said in the status and the diagnostics): an operator clearing the state
        for the first reason was not told of the second (review of session 36)."""
        if self.safe_state is None:
            self.safe_state, self.safe_since = reason, now
            self.escalations += 1
        elif reason != self.safe_state and reason not in self.also_unsafe:
            self.also_unsafe.append(reason)

    # -- what an operator asks ---------------------------------------------------------------------
    def start(self, name, now):
        """An operator's start. Returns (accepted, actions, message); refused changes nothing."""
        s = self.services[name]
        if s.state in (State.STOPPED, State.FAILED):
            if s.state == State.FAILED or s.failed_before:
                # the operator takes it back: a fresh restart allowance (also for one FAILED in the
                # manager's previous run, held down since: its restarts came with the record)
                s.restarts.clear()
                s.failed_before = False
            return True, [('spawn', name)], 'starting %s' % name
        if s.state in (State.STARTING, State.RUNNING):
            return False, [], '%s is already %s' % (name, s.state.name.lower())
        return False, [], '%s is %s: wait until it settles' % (name, s.state.name.lower())

    def stop(self, name, now):
        s = self.services[name]
        if s.state == State.STOPPED:
            return False, [], '%s is already stopped' % name
        if s.state == State.RESTARTING and s.spawn_at is None:
            return False, [], '%s is restarting: wait until it settles' % name
        was = s.state
        s.end_hold(now)    # (a restart the back-off holds is called off)
        s._change(State.STOPPED, now, 'stopped by an operator')
        actions = [] if was == State.FAILED else self._terminate_with(name, now) + [('kill', name)]
        escalated = self._critical_stopped(name, actions, now, 'stopped by an operator (with %s)' % name)
        return True, actions, 'stopping %s%s' % (name, '; safe state: %s' % escalated if escalated else '')

    def restart(self, name, now):
        s = self.services[name]
        if s.state == State.FAILED or s.failed_before:   # (FAILED in the previous run: as now, start it)
            return False, [], '%s has failed: start it instead' % name
        if s.state == State.ERROR or (s.state == State.RESTARTING and s.spawn_at is None):
            return False, [], '%s is %s: wait until it settles' % (name, s.state.name.lower())
        s.end_hold(now)   # an operator's restart does not wait for the back-off
        actions = self._restart(name, now, 'restarted by an operator')
        escalated = self._critical_stopped(name, actions, now, 'terminated by an operator\'s restart of %s' % name)
        return True, actions, 'restarting %s%s' % (name, '; safe state: %s' % escalated if escalated else '')

    def record(self):
        """What a manager started again (killed, crashed, restarted) must not forget: the safe state,
        and the services an operator, a failure action or an exhausted restart limit left down. Its
        successor lifted the safe state and restarted them all at once (review of stop 39). And each
        service's counts: its errors by kind, the run of consecutive faults the back-off follows, and
        the restarts its restart_limit counts, each at the latest time on the system's monotonic clock
        (shared by every process until a reboot) it may have happened. A manager crashing with its
        service, or killed by it, gave a service that fails at every start a fresh allowance and no
        back-off each time: never FAILED, never the safe state (review of session 36). And the end of
        a back-off hold under way, which the next manager resumes (session 39). Only what changes at a
        fault (and at the held spawn) is recorded, so the record is written again only then."""
        down = {n: dict({'state': s.state.name, 'reason': s.reason}, **({'failed': True} if s.failed_before else {}))
                for n, s in self.services.items()
                if s.state == State.FAILED or (s.state == State.STOPPED and (s.starts or s.held_down))}
        # On the system's clock, a restart r of the service's clock was at r + its holds at the latest (a
        # hold under way counted from its start: the record stays the same while it lasts).
        counts = {n: dict({'errors': dict(s.errors), 'consecutive': min(s.consecutive, MAX_CONSECUTIVE),
                           'restarts': [r + s.held + (0.0 if s.held_from is None else s.spawn_at - s.held_from)
                                        for r in s.restarts]},
                          # A back-off hold under way: the next manager holds the restart until then too
                          # (it started the service at once; Limits of session 38).
                          **({'hold_until': s.spawn_at} if s.spawn_at is not None and s.state == State.RESTARTING
                             else {}))
                  for n, s in self.services.items() if s.errors or s.restarts or s.consecutive}
        return {'safe_state': self.safe_state, 'down': down, 'counts': counts}

    @staticmethod
    def _check_counts(counts):
        """Raise ServiceConfigError unless counts is what record() writes."""
        def number(v):
            return isinstance(v, (int, float)) and not isinstance(v, bool) and -1e18 < v < 1e18   # (NaN fails too)
        if not isinstance(counts, dict):
            raise ServiceConfigError('the manager\'s record is malformed: its counts %r are not a mapping' % (counts,))
        for name, entry in counts.items():
            ok = isinstance(entry, dict) and isinstance(entry.get('errors', {}), dict) and all(
                isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool) and v >= 0
                for k, v in entry.get('errors', {}).items()) and isinstance(entry.get('restarts', []), list) and all(
                number(r) for r in entry.get('restarts', [])) and number(entry.get('hold_until', 0.0)) and \
                isinstance(entry.get('consecutive', 0), int) and \
                not isinstance(entry.get('consecutive', 0), bool) and 0 <= entry.get('consecutive', 0) <= MAX_CONSECUTIVE
            if not ok:
                raise ServiceConfigError('the manager\'s record is malformed: counts.%s is %r, not {errors: {kind: '
                                         'count}, consecutive: count, restarts: [times]}' % (name, entry))

    def restore(self, record, now):
        """Take a record of an earlier run (:meth:`record`) before anything starts. Returns the names of
        the services held down (not autostarted); a malformed record raises ServiceConfigError, and
        changes nothing (one with a number for its safe state crashed the manager at start, review of
        session 34)."""
        if not isinstance(record, dict) or not isinstance(record.get('down', {}), dict):
            raise ServiceConfigError('the manager\'s record is not a mapping: %r' % (record,))
        if not isinstance(record.get('safe_state'), (str, type(None))):
            raise ServiceConfigError('the manager\'s record is malformed: its safe_state %r is no text'
                                     % (record['safe_state'],))
        for name, entry in record.get('down', {}).items():
            if not isinstance(entry, dict) or not isinstance(entry.get('reason', ''), str):
                raise ServiceConfigError('the manager\'s record is malformed: down.%s is %r, not {reason: text}'
                                         % (name, entry))
        self._check_counts(record.get('counts', {}))
        for name, entry in record.get('counts', {}).items():
            s = self.services.get(name)
            if s is None:
                continue
            s.errors.update(entry.get('errors', {}))
            s.consecutive = entry.get('consecutive', 0)
            # This service's clock is the system's until its first hold; a time ahead of now (the
            # clock started again at a reboot) counts as now: within the window, never forgotten early.
            s.restarts.extend(sorted(min(r, now) for r in entry.get('restarts', [])))
            # The back-off hold the earlier manager had under way: resumed until its end, never longer
            # than the longest back-off (a time far ahead: the clock started again at a reboot).
            delay = min(entry.get('hold_until', now) - now, s.config['restart_delay_max'])
            if delay > 0 and name not in record.get('down', {}) and s.state == State.STOPPED:
                s._change(State.RESTARTING, now, 'the back-off hold of the previous manager resumed (%.2f s left)'
                          % delay)
                s.hold(now, delay)
        held = []
        for name, entry in sorted(record.get('down', {}).items()):
            s = self.services.get(name)
            if s is None or s.state != State.STOPPED:   # no longer configured: nothing to hold
                continue
            reason = entry.get('reason', '')
            s.reason = reason if reason.startswith(HELD_DOWN) else '%s (%s): start it to run it again' % (HELD_DOWN,
                                                                                                          reason)
            s.held_down = True   # recorded again, whatever number of restarts of the manager
            s.failed_before = entry.get('state') == State.FAILED.name or bool(entry.get('failed'))
            held.append(name)
        reason = record.get('safe_state')
        if reason:
            self._escalate(reason if reason.startswith(HELD_SAFE) else '%s: %s' % (HELD_SAFE, reason), now)
        return held

    def clear_safe_state(self, now):
        """An operator clears the safe state. Refused while a critical service is not running."""
        if self.safe_state is None:
            return False, 'the system is not in the safe state'
        down = [n for n, s in self.services.items() if s.config['critical'] and s.state != State.RUNNING]
        if down:
            return False, 'critical services not running: %s (start them first)' % ', '.join(down)
        reasons = '; '.join([self.safe_state] + self.also_unsafe)
        self.safe_state, self.safe_since, self.also_unsafe = None, None, []
        return True, 'safe state cleared (it was: %s)' % reasons

    # -- what the caller reports back ----------------------------------------------------------------
    def spawn_failed(self, name, now, error):
        """Its spawn failed: a fault like an exit, counted against the restart limit and retried after
        the back-off (at least SPAWN_RETRY), escalated once the limit is exhausted. Returns the Decision.
        One transient failure (EAGAIN) left a service FAILED for good, silently unless critical (review
        of session 34)."""
        s = self.services[name]
        s.end_hold(now)
        if s.state in (State.STOPPED, State.FAILED, State.RESTARTING):
            s._change(State.STARTING, now, 'spawn asked')
        return self.fault(name, 'spawn', 'cannot be spawned: %s' % error, now)
