"""Two replica sites, the witness and the clients' Proxies, and what connects them beyond topics:
heartbeats, fail-silence and alarms.

A site is one roslaunch of the replica's nodes (replica.launch, own_launcher): its nodes are
required, so the site lives and dies as a whole, with its server. Each start is a new
incarnation: new processes and an empty server. Its nodes set up in a random order, except that
the After waits for its Protocol and Proceed (its connections to them), and Recovery for all of them
(their services).
"""
from .replica import (AfterModel, DetectorModel, ProceedModel, ProtocolModel, ProxyModel, RecoveryModel, Server,
                      WitnessModel)
from aft_ftm.detector import PeerState

from .world import CLIENTS

NODES = (('protocol', ProtocolModel), ('proceed', ProceedModel), ('after', AfterModel), ('detector', DetectorModel))
KINDS = tuple(kind for kind, _ in NODES) + ('recovery',)


class Site(object):
    def __init__(self, env, name, peer, claims):
        self.env = env
        self.name = name
        self.peer = peer
        self.claims = claims           # launched as role:=primary
        self.incarnation = 0
        self.incarnation_id = ''
        self.alive = False
        self.nodes = {}
        self.server = None
        self.stopped_why = None

    def node(self, kind):
        return self.nodes.get(kind) if self.alive else None

    def start(self):
        """A new incarnation: its nodes come up one by one."""
        world = self.env.world
        self.incarnation += 1
        self.incarnation_id = '%s#%d' % (self.name, self.incarnation)
        self.alive = True
        self.stopped_why = None
        self.nodes = {}
        self.server = Server()
        world.log('site %s starts', self.incarnation_id)
        low, high = self.env.params.startup
        up = {}
        for kind, cls in NODES:
            delay = world.rng.uniform(low, high)
            if kind == 'after':   # its set-up waits for its connections to the Protocol and Proceed
                delay += max(up['protocol'], up['proceed'])
            up[kind] = delay
            world.after(delay, self._up, self.incarnation, kind, cls)
        # Recovery waits for the services of the nodes it promotes.
        world.after(max(up.values()) + world.rng.uniform(low, high), self._up, self.incarnation, 'recovery',
                    RecoveryModel)

    def _up(self, incarnation, kind, cls):
        if incarnation != self.incarnation or not self.alive:
            return
        node = cls(self)
        self.nodes[kind] = node
        setup = getattr(node, 'setup', None)
        if setup is not None:
            setup()
        node.rearm()

    def stop(self, why):
        """The whole site goes (a crash, a power loss, a required node exiting, fail-silence)."""
        if not self.alive:
            return
        self.env.world.log('site %s stops: %s', self.incarnation_id, why)
        self.alive = False
        self.stopped_why = why
        for node in self.nodes.values():
            node.kill()
        self.server = None
        self.env.heartbeats(self.name, self.peer)
        self.env.heartbeats(self.peer, self.name)
        if self.env.on_site_stopped is not None:
            self.env.on_site_stopped(self)

    def stall(self, duration, kinds=KINDS):
        """A pause of the machine (every node) or of some of its nodes."""
        world = self.env.world
        world.log('site %s: %s stall for %.3f s', self.incarnation_id, '+'.join(kinds), duration)
        for kind in kinds:
            node = self.nodes.get(kind)
            if node is not None and node.alive:
                node.stall(duration)
        if 'detector' in kinds:
            self.env.heartbeats(self.name, self.peer)
            world.after(duration + 1e-6, self.env.heartbeats, self.name, self.peer)


class Deployment(object):
    """The system under test: the witness (on the clients' host, or on a third one: ``witness_host``),
    the sites 'a' (launched as primary) and 'b', and the clients' Proxies."""

    def __init__(self, world, params, checker, proxies=1, initial_primary='', witness_host=CLIENTS):
        self.world = world
        self.params = params
        self.checker = checker
        self.on_site_stopped = None
        self.alarms = []            # (time, incarnation, node, kind, key, detail)
        self.batched = 0            # checkpoints that covered more than one request (group commit)
        self.caught_up = 0          # checkpoints whose replies went at once while a joiner caught up
        self.parted = 0             # state transfers sent in parts (aft_ftm.transfer)
        self.parted_joined = 0      # ... whose last part the joiner acknowledged
        self.witness = WitnessModel(self, initial_primary, witness_host)
        self.sites = {'a': Site(self, 'a', 'b', claims=True), 'b': Site(self, 'b', 'a', claims=False)}
        self.proxies = [ProxyModel(self, '/proxy%d' % i, 1000 * (i + 1)) for i in range(proxies)]
        self._beats = {}            # (from site, to site) -> [visible, generation]
        world.on_hiccup = self.hiccup
        checker.attach(self)

    def hiccup(self, process):
        """A process stalls right after a message (descheduled, a GC pause, swapping): mostly briefly."""
        rng = self.world.rng
        seconds = rng.uniform(0.001, 0.02) if rng.random() < 0.7 else rng.uniform(0.05, 0.5)
        if process.site is None:
            process.stall(seconds)
        elif process.alive:
            process.site.stall(seconds, (process.name.rsplit('/', 1)[1],))

    def node(self, site, kind):
        return self.sites[site].node(kind)

    def alarm(self, process, kind, detail, key=None):
        incarnation = process.site.incarnation_id if process.site is not None else ''
        self.alarms.append((self.world.now, incarnation, process.name, kind, key, detail))
        self.world.log('ALARM %s %s: %s', process.name, kind, detail)

    # -- heartbeats ------------------------------------------------------------------------------
    def _beating(self, src, dst):
        """Do src's heartbeats reach dst's detector now?"""
        s = self.sites[src]
        detector = s.node('detector')
        if detector is None or detector.stalls or detector.stopped is not None:
            return False
        return not self.world.link_is_down(src, dst)

    def heartbeats(self, src, dst, hello=False):
        """Re-evaluate src's beats as dst sees them: where they stop, dst checks ~timeout later whether any
        came since; where they start again, a Beat is sent. ``hello``: dst (re)started watching src."""
        state = self._beats.setdefault((src, dst), [False, 0])
        visible = self._beating(src, dst)
        changed = visible != state[0]
        if changed:
            state[0] = visible
            state[1] += 1
        watcher = self.sites[dst].node('detector')
        if watcher is None:
            return
        world = self.world
        if changed and not visible:
            world.after(world.delay(src, dst) + self.params.hb_timeout, watcher.receive, watcher.silence, (state[1],))
        elif visible and (changed or hello):
            source = self.sites[src].node('detector')
            world.send(source, watcher, 'heartbeat', watcher.beat, state[1], self.sites[src].incarnation_id)

    def heartbeats_heard_now(self, src, dst):
        """dst's detector takes src as heard now: if src's beats do not come (stopped already), the
        silence is checked ~timeout from now."""
        state = self._beats.setdefault((src, dst), [False, 0])
        watcher = self.sites[dst].node('detector')
        if watcher is None or state[0]:
            return
        watcher.state = PeerState.ALIVE
        watcher.heard = state[1] - 1
        self.world.after(self.params.hb_timeout, watcher.receive, watcher.silence, (state[1],))

    def partition(self, host_a, host_b, duration):
        self.world.link_down(host_a, host_b, duration)
        self._links_changed()
        self.world.after(duration + 1e-6, self._links_changed)

    def _links_changed(self):
        self.heartbeats('a', 'b')
        self.heartbeats('b', 'a')

    # -- fail-silence ----------------------------------------------------------------------------
    def fence(self, recovery, failure):
        """RecoveryNode._fail_silence: kill the failed incarnation, if it is reached (a node on another host
        can only be asked to shut down: ~params.fence is the chance that this works)."""
        site = self.sites[failure.site]
        if not site.alive or site.incarnation_id != failure.incarnation:
            return '%s already gone' % failure.incarnation
        if self.world.rng.random() >= self.params.fence:
            return '%s not reached' % failure.incarnation
        site.stop('fenced by %s' % recovery.name)
        return '%s killed' % failure.incarnation

    # -- start -----------------------------------------------------------------------------------
    def start(self, b_delay=0.0):
        self.sites['a'].start()
        self.world.after(b_delay, self.sites['b'].start)
        for proxy in self.proxies:
            proxy.rearm()

    def serving(self):
        """The site that answers new requests now, per the witness: its primary, the incarnation the
        witness knows, with its Protocol promoted and its After not deposed; else None."""
        w = self.witness.witness
        site = self.sites.get(w.primary)
        if site is None or not site.alive or site.incarnation_id != w.incarnations.get(w.primary):
            return None
        protocol, after = site.node('protocol'), site.node('after')
        if protocol is None or after is None or protocol.core.role.name == 'BACKUP' or after.sender is None \
                or after.sender.deposed:
            return None
        return site


__all__ = ['Deployment', 'Site', 'CLIENTS', 'KINDS']
