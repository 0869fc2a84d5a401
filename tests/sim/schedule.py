"""Seeded schedules of faults, and the runner that checks the properties after every step.

``run(seed)`` draws everything from the seed: the timings, the clients' calls, the faults and
every delay, so that ``run(seed)`` replays the same schedule, step for step. A schedule is short:
a few calls and faults in the first ~1.2 simulated seconds, then it runs until every call is
answered and nothing is left to happen, or 2.5 s, or a bound of steps.

The faults (each at a random time, on a random site or node):

- crash: a site loses every process and its server's state; it may come back (a new incarnation
  that registers and joins) after any time, as may a site that stopped for any other reason;
- stall: a whole site (a paused machine) or some of its nodes do nothing for a short or long
  while, then go on with what they had queued (a stalled crash detector sends no heartbeats: its
  peer may suspect a live site);
- partition: the link between two hosts (the sites, a site and the clients' host, a site and the
  witness's: half the schedules give it a host of its own) is down for a while; TCP delivers what
  crossed it afterwards, in order;
- hang: a site's server stops answering, for ever or for a while (Proceed fail-stops past its
  timeout, or waits for the late answer where its site serves alone);
- capture_fails: the next get_state calls fail (1: tried again and fine; more: fail-stop);
- apply_fails: the backup's next set_state fails (it must re-join);
- stray: a checkpoint from an After nobody follows (/intruder/after), plain or a state transfer;
- witness_stall, proxy_stall: the witness or a Proxy does nothing for a while;
- and, in some schedules, hiccups (a process stalls right after a message, at an arbitrary point of
  the protocol) and late messages (10-150 ms).

The network faults beyond TCP (loss of any message, duplicates, reordering within a connection)
are enabled separately, with a :class:`sim.world.NetFaults` (``parse_net``: AFT_SIM_NET).
"""
import collections
import types

from .deployment import KINDS, Deployment
from .properties import Checker
from .replica import Params
from .world import CLIENTS, NetFaults, Process, Violation, World

WITNESS = 'w'           # the witness's host when it has one of its own
HORIZON = 2.5           # s of simulated time at most
MAX_STEPS = 6000        # events at most
SETTLE = 0.3            # s after the last call and fault before a schedule may end

__all__ = ['run', 'random_scenario', 'Scenario', 'Result', 'NetFaults', 'Params']


class Scenario(object):
    """What happens in a schedule besides the delays: parameters, calls, faults, sites coming back."""

    def __init__(self, params=None, calls=(), faults=(), returns=0.0, restarts=0, proxies=1, initial_primary='',
                 b_delay=0.0, chained=0, hiccup=0.0, slow=0.0, witness_host=CLIENTS):
        self.params = params or Params()
        self.calls = list(calls)            # (time, proxy index)
        self.chained = chained              # calls made each as soon as the one before is answered
        self.hiccup = hiccup                # chance that a process stalls after a message
        self.slow = slow                    # chance that a message is late
        self.witness_host = witness_host    # CLIENTS, or WITNESS: a host of its own
        self.faults = list(faults)          # (time, name, args...)
        self.returns = returns              # chance that a stopped site comes back
        self.restarts = restarts            # at most this many comebacks
        self.proxies = proxies
        self.initial_primary = initial_primary
        self.b_delay = b_delay

    def describe(self):
        return ['%.3f %s%s' % (f[0], f[1], ' %s' % (f[2:],) if len(f) > 2 else '') for f in sorted(self.faults)]


def random_scenario(rng):
    """A schedule drawn from rng: timings, 2-12 calls (some made one after the other), 0-6 faults, each
    degradation maybe followed by a crash (the failure that finds it), sites that may come back."""
    params = Params(
        ack_timeout=rng.choice((0.1, 0.2, 0.4)),
        hb_timeout=rng.choice((0.03, 0.05, 0.1)),
        apply_period=rng.choice((0.0, 0.01, 0.05)),
        cache_bytes=rng.choice((64 << 20,) * 5 + (150, 300)),
        fence=rng.choice((1.0, 1.0, 0.5, 0.0)))
    proxies = rng.choice((1, 1, 2))
    witness_host = rng.choice((CLIENTS, WITNESS))
    calls = sorted((rng.uniform(0.02, 1.2), rng.randrange(proxies)) for _ in range(rng.randint(1, 6)))
    faults = []
    for _ in range(rng.choice((0, 1, 1, 2, 2, 3, 4))):
        fault = random_fault(rng, rng.uniform(0.03, 1.2), witness_host)
        faults.append(fault)
        if fault[1] != 'crash' and rng.random() < 0.4:
            faults.append((fault[0] + rng.uniform(0.01, 0.5), 'crash', rng.choice('ab')))
    return Scenario(params, calls, faults, returns=rng.choice((0.0, 0.5, 0.9)), restarts=rng.choice((1, 2, 3)),
                    proxies=proxies, initial_primary=rng.choice(('', 'a')), b_delay=rng.uniform(0, 0.05),
                    chained=rng.randint(0, 8), hiccup=rng.choice((0.0, 0.0, 0.01, 0.03)),
                    slow=rng.choice((0.0, 0.0, 0.02, 0.1)), witness_host=witness_host)


def duration(rng):
    return rng.uniform(0.005, 0.06) if rng.random() < 0.5 else rng.uniform(0.1, 0.6)


NODE_STALLS = ('after',) * 3 + ('detector', 'recovery') * 2 + ('protocol', 'proceed')


def random_fault(rng, t, witness_host=CLIENTS):
    site = rng.choice('ab')
    kind = rng.choice(('crash', 'crash', 'stall_site', 'stall_site', 'stall_node', 'stall_node', 'stall_node',
                       'partition', 'partition', 'hang', 'capture_fails', 'apply_fails', 'stray', 'witness_stall',
                       'proxy_stall'))
    if kind == 'crash':
        return (t, kind, site)
    if kind == 'hang':   # for ever, or for a while (longer than Proceed's timeout, or shorter)
        return (t, kind, site, None if rng.random() < 0.5 else duration(rng))
    if kind == 'stall_site':
        return (t, 'stall', site, KINDS, duration(rng))
    if kind == 'stall_node':
        return (t, 'stall', site, (rng.choice(NODE_STALLS),), duration(rng))
    if kind == 'partition':
        return (t, kind, site, rng.choice(tuple(sorted({CLIENTS, witness_host})) + ('b' if site == 'a' else 'a',)),
                duration(rng))
    if kind == 'capture_fails':
        return (t, kind, site, rng.choice((1, 1, 2, 1000)))
    if kind == 'apply_fails':
        return (t, kind, site, 1)
    if kind == 'stray':
        return (t, kind, site, rng.random() < 0.5, rng.randrange(1, 5000000), rng.randrange(0, 6))
    if kind == 'witness_stall':
        return (t, kind, duration(rng))
    return (t, kind, 0, duration(rng))


class Result(object):
    def __init__(self, seed, net, scenario, world, env, checker, violation):
        self.seed = seed
        self.net = net
        self.scenario = scenario
        self.world = world
        self.env = env
        self.checker = checker
        self.violation = violation
        self.trace = world.trace_lines()
        self.steps = world.steps
        self.calls = sum(len(p.opened) for p in env.proxies)
        self.unanswered = sum(len(p.unanswered()) for p in env.proxies)
        self.refused = sum(1 for p in env.proxies for e in p.opened if e.reply is not None and not e.reply.ok)
        self.batched = env.batched
        self.parted, self.parted_joined = env.parted, env.parted_joined
        self.caught_up = env.caught_up
        self.alarms = checker.alarm_counts()
        self.transitions = checker.transition_counts
        w = env.witness.witness
        self.history = list(w.history)
        self.failovers = sum(1 for h in w.history if 'promoted' in h[3])

    def outcomes(self):
        """Every call's outcome: (proxy, id, value or the error)."""
        return [(p.name, e.id, None if e.reply is None else e.reply.value if e.reply.ok else e.reply.error)
                for p in self.env.proxies for e in p.opened]

    def report(self):
        lines = ['seed %d (replay: AFT_SIM_SEED=%d%s pytest tests/unit/test_replication_sim.py)'
                 % (self.seed, self.seed, '' if self.net is None else ' AFT_SIM_NET=%s' % net_name(self.net))]
        if self.violation is not None:
            lines.append('VIOLATION %s' % self.violation)
        lines.append('faults: %s' % ('; '.join(self.scenario.describe()) or 'none'))
        lines.append('witness: %s' % self.history)
        lines.append('last %d steps of %d:' % (len(self.trace), self.steps))
        return '\n'.join(lines + ['  ' + line for line in self.trace])


def net_name(net):
    return ','.join(n for n, on in (('loss', net.loss), ('dup', net.dup), ('reorder', net.reorder),
                                   ('local', net.local)) if on)


def parse_net(text):
    """NetFaults from AFT_SIM_NET's form: loss, dup, reorder, local, comma-separated ('' : none)."""
    names = [n for n in text.split(',') if n]
    unknown = set(names) - {'loss', 'dup', 'reorder', 'local'}
    if unknown:
        raise ValueError('AFT_SIM_NET: unknown fault classes %s (known: loss, dup, reorder, local)' % sorted(unknown))
    if not names:
        return None
    return NetFaults(loss=0.02 if 'loss' in names else 0.0, dup=0.05 if 'dup' in names else 0.0,
                     reorder='reorder' in names, local='local' in names)


class Intruder(Process):
    """Whoever publishes a stray checkpoint (a forger on the clients' host)."""


def apply_fault(env, fault):
    world = env.world
    name, args = fault[1], fault[2:]
    world.log('FAULT %s %s', name, args)
    if name == 'crash':
        env.sites[args[0]].stop('crash')
    elif name == 'restart':
        if not env.sites[args[0]].alive:
            env.sites[args[0]].start()
    elif name == 'stall':
        site, kinds, seconds = args
        if env.sites[site].alive:
            env.sites[site].stall(seconds, kinds)
    elif name == 'partition':
        env.partition(args[0], args[1], args[2])
    elif name in ('hang', 'capture_fails', 'apply_fails'):
        site = env.sites[args[0]]
        if site.alive:
            if name == 'hang':
                site.server.hung = True
                if len(args) > 1 and args[1] is not None:
                    world.after(args[1], site.server.thaw)
            elif name == 'capture_fails':
                site.server.capture_failures += args[1]
            else:
                site.server.apply_failures += args[1]
    elif name == 'stray':
        site, full, seq, epoch = args
        after = env.node(site, 'after')
        if after is not None:
            forger = Intruder(world, None, '/intruder/after', CLIENTS)
            world.send(forger, after, 'checkpoints', after.on_checkpoint, _stray(seq, epoch, full))
    elif name == 'witness_stall':
        env.witness.stall(args[0])
    elif name == 'proxy_stall':
        env.proxies[args[0] % len(env.proxies)].stall(args[1])
    else:
        raise ValueError('unknown fault %r' % (name,))


def _stray(seq, epoch, full):
    reply = types.SimpleNamespace(id=1, origin='/proxy0', client='/client', attempt=0, oldest_pending=0, ok=True,
                                  value=999, error='', epoch=epoch, refusal=False)
    return types.SimpleNamespace(seq=seq, first_seq=1, sender='/intruder/after', replaces='', epoch=epoch, full=full,
                                 reply=None if full else reply, cache=[reply] if full else None,
                                 state=(('/proxy0', 1, 0),) * 3)


def run(seed, net=None, scenario=None, horizon=HORIZON, max_steps=MAX_STEPS, **params):
    """One schedule: the scenario drawn from the seed (or the one given), with ``params`` (Params
    attributes, e.g. fix_stale_exclusion=False) set after it is drawn. Returns a Result; a property
    that failed is in Result.violation (with the trace of the last steps)."""
    world = World(seed, net)
    if scenario is None:
        scenario = random_scenario(world.rng)
    for name, value in params.items():
        if not hasattr(scenario.params, name):
            raise AttributeError('no parameter %r' % name)
        setattr(scenario.params, name, value)
    checker = Checker()
    env = Deployment(world, scenario.params, checker, proxies=scenario.proxies,
                     initial_primary=scenario.initial_primary, witness_host=scenario.witness_host)
    restarts = [scenario.restarts]

    def came_down(site):
        if restarts[0] > 0 and world.rng.random() < scenario.returns:
            restarts[0] -= 1
            world.after(world.rng.uniform(0.02, 0.8), apply_fault, env, (None, 'restart', site.name))
    env.on_site_stopped = came_down
    world.after_step = checker.after_step
    world.hiccup, world.slow = scenario.hiccup, scenario.slow
    env.start(scenario.b_delay)
    for t, index in scenario.calls:
        proxy = env.proxies[index]
        world.at(t, proxy.receive, proxy.call, ())
    chained = [scenario.chained]

    def again(proxy, entry):
        if chained[0] > 0:
            chained[0] -= 1
            world.after(world.rng.uniform(0.0, 0.03), proxy.receive, proxy.call, ())
    for proxy in env.proxies:
        proxy.answered = again
    for fault in scenario.faults:
        world.at(fault[0], apply_fault, env, fault)
    quiet_after = max([t for t, _ in scenario.calls] + [f[0] for f in scenario.faults] + [0.0]) + SETTLE

    def done():
        return world.now > quiet_after and not chained[0] and not any(len(p.table) for p in env.proxies)
    violation = None
    try:
        world.run(horizon, max_steps, done)
    except Violation as v:
        violation = v
    return Result(seed, net, scenario, world, env, checker, violation)


def summary(results):
    """Counts over many schedules: for the report at the end of a run."""
    total = collections.Counter()
    for r in results:
        total['schedules'] += 1
        total['steps'] += r.steps
        total['calls'] += r.calls
        total['unanswered'] += r.unanswered
        total['refused'] += r.refused
        total['batched'] += r.batched
        total['parted'] += r.parted
        total['caught_up'] += r.caught_up
        total['parted_joined'] += r.parted_joined
        total['stuck schedules'] += bool(r.unanswered)
        total['failovers'] += r.failovers
        total['violations'] += r.violation is not None
        for kind, n in r.alarms.items():
            total['alarm ' + kind] += n
    return total
