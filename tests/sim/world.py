"""Simulated time, hosts, links and processes: the ground the replica models run on.

Everything happens in one thread, one event at a time, in the order of a priority queue keyed by
simulated time (ties in the order the events were scheduled), and every random choice comes from
one ``random.Random(seed)``: a seed replays its schedule exactly.

The network is what ROS topics and services over TCP are:

- each (sender, receiver, topic) is a connection that delivers in order, after a random delay
  (shorter on one host than between hosts);
- a message to a process that is dead when it arrives is lost, and so is (with probability 1/2)
  one still in flight from a process that died: nothing else is ever lost;
- a link between two hosts can be down for a while (a partition, a saturated switch): TCP
  retransmits, so what crosses it arrives, in order, once it is back;
- a new incarnation of a process gets only what was sent to it (a connection is per subscriber).

:class:`NetFaults` adds what TCP never does, each separately: loss of any message, duplicates and
reordering within a connection, to see what the protocol relies on.

A process handles one message at a time. Stalled (SIGSTOP, a starved CPU, a paused machine) it
handles nothing and keeps what arrives; it resumes with all of it, in arrival order. Besides the
stalls a schedule injects at given times, ``hiccup`` stalls a process right after some messages
(at arbitrary points of a protocol: where races are), and ``slow`` makes some messages late. Busy (a
Recovery running its plan under its lock) it handles only the answers to its own calls. Its timers
tick on a grid while it has something to check (a tick with nothing to do changes nothing, so it
is skipped); a stalled process's missed ticks come as one late tick.
"""
import collections
import heapq
import itertools
import math
import random

CLIENTS = 'c'    # the clients' host: the Proxies and the witness (never a replica's host)

LOCAL_DELAY = (0.00005, 0.0005)    # s, one host
REMOTE_DELAY = (0.0005, 0.004)     # s, between hosts


class Violation(AssertionError):
    """A property failed: which one and why (the runner adds the seed and the trace)."""

    def __init__(self, prop, detail):
        super(Violation, self).__init__('%s: %s' % (prop, detail))
        self.prop = prop
        self.detail = detail


class NetFaults(object):
    """What the network does beyond TCP, each off by default: loss of messages between live processes,
    duplicates, reordering within a connection. ``local`` False: only between hosts (a network that
    misbehaves); True: on one host too (every message, ROS's loopback connections included)."""
    __slots__ = ('loss', 'dup', 'reorder', 'local')

    def __init__(self, loss=0.0, dup=0.0, reorder=False, local=False):
        self.loss = loss          # probability that a message is lost
        self.dup = dup            # probability that a message arrives twice
        self.reorder = reorder    # True: a connection does not keep the order of its messages
        self.local = local

    def __repr__(self):
        return 'NetFaults(loss=%s, dup=%s, reorder=%s, local=%s)' % (self.loss, self.dup, self.reorder, self.local)

    def applies(self, src_host, dst_host):
        return self.local or src_host != dst_host


class World(object):
    """Simulated time, the event queue, the links between hosts, and the trace of what happened."""

    def __init__(self, seed, net=None, trace_length=60):
        self.seed = seed
        self.rng = random.Random(seed)
        self.net = net or NetFaults()
        self.now = 0.0
        self.steps = 0
        self.uids = itertools.count(1)
        self.trace = collections.deque(maxlen=trace_length)
        self.after_step = None      # called after every event (the property checker)
        self.slow = 0.0             # chance that a message takes 10-150 ms (congestion, retransmits)
        self.hiccup = 0.0           # chance that a process stalls after handling a message
        self.on_hiccup = None       # hiccup(process): stall it (the deployment knows how)
        self._queue = []
        self._order = itertools.count()
        self._fifo = {}             # connection -> arrival time of its last message
        self._down = {}             # (host, host) sorted -> the time the link is back
        self.sent = self.lost = self.duplicated = 0

    # -- events -------------------------------------------------------------------------------
    def at(self, when, fn, *args):
        heapq.heappush(self._queue, (when, next(self._order), fn, args))

    def after(self, delay, fn, *args):
        self.at(self.now + delay, fn, *args)

    def run(self, until, max_steps, done=None):
        """Run events up to time ``until`` or ``max_steps`` events; stops early once ``done()``."""
        queue = self._queue
        while queue and self.steps < max_steps:
            when, _, fn, args = queue[0]
            if when > until:
                break
            heapq.heappop(queue)
            self.now = when
            self.steps += 1
            fn(*args)
            if self.after_step is not None:
                self.after_step()
            if done is not None and done():
                break
        return self.steps

    def log(self, fmt, *args):
        """One line of the trace (formatted only if a violation prints it)."""
        self.trace.append((self.now, fmt, args))

    def trace_lines(self):
        return ['%8.4f  %s' % (t, fmt % args if args else fmt) for t, fmt, args in self.trace]

    # -- the network --------------------------------------------------------------------------
    def delay(self, src_host, dst_host):
        low, high = LOCAL_DELAY if src_host == dst_host else REMOTE_DELAY
        return self.rng.uniform(low, high)

    def link_down(self, host_a, host_b, duration):
        key = tuple(sorted((host_a, host_b)))
        self._down[key] = max(self._down.get(key, 0.0), self.now + duration)
        self.log('link %s-%s down for %.3f s', host_a, host_b, duration)

    def link_is_down(self, host_a, host_b):
        return self._down.get(tuple(sorted((host_a, host_b))), 0.0) > self.now

    def send(self, src, dst, topic, fn, *args, response=False):
        """Deliver fn(*args) to process dst (fn is one of dst's handlers) over connection (src, dst, topic)."""
        if dst is None or not dst.alive:
            return
        self.sent += 1
        net = self.net
        faulty = net.applies(src.host, dst.host)
        if faulty and net.loss and self.rng.random() < net.loss:
            self.lost += 1
            self.log('LOST %s %s -> %s', topic, src.name, dst.name)
            return
        copies = 2 if faulty and net.dup and self.rng.random() < net.dup else 1
        self.duplicated += copies - 1
        for _ in range(copies):
            delay = self.delay(src.host, dst.host)
            if self.slow and self.rng.random() < self.slow:
                delay += self.rng.uniform(0.01, 0.15)
            self._schedule(src, dst, (src.uid, dst.uid, topic), delay, fn, args, response)

    def _schedule(self, src, dst, connection, delay, fn, args, response):
        arrival = self.now + delay
        if not (self.net.reorder and self.net.applies(src.host, dst.host)):
            arrival = max(arrival, self._fifo.get(connection, 0.0) + 1e-7)
            self._fifo[connection] = arrival
        self.at(arrival, self._arrive, src, dst, connection, fn, args, response)

    def _arrive(self, src, dst, connection, fn, args, response):
        if src.host != dst.host:
            back = self._down.get((src.host, dst.host) if src.host < dst.host else (dst.host, src.host), 0.0)
            if back > self.now:
                # TCP retransmits once the link is back: later, still in order.
                self._schedule(src, dst, connection, back - self.now + self.delay(src.host, dst.host), fn, args,
                               response)
                return
        if not dst.alive:
            return
        if not src.alive and self.rng.random() < 0.5:
            self.lost += 1
            return   # in flight when its sender died: lost with its socket
        dst.receive(fn, args, response)


class Timer(object):
    """A rospy.Timer of ``process``: fn() every period while wanted()."""
    __slots__ = ('process', 'period', 'phase', 'fn', 'wanted', 'scheduled')

    def __init__(self, process, period, fn, wanted):
        self.process = process
        self.period = period
        self.phase = process.world.rng.uniform(0, period)
        self.fn = fn
        self.wanted = wanted
        self.scheduled = False

    def arm(self):
        if self.scheduled or not self.process.alive or not self.wanted():
            return
        world = self.process.world
        tick = self.phase + (math.floor((world.now - self.phase) / self.period) + 1) * self.period
        if tick <= world.now + 1e-9:
            tick += self.period     # rounding put it on the tick just taken
        self.scheduled = True
        world.at(tick, self._tick)

    def _tick(self):
        self.scheduled = False
        self.process.receive(self._fire, ())

    def _fire(self):
        if self.wanted():
            self.fn()


class Process(object):
    """One ROS node: handles one message at a time; can stall, be busy, die."""

    def __init__(self, world, site, name, host):
        self.world = world
        self.site = site            # the Site (None for the clients' processes)
        self.name = name
        self.host = host
        self.uid = next(world.uids)
        self.alive = True
        self.stalls = 0
        self.busy = False
        self.backlog = []
        self.timers = []
        self.hiccups = 1.0          # how much more often than others this process stalls after a message

    def __repr__(self):
        return '<%s %s>' % (type(self).__name__, self.name)

    def timer(self, period, fn, wanted):
        timer = Timer(self, period, fn, wanted)
        self.timers.append(timer)
        return timer

    def receive(self, fn, args, response=False):
        if not self.alive:
            return
        if self.stalls or (self.busy and not response):
            self.backlog.append((fn, args, response))
            return
        fn(*args)
        self.rearm()
        world = self.world
        if world.hiccup and world.rng.random() < world.hiccup * self.hiccups and world.on_hiccup is not None:
            world.on_hiccup(self)

    def rearm(self):
        for timer in self.timers:
            timer.arm()

    def stall(self, duration):
        self.stalls += 1
        self.world.after(duration, self._unstall)

    def _unstall(self):
        self.stalls -= 1
        self.drain()

    def drain(self):
        """Take up what arrived while stalled or busy, in arrival order."""
        if not self.alive or self.stalls:
            return
        items, self.backlog = self.backlog, []
        for fn, args, response in items:
            self.world.at(self.world.now, self.receive, fn, args, response)
        self.rearm()

    def kill(self):
        self.alive = False
        self.backlog = []

    # -- calls: coroutines that wait for answers ------------------------------------------------
    def spawn(self, coroutine, blocking=False):
        """Run a generator that yields waits (Call, WitnessCall, Sleep, a list of them in parallel).
        Blocking: the process handles nothing else until it returns (a plan under a lock)."""
        if blocking:
            self.busy = True
        self._resume(coroutine, None, blocking)

    def _resume(self, coroutine, value, blocking):
        try:
            wait = coroutine.send(value)
        except StopIteration:
            if blocking:
                self.busy = False
                self.drain()
            return
        start(wait, self, lambda result: self._resume(coroutine, result, blocking))


def start(wait, process, resume):
    """Start a wait of ``process``; resume(result) is delivered to it as a message."""
    if isinstance(wait, list):
        results = [None] * len(wait)
        left = [len(wait)]
        if not wait:
            resume([])
            return

        def one(index):
            def done(result):
                results[index] = result
                left[0] -= 1
                if not left[0]:
                    resume(results)
            return done
        for index, w in enumerate(wait):
            start(w, process, one(index))
        return
    wait.start(process, resume)


class Sleep(object):
    def __init__(self, seconds):
        self.seconds = seconds

    def start(self, process, resume):
        process.world.after(self.seconds, process.receive, resume, (None,), True)


class Call(object):
    """A ROS service call to a process of the same site, without a time limit (as Recovery's set_role
    and rebind calls): the answer, or CallFailed if the node is gone."""

    def __init__(self, target, method, **kwargs):
        self.target = target
        self.method = method
        self.kwargs = kwargs

    def start(self, process, resume):
        world = process.world
        target = self.target
        if target is None or not target.alive:
            world.after(0.0, process.receive, resume, (CallFailed('%s is gone' % (target,)),), True)
            return

        def respond(result):
            world.send(target, process, 'srv_reply', resume, result, response=True)
        world.send(process, target, 'srv:' + self.method, getattr(target, 'srv_' + self.method), respond,
                   self.kwargs)


class CallFailed(object):
    """The answer of a call whose node is gone."""
    success = False

    def __init__(self, message):
        self.message = message


class Answer(object):
    """A service's answer (SetRole, Rebind)."""
    __slots__ = ('success', 'message', 'last_seq')

    def __init__(self, success, message='', last_seq=0):
        self.success = success
        self.message = message
        self.last_seq = last_seq
