"""Adaptation scripts: what changes in a running FTM, and in which order (paper section 6.1).

A script is a small declarative YAML file: which nodes to suspend, which to launch, which ports
to rebind, which nodes Recovery promotes from now on, which nodes to retire (kill). The engine
turns it into steps in one of two orders:

- ``paper``: the paper's order. Suspend, kill, launch, rebind, resume: the pause includes the
  start-up of the new processes (about a second per roslaunch).
- ``prepared``: launch the new nodes first, their inputs unbound, and wait until they are set up
  and their publishers connected; then suspend, rebind, resume; then kill the old nodes. The pause
  covers only quiescence, rebinding and resuming.

Example (PBR -> PBR+TR, the paper's worked example)::

    name: compose-pbr-tr
    kind: compose
    description: Time Redundancy stands in for Proceed on each replica.
    args: {site: [master, slave]}
    each: site                      # entries naming $(arg site) are repeated for each site
    suspend: [/$(arg site)/protocol]
    launch:
      - file: aft_ftm/mechanism.launch
        args: {ns: /$(arg site)/tr, mechanism: tr, bind_input: false, ...}
    bind:
      - {node: /$(arg site)/proceed, port: inp, unbind: true}
      - {node: /$(arg site)/tr/protocol, port: requests, topic: /$(arg site)/bfr2prd}
    retire: [/$(arg site)/proceed]

This module parses and checks scripts (:func:`check_fit`: against the master's view of the live
graph too) and plans steps and their undoing; it never touches ROS (see
:mod:`aft_ftm.ros.adaptation_engine`; the run itself is :mod:`aft_ftm.transaction`).
"""
import collections
import re

import yaml

from .config import load_yaml
from .errors import AftError

KINDS = ('update', 'switch', 'compose')
MODES = ('prepared', 'paper')
TOP_KEYS = ('name', 'kind', 'description', 'args', 'each', 'suspend', 'launch', 'bind', 'promote', 'retire')
LAUNCH_KEYS = ('file', 'args')
BIND_KEYS = ('node', 'port', 'topic', 'direction', 'unbind')
PROMOTE_KEYS = ('recovery', 'nodes')
DIRECTIONS = ('subscribe', 'publish')
_ARG = re.compile(r'\$\(arg ([A-Za-z_][A-Za-z0-9_]*)\)')
_NAME = re.compile(r'^(/[A-Za-z][A-Za-z0-9_]*)+$')


class ScriptError(AftError):
    """An adaptation script is malformed or does not fit the live system; nothing was changed."""


class StepError(AftError):
    """A step of an adaptation failed; the engine rolls back what was done."""


Launch = collections.namedtuple('Launch', 'file args')             # args: ordered (name, value) pairs
Bind = collections.namedtuple('Bind', 'node port topic direction activate')
Promote = collections.namedtuple('Promote', 'recovery nodes')


class Script(object):
    """A parsed, expanded and checked script: every name absolute, every $(arg) substituted."""

    def __init__(self, name, kind, description, suspend, launch, bind, promote, retire, args, suspend_entry=None):
        self.name = name
        self.kind = kind
        self.description = description
        self.suspend = suspend       # [node]
        self.launch = launch         # [Launch]
        self.bind = bind             # [Bind]
        self.promote = promote       # [Promote]
        self.retire = retire         # [node]
        self.args = args             # the argument values used
        # node -> the entry of "suspend" it comes from: the copies of one entry (one per value of
        # "each": different sites) may be suspended together; different entries in the script's order.
        self.suspend_entry = dict(suspend_entry or {})

    def nodes_touched(self, launched=()):
        """Every node the adaptation acts on: suspended, rebound, promoted by, retired, launched."""
        names = set(self.suspend) | set(self.retire) | {b.node for b in self.bind}
        names |= {p.recovery for p in self.promote} | set(launched)
        return sorted(names)


def _fail(where, what):
    raise ScriptError('%s: %s' % (where, what))


def _check_keys(where, mapping, allowed):
    if not isinstance(mapping, dict):
        _fail(where, 'must be a mapping, got %r' % (mapping,))
    unknown = sorted(set(mapping) - set(allowed))
    if unknown:
        _fail(where, 'unknown key%s %s (allowed: %s)' % ('s' if len(unknown) > 1 else '', ', '.join(unknown),
                                                          ', '.join(allowed)))


def parse_overrides(items):
    """Command-line ``name:=value`` pairs -> dict. A value with commas is a list."""
    result = {}
    for item in items:
        if ':=' not in item:
            raise ScriptError('argument %r must be written name:=value' % item)
        key, value = item.split(':=', 1)
        if not key:
            raise ScriptError('argument %r has no name' % item)
        result[key] = value.split(',') if ',' in value else value
    return result


def load(text, overrides=None, source='script'):
    """Parse a script's YAML text, substitute its arguments and check its form.

    ``overrides`` maps argument names to values (command line). Raises ScriptError naming the
    problem (and where it is) when anything is wrong.
    """
    try:
        data = load_yaml(text)
    except yaml.YAMLError as e:
        raise ScriptError('%s: not valid YAML: %s' % (source, e))
    _check_keys(source, data, TOP_KEYS)
    name = data.get('name')
    if not isinstance(name, str) or not name:
        _fail(source, 'missing "name" (a non-empty string)')
    kind = data.get('kind')
    if kind not in KINDS:
        _fail(source, '"kind" must be one of %s, got %r' % (', '.join(KINDS), kind))
    if not isinstance(data.get('args') or {}, dict):   # (checked first: dict() of a list raised ValueError)
        _fail(source, '"args" must be a mapping of names to default values')
    args = dict(data.get('args') or {})
    for key, value in (overrides or {}).items():
        if key not in args:
            _fail(source, 'unknown argument %r (the script declares: %s)' % (key, ', '.join(sorted(args)) or 'none'))
        args[key] = value
    args = _resolve_defaults(source, args)
    each = data.get('each')
    values = [None]
    if each is not None:
        if not isinstance(each, str) or each not in args:   # (a list raised TypeError: unhashable)
            _fail(source, '"each" names %r, which is not an argument' % (each,))
        values = args[each] if isinstance(args[each], list) else [args[each]]
        if not values or not all(isinstance(v, str) and v for v in values):
            _fail(source, 'argument %r of "each" must be a non-empty list of names, got %r' % (each, args[each]))

    def expand(section, entries):
        """Substitute arguments; an entry naming the "each" argument is repeated per value."""
        if entries is None:
            return []
        if not isinstance(entries, list):
            _fail(source, '"%s" must be a list' % section)
        out = []
        for i, entry in enumerate(entries):
            where = '%s: %s[%d]' % (source, section, i)
            repeat = each is not None and _mentions(entry, '$(arg %s)' % each)
            for value in (values if repeat else [None]):
                bound = dict(args)
                if repeat:
                    bound[each] = value
                out.append((where, _substitute(entry, bound, where)))
        return out

    expanded = expand('suspend', data.get('suspend'))
    suspend = [_node(w, n) for w, n in expanded]
    # The copies of one entry (one per value of "each": different sites) may be suspended together;
    # different entries are suspended in the script's order.
    suspend_entry = {n: w for (w, _), n in zip(expanded, suspend)}
    retire = [_node(w, n) for w, n in expand('retire', data.get('retire'))]
    launch = [_launch(w, e) for w, e in expand('launch', data.get('launch'))]
    bind = [_bind(w, e) for w, e in expand('bind', data.get('bind'))]
    promote = [_promote(w, e) for w, e in expand('promote', data.get('promote'))]
    if not (suspend or launch or bind or promote or retire):
        _fail(source, 'the script changes nothing (no suspend, launch, bind, promote or retire)')
    if (bind or retire) and not suspend:
        _fail(source, 'rebinding or retiring nodes needs a suspension first: name the entry nodes in "suspend"')
    for where, values_ in (('suspend', suspend), ('retire', retire)):
        duplicates = sorted({n for n in values_ if values_.count(n) > 1})
        if duplicates:
            _fail(source, '"%s" names %s more than once' % (where, ', '.join(duplicates)))
    return Script(name, kind, str(data.get('description') or ''), suspend, launch, bind, promote, retire, args,
                  suspend_entry)


def _resolve_defaults(source, args):
    """Arguments whose value names other arguments (``primary_after_old: $(arg old)``: a default that
    follows another argument unless given itself), substituted until none is left. A cycle, or a
    name that is not an argument, is an error naming it."""
    resolved = dict(args)
    for _ in range(len(resolved) + 1):
        pending = {k: v for k, v in resolved.items() if isinstance(v, str) and _ARG.search(v)}
        if not pending:
            return resolved
        for key, value in pending.items():
            names = _ARG.findall(value)
            if all(not (isinstance(resolved.get(n), str) and _ARG.search(resolved[n])) for n in names):
                resolved[key] = _substitute(value, resolved, '%s: args: %s' % (source, key))
    _fail(source, 'arguments %s name each other in a cycle' % ', '.join(sorted(
        k for k, v in resolved.items() if isinstance(v, str) and _ARG.search(v))))


def _mentions(value, text):
    """True if text occurs in any string of value (nested lists and mappings)."""
    if isinstance(value, str):
        return text in value
    if isinstance(value, list):
        return any(_mentions(v, text) for v in value)
    if isinstance(value, dict):
        return any(_mentions(v, text) for v in value.values())
    return False


def _substitute(value, args, where):
    if isinstance(value, str):
        def one(match):
            key = match.group(1)
            if key not in args:
                _fail(where, 'unknown argument $(arg %s)' % key)
            bound = args[key]
            if isinstance(bound, list):
                _fail(where, '$(arg %s) is a list: only the "each" argument is repeated' % key)
            return str(bound)
        return _ARG.sub(one, value)
    if isinstance(value, list):
        return [_substitute(v, args, where) for v in value]
    if isinstance(value, dict):
        return {k: _substitute(v, args, where) for k, v in value.items()}
    return value


def _node(where, name):
    if not isinstance(name, str) or not _NAME.match(name):
        _fail(where, 'a node must be named by an absolute ROS name like /master/protocol, got %r' % (name,))
    return name


def _launch(where, entry):
    _check_keys(where, entry, LAUNCH_KEYS)
    path = entry.get('file')
    if not isinstance(path, str) or not path.endswith('.launch'):
        _fail(where, '"file" must name a .launch file (package/file.launch or a path), got %r' % (path,))
    args = entry.get('args') or {}
    if not isinstance(args, dict):
        _fail(where, '"args" must be a mapping')
    pairs = []
    for key in sorted(args):
        value = args[key]
        if isinstance(value, bool):
            value = 'true' if value else 'false'
        elif isinstance(value, list):
            value = '[%s]' % ', '.join(str(v) for v in value)
        pairs.append((str(key), str(value)))
    return Launch(path, tuple(pairs))


def _bind(where, entry):
    _check_keys(where, entry, BIND_KEYS)
    node = _node(where, entry.get('node'))
    port = entry.get('port')
    if not isinstance(port, str) or not port:
        _fail(where, 'missing "port" (the node\'s port name)')
    direction = entry.get('direction', 'subscribe')
    if direction not in DIRECTIONS:
        _fail(where, '"direction" must be subscribe or publish, got %r' % (direction,))
    unbind = entry.get('unbind', False)
    if not isinstance(unbind, bool):
        _fail(where, '"unbind" must be true or false')
    topic = entry.get('topic', '')
    if unbind and topic:
        _fail(where, 'give either "topic" (bind) or "unbind: true", not both')
    if not unbind:
        topic = _node(where + ' topic', topic) if topic else _fail(where, 'missing "topic" to bind %s to' % port)
    return Bind(node, port, topic, direction, not unbind)


def _promote(where, entry):
    _check_keys(where, entry, PROMOTE_KEYS)
    nodes = entry.get('nodes')
    if not isinstance(nodes, list) or not nodes:
        _fail(where, '"nodes" must be a non-empty list of node names')
    return Promote(_node(where, entry.get('recovery')), tuple(_node(where, n) for n in nodes))


# -- fitting the live graph ----------------------------------------------------------------------

# The services an aft_ftm node calls once it runs, by (executable, ~mechanism): each is the node's
# relative name, usually remapped by the launch file. None: whatever the mechanism.
SERVICES_CALLED = {
    ('proceed', None): ('server',),
    ('fault_injector', None): ('server',),
    ('before', 'tr'): ('get_state', 'set_state'),
    ('after', 'pbr'): ('get_state', 'set_state'),
    ('cycle_after', None): ('set_state',),
    ('sec_gate', None): ('certificate',),
}
def follows_witness(node_type, mechanism, site, follow_witness=''):
    """Whether an aft_ftm node of a replica (``site`` set) follows its ~witness: Recovery and the PBR or
    LFR After call it; the Protocol, Before, Proceed, and a crash detector told to (``follow_witness``),
    hear its configurations. A node outside a replica follows none."""
    if not site:
        return False
    if node_type == 'after':
        return mechanism in ('pbr', 'lfr')
    if node_type == 'crash_detector':
        return follow_witness is True or str(follow_witness).lower() == 'true'
    return node_type in ('protocol', 'before', 'proceed', 'recovery')


def services_called(node, node_type, mechanism, remaps, witness=''):
    """The resolved names of the services a launched aft_ftm node will call: ``node`` its absolute
    name, ``remaps`` {from: to} of its launch file, ``witness`` its ~witness parameter. LFR's After
    calls the state services only with a witness (a join is a state transfer). The After and Recovery
    call their witness; the Protocol, Before, Proceed and crash detector only hear its configurations,
    which the same witness node publishes: its service must be offered for them too, or the node
    follows a witness that does not run (review of session 40: a compose without witness:= on
    another service followed the bank's)."""
    called = list(SERVICES_CALLED.get((node_type, None), ()) or SERVICES_CALLED.get((node_type, mechanism), ()))
    if node_type == 'after' and mechanism == 'lfr' and witness:
        called += ['get_state', 'set_state']
    namespace = node.rsplit('/', 1)[0] or '/'
    names = []
    for name in called:
        target = remaps.get(name, name)
        names.append(target if target.startswith('/') else '%s/%s' % (namespace.rstrip('/'), target))
    if witness:   # called, or its configurations heard: offered by the same node
        names.append(witness)
    return names


def check_fit(script, nodes, services, launched, calls=None, witnesses=None, site_witnesses=None):
    """Check script against a view of the live graph; raises ScriptError naming the first problem.

    ``nodes``: the running nodes; ``services``: the services offered; ``launched``: for each of
    the script's Launch entries, the nodes its launch file starts; ``calls``: for each entry, {node:
    the services it will call (services_called())}: each must be offered now, or the new nodes would
    wait for it and the adaptation roll back long after (the script's defaults name the bank demo's
    services: another service needs its own names, server:= or state_manager:=). What only the nodes
    can answer (a dry run of each rebind, where a retired node runs) the engine asks them afterwards.
    ``witnesses``: {node: (its ~witness, '' for none; its ~site)} for the new nodes that follow a
    witness in a replica (:func:`follows_witness`);
    ``site_witnesses``: {site: the witness its Recovery follows}: a new node of a site must follow the
    same one (review of session 40: a script's default witness is the bank demo's; on a second service
    the new nodes followed the bank's witness, a running one, and never heard their own site's role).
    """
    started = {}   # node -> the launch file that starts it
    for entry in script.launch:
        clash = sorted(set(launched[entry]) & set(nodes))
        if clash:
            raise ScriptError('launch file %s would start %s, already running (a second node of the same '
                              'name stops the first): choose other names' % (entry.file, ', '.join(clash)))
        # Two launches of one run starting the same name: the second stops the first's node, whose
        # required launch then ends and its guard fail-stops the site (review of session 35).
        twice = sorted(n for n in launched[entry] if n in started)
        if twice:
            raise ScriptError('launch file %s would start %s, which %s starts too (a second node of the same name '
                              'stops the first)' % (entry.file, ', '.join(twice), started[twice[0]]))
        started.update((n, entry.file) for n in launched[entry])
    new = {name for names in launched.values() for name in names}
    for node, (witness, site) in sorted((witnesses or {}).items()):
        ours = (site_witnesses or {}).get(site)
        if ours is not None and witness != ours:
            raise ScriptError('%s would follow the witness %s, and site %s\'s Recovery follows %s: give the '
                              'replica\'s own (witness:=%s)' % (node, witness or 'none', site, ours or 'none',
                                                                 ours or 'none'))

    def need(node, service, why):
        if node in new:
            return
        if node not in nodes:
            raise ScriptError('unknown node %s (%s): it is not running' % (node, why))
        if node + '/' + service not in services:
            raise ScriptError('node %s offers no %s service (%s): is it an FTM node?' % (node, service, why))
    for node in script.suspend:
        need(node, 'suspend', 'to suspend')
    for node in script.retire:
        if node not in nodes:
            raise ScriptError('unknown node %s (to retire): it is not running' % node)
    for bind in script.bind:
        need(bind.node, 'rebind', 'to rebind its port %s' % bind.port)
    for promote in script.promote:
        need(promote.recovery, 'set_promote', 'to change the nodes it promotes')
        for node in promote.nodes:
            if node not in new and node not in nodes:
                raise ScriptError('unknown node %s (for %s to promote)' % (node, promote.recovery))
    for entry, called in sorted((calls or {}).items(), key=lambda item: item[0].file):
        for node, names in sorted(called.items()):
            missing = [n for n in names if n not in services]
            witness = (witnesses or {}).get(node, (None, None))[0]
            if witness in missing:
                raise ScriptError('launch file %s would start %s, which follows the witness %s: no node offers it '
                                  '(give the running replica\'s witness, witness:=/NS/witness/request)'
                                  % (entry.file, node, witness))
            if missing:   # (its witness, offered, is not named among what it calls: a follower only hears it)
                raise ScriptError('launch file %s would start %s, which calls %s: no node offers %s (name '
                                  'your service in the script\'s arguments, e.g. server:= or state_manager:=)'
                                  % (entry.file, node, ', '.join(n for n in names if n != witness),
                                     ', '.join(missing)))


def unconnected_binds(script, publishers, subscribers, only=None):
    """The binds of script (of ``only``, if given) that would leave their port with no peer; [message
    naming each].

    ``publishers``, ``subscribers``: {topic: node names} as the master has them once the script's
    launches are up (before its rebinds). A port bound to a subscription needs a publisher of the
    topic, a publishing port a subscriber: a node registered on it now, other than the port's own
    node and the nodes the script retires, or another bind of the script on that topic the other
    way. A topic nobody publishes (a typo) was accepted, the run said it succeeded, and requests were
    lost until the Protocol's 30 s backstop fail-stopped the site (review of session 35)."""
    retired = set(script.retire)
    bound = collections.defaultdict(set)   # (topic, direction) -> the nodes the script binds there
    for b in script.bind:
        if b.activate:
            bound[(b.topic, b.direction)].add(b.node)
    problems = []
    for b in script.bind if only is None else only:
        if not b.activate:
            continue
        subscribing = b.direction == 'subscribe'
        table = publishers if subscribing else subscribers
        other = 'publish' if subscribing else 'subscribe'
        peers = (set(table.get(b.topic, ())) | bound[(b.topic, other)]) - retired - {b.node}
        if not peers:
            problems.append('%s.%s would be bound to %s, which no node %s (a misspelt topic?)' % (
                b.node, b.port, b.topic, 'publishes' if subscribing else 'subscribes to'))
    return problems


# -- planning -----------------------------------------------------------------------------------

Step = collections.namedtuple('Step', 'action target detail')
# action: launch | wait_launched | suspend | kill | rebind | promote | resume


def plan(script, mode):
    """The steps of script in mode 'paper' or 'prepared' (see the module documentation).

    A rebind of a node retired earlier in the same plan is left out (the node is gone), so the
    paper's order does not unbind the Proceed it has already killed.
    """
    if mode not in MODES:
        raise ScriptError('mode must be one of %s, got %r' % (', '.join(MODES), mode))
    launch = [Step('launch', l.file, l) for l in script.launch]
    wait = [Step('wait_launched', '%d launch file(s)' % len(script.launch), None)] if script.launch else []
    suspend = [Step('suspend', n, script.suspend_entry.get(n, n)) for n in script.suspend]
    resume = [Step('resume', n, None) for n in reversed(script.suspend)]
    kill = [Step('kill', n, None) for n in script.retire]
    promote = [Step('promote', p.recovery, p) for p in script.promote]
    if mode == 'paper':
        gone = set(script.retire)
        rebind = [Step('rebind', b.node, b) for b in script.bind if b.node not in gone]
        resume = [s for s in resume if s.target not in gone]
        return suspend + kill + launch + wait + rebind + promote + resume
    rebind = [Step('rebind', b.node, b) for b in script.bind]
    return launch + wait + suspend + rebind + promote + resume + kill


PARALLEL = ('launch', 'rebind', 'promote', 'resume', 'kill')


def groups(steps):
    """Consecutive steps of one action that can run together, as lists, in order. Suspensions
    follow the script's order, except the copies of one entry (one per site); two steps on one
    node are not run together (its services answer one call at a time)."""
    out = []
    for step in steps:
        together = step.action in PARALLEL or (step.action == 'suspend' and step.detail == out[-1][0].detail
                                                if out else False)
        if out and step.action == out[-1][0].action and together and \
                (step.action == 'launch' or step.target not in {s.target for s in out[-1]}):
            out[-1].append(step)
        else:
            out.append([step])
    return out


def cleanup_steps(steps):
    """The steps after the last resume (the prepared order's kills). The new configuration serves
    by then: a failure there is reported, never rolled back (undoing would rebind a live graph)."""
    resumes = [i for i, s in enumerate(steps) if s.action == 'resume']
    return steps[resumes[-1] + 1:] if resumes else []


def pause_bounds(steps):
    """Indexes (first, last) of the steps between the first suspend and the last resume."""
    actions = [s.action for s in steps]
    if 'suspend' not in actions:
        return None
    first = actions.index('suspend')
    last = len(actions) - 1 - actions[::-1].index('resume')
    return first, last


def undo_plan(done):
    """What to do, in order, to take back the steps done (a list of (Step, undo info)).

    Bindings and Recovery's list are restored and killed nodes started again (from their recorded
    command line) in reverse order; then every suspended node is resumed, so that clients wait no
    longer than that; the nodes launched, now bound to nothing, are stopped last.
    """
    undo, stops, suspended = [], [], []
    for step, info in reversed(done):
        if step.action == 'suspend':
            suspended.append(step.target)
        elif step.action == 'launch':
            stops.append(Step('stop_launch', step.target, info))
        elif step.action == 'kill':
            undo.append(Step('respawn', step.target, info))
        elif step.action == 'rebind':
            undo.append(Step('restore_binding', step.target, (step.detail, info)))
        elif step.action == 'promote':
            undo.append(Step('restore_promote', step.target, info))
        # A resume before the failure needs no undo: that node runs as before, nothing of its own changed.
    return undo + [Step('resume', node, None) for node in suspended] + stops
