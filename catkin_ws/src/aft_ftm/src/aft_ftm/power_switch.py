"""Fencing across hosts by a power switch: the request/response of the switch and the decision.

Pure (no rospy, no sockets, no processes): :mod:`aft_ftm.power_switch_exec` talks to a switch,
Recovery (``aft_ftm.ros.recovery_node``) asks it in its FAIL_SILENCE step, and
:class:`aft_ftm.hosts_exec.PowerSwitch` is the switch of emulated hosts.

A switch is named by a spec (Recovery's ``~power_switch``):

- ``''`` or ``none``: no switch (sites on one host: fail-silence kills by pid);
- ``unix:PATH``: a switch agent on a Unix-domain socket (the emulated hosts' agent, on the run's
  root-only state directory: a management network that partitions of the data network do not cut);
- ``command:ARGV ...``: a fence agent run as a command (e.g. ``command:fence_ipmilan --ip=10.0.0.2
  --username=admin --password-script=/etc/aft/ipmi_pw --action=off``); ``{host}`` in an argument is
  replaced by the peer's host name. Exit status 0 means the host is off, anything else that it may
  still run.

The agent's protocol is one JSON line each way: the request ``{"op": "off", "host": H}`` (or
``"status"``), the answer ``{"ok": true, "host": H, "state": "off", "detail": ...}`` sent only once
the host is off (link down, every process killed), or ``{"ok": false, "host": H, "error": ...}``.

Invariants:

- a host is *confirmed off* only by an answer that says ``ok``, names that host and the state
  ``off`` (or a fence command's exit status 0); anything else (no answer within the timeout, an
  unreadable answer, another host, an error) is *not confirmed*: the host may still answer clients;
- :class:`Fencing` allows a promotion after a failure only once the peer's host is confirmed off (or
  no switch is configured); a refusal or a silence never allows it, whatever the number of attempts.
"""
import enum
import json
import shlex

from .errors import AftError

OPS = ('off', 'status')
MAX_LINE = 64 * 1024


class SwitchError(AftError):
    """A power switch spec, request or answer is invalid; the message names what was wrong."""


class SwitchSpec(object):
    """A parsed ``~power_switch``: kind ``unix`` (``path``) or ``command`` (``argv``)."""

    def __init__(self, kind, path=None, argv=None):
        self.kind = kind
        self.path = path
        self.argv = list(argv or [])

    def command_for(self, host):
        """The fence command's argv for host (``{host}`` replaced)."""
        return [arg.replace('{host}', host) for arg in self.argv]

    def describe(self):
        return 'unix:%s' % self.path if self.kind == 'unix' else 'command:%s' % ' '.join(self.argv)

    def __eq__(self, other):
        return isinstance(other, SwitchSpec) and (self.kind, self.path, self.argv) == (other.kind, other.path,
                                                                                      other.argv)

    def __repr__(self):
        return 'SwitchSpec(%r)' % self.describe()


def parse_spec(text):
    """``~power_switch`` -> SwitchSpec, or None for no switch. Raises SwitchError naming the problem."""
    if not isinstance(text, str):
        raise SwitchError('power switch %r: give a string (unix:PATH, command:ARGV..., or none)' % (text,))
    text = text.strip()
    if text in ('', 'none'):
        return None
    kind, sep, rest = text.partition(':')
    if not sep or kind not in ('unix', 'command'):
        raise SwitchError('power switch %r: unknown kind %r (give unix:PATH, command:ARGV..., or none)'
                          % (text, kind))
    rest = rest.strip()
    if kind == 'unix':
        if not rest.startswith('/'):
            raise SwitchError('power switch %r: the socket path must be absolute' % text)
        return SwitchSpec('unix', path=rest)
    try:
        argv = shlex.split(rest)
    except ValueError as e:
        raise SwitchError('power switch %r: cannot split the command: %s' % (text, e))
    if not argv:
        raise SwitchError('power switch %r: no command given' % text)
    return SwitchSpec('command', argv=argv)


def encode_request(op, host):
    if op not in OPS:
        raise SwitchError('power switch request: unknown op %r (one of %s)' % (op, ', '.join(OPS)))
    if not isinstance(host, str) or not host:
        raise SwitchError('power switch request: no host named')
    return (json.dumps({'op': op, 'host': host}) + '\n').encode()


def parse_request(line):
    """A request line (bytes or str) -> (op, host). Raises SwitchError naming the problem."""
    data = _json_line(line, 'request')
    op, host = data.get('op'), data.get('host')
    if op not in OPS:
        raise SwitchError('request: unknown op %r (one of %s)' % (op, ', '.join(OPS)))
    if not isinstance(host, str) or not host:
        raise SwitchError('request: no host named (%r)' % (host,))
    return op, host


def encode_answer(host, ok, state=None, detail='', error=''):
    data = {'ok': bool(ok), 'host': host}
    if ok:
        data.update(state=state, detail=detail)
    else:
        data['error'] = error or 'refused'
    return (json.dumps(data, sort_keys=True) + '\n').encode()


class Outcome(object):
    """What one call of the switch established: ``confirmed`` (the host is off) and why."""

    def __init__(self, confirmed, detail):
        self.confirmed = bool(confirmed)
        self.detail = detail

    def __repr__(self):
        return 'Outcome(%r, %r)' % (self.confirmed, self.detail)


def answer_outcome(line, host):
    """The Outcome of an agent's answer line for a request to power ``host`` off."""
    try:
        data = _json_line(line, 'answer')
    except SwitchError as e:
        return Outcome(False, 'the switch answered unreadably (%s): %s may still run' % (e, host))
    if data.get('host') != host:
        return Outcome(False, 'the switch answered for host %r, not %s: %s may still run'
                       % (data.get('host'), host, host))
    if data.get('ok') is not True:
        return Outcome(False, 'the switch refused to power %s off: %s' % (host, data.get('error', 'no reason given')))
    if data.get('state') != 'off':
        return Outcome(False, 'the switch says %s is %r, not off' % (host, data.get('state')))
    return Outcome(True, 'power switch: %s off%s' % (host, ' (%s)' % data['detail'] if data.get('detail') else ''))


def command_outcome(argv, returncode, output, host):
    """The Outcome of a fence command: exit status 0 is off, anything else may still run."""
    tail = ' '.join((output or '').strip().split())[-200:]
    if returncode == 0:
        return Outcome(True, 'fence command %s: %s off' % (argv[0], host))
    return Outcome(False, 'fence command %s exited %s%s: %s may still run'
                   % (' '.join(argv), returncode, ' (%s)' % tail if tail else '', host))


def _json_line(line, what):
    if isinstance(line, bytes):
        if len(line) > MAX_LINE:
            raise SwitchError('%s: longer than %d bytes' % (what, MAX_LINE))
        line = line.decode('utf-8', errors='replace')
    line = (line or '').strip()
    if not line:
        raise SwitchError('%s: empty' % what)
    try:
        data = json.loads(line)
    except ValueError as e:
        raise SwitchError('%s: not JSON (%s): %r' % (what, e, line[:80]))
    if not isinstance(data, dict):
        raise SwitchError('%s: not a JSON object: %r' % (what, line[:80]))
    return data


class FenceState(enum.Enum):
    IDLE = 'no failure to fence'
    NO_SWITCH = 'no power switch configured: the peer is fenced by pid on this host only'
    FENCING = 'the switch is being asked to power the peer off'
    REFUSED = 'the switch did not confirm: no promotion, asked again later'
    OFF = "the switch confirmed the peer's host is off: promotion allowed"


# Each edge and why it may be taken. Only FENCING -> OFF (a confirmation) opens the promotion.
EDGES = {
    (FenceState.IDLE, FenceState.NO_SWITCH): 'a failure, and no switch to call',
    (FenceState.IDLE, FenceState.FENCING): 'a failure: ask the switch',
    (FenceState.FENCING, FenceState.OFF): 'the switch confirmed the host is off',
    (FenceState.FENCING, FenceState.REFUSED): 'the switch refused, failed or did not answer in time',
    (FenceState.REFUSED, FenceState.FENCING): 'the retry period passed: ask again',
    (FenceState.OFF, FenceState.IDLE): 're-armed: the peer re-joined',
    (FenceState.NO_SWITCH, FenceState.IDLE): 're-armed: the peer re-joined',
    (FenceState.REFUSED, FenceState.IDLE): 're-armed: the peer came back and re-joined',
    (FenceState.FENCING, FenceState.IDLE): 're-armed while the switch was asked: its outcome is ignored',
}


class Fencing(object):
    """The fencing of one peer by a power switch, as a state machine (one :meth:`_change`).

    The caller (Recovery) calls :meth:`begin` at a failure, the switch when it says so
    (``state is FENCING``), then :meth:`settle` with the Outcome; :meth:`may_promote` tells whether
    a promotion may go on, :meth:`retry_due` when the switch is to be asked again.
    """

    def __init__(self, switch, host, retry_period=1.0):
        if switch is not None and not host:
            raise SwitchError('a power switch (%s) needs the peer\'s host name (~peer_host)' % switch.describe())
        if not retry_period > 0:
            raise SwitchError('fence retry period %r: give a positive number of seconds' % (retry_period,))
        self.switch = switch
        self.host = host
        self.retry_period = float(retry_period)
        self.state = FenceState.IDLE
        self.attempts = 0
        self.last = None          # the last Outcome
        self.next_try = None      # monotonic time of the next attempt (REFUSED)

    def _change(self, new):
        if (self.state, new) not in EDGES:
            raise SwitchError('fencing of %s: no edge %s -> %s' % (self.host, self.state.name, new.name))
        self.state = new

    def begin(self, now):
        """A failure of the peer: FENCING (call the switch now) or NO_SWITCH. Idempotent while fencing."""
        if self.state in (FenceState.FENCING, FenceState.OFF, FenceState.NO_SWITCH):
            return self.state
        if self.state is FenceState.REFUSED:
            return self.retry(now)
        self.attempts = 0
        self._change(FenceState.FENCING if self.switch is not None else FenceState.NO_SWITCH)
        return self.state

    def settle(self, outcome, now):
        """The switch's Outcome of the attempt under way; ignored (nothing changes) if none is under
        way any more (re-armed meanwhile)."""
        if self.state is not FenceState.FENCING:
            return self.state
        self.attempts += 1
        self.last = outcome
        if outcome.confirmed:
            self._change(FenceState.OFF)
            self.next_try = None
        else:
            self._change(FenceState.REFUSED)
            self.next_try = now + self.retry_period
        return self.state

    def retry_due(self, now):
        return self.state is FenceState.REFUSED and now >= self.next_try

    def retry(self, now):
        """REFUSED -> FENCING once the retry period passed; otherwise nothing changes."""
        if self.retry_due(now):
            self._change(FenceState.FENCING)
        return self.state

    def may_promote(self):
        """False while a fencing is unconfirmed (FENCING, REFUSED): a promotion goes on only once the
        peer's host is confirmed off, with no switch, or with no failure to fence (the first primary)."""
        return self.state not in (FenceState.FENCING, FenceState.REFUSED)

    def rearm(self):
        """The peer re-joined: its next failure is fenced afresh."""
        if self.state is not FenceState.IDLE and (self.state, FenceState.IDLE) in EDGES:
            self._change(FenceState.IDLE)
        return self.state
