"""The nodes of a PBR deployment with a witness, as models of their ROS adapters' rules.

Each model is a :class:`sim.world.Process` that composes the real pure classes exactly as its
adapter does, handler for handler (the adapter's method is named in each docstring):

- :class:`ProtocolModel`  aft_ftm.ros.protocol_node.ProtocolNode      (ProtocolCore)
- :class:`ProceedModel`   aft_ftm.ros.bpa_nodes.ProceedNode, with the server replica
- :class:`AfterModel`     aft_ftm.ros.pbr_nodes.PbrAfterNode          (CheckpointSender/Receiver)
- :class:`DetectorModel`  aft_ftm.ros.detector_node.CrashDetectorNode (heartbeats, lazily)
- :class:`RecoveryModel`  aft_ftm.ros.recovery_node.RecoveryNode      (aft_ftm.recovery plans)
- :class:`WitnessModel`   aft_ftm.ros.witness_node.WitnessNode        (Witness)
- :class:`ProxyModel`     aft_ftm.ros.proxy_node.ProxyNode            (PendingTable)

Where the simulation found an adapter rule that breaks a property, the model follows the fix
proposed for the adapter, behind a flag of :class:`Params` named after it (``fix_*``), so that a
schedule can show the rule as it is (flag off) and as proposed (on, the default).

The server is a sequential model of the application: its state is the list of the request keys
it applied, in order; a reply's value is its position in that list.
"""
import types

from aft_ftm.checkpoint import (HARMLESS, NOT_EXECUTED, BatchError, CheckpointReceiver, CheckpointSender, Decision,
                                Follow, GroupCommit, Need, is_refusal)
from aft_ftm.detector import PeerState
from aft_ftm.errors import RoleError
from aft_ftm.protocol import Answer as AnswerAction, DuplicateCache, Forward, ProtocolCore, Refuse, Renumber, Role, key
from aft_ftm.proxy import PendingTable
from aft_ftm.transfer import Incoming, Outgoing, TransferError
from aft_ftm.recovery import GATES, OnHang, SiteRole, Step, plan, role_after, role_in, start_plan
from aft_ftm.witness import Op, Witness

from .world import CLIENTS, Answer, Call, Process, Sleep

STALE_ID = 3   # aft_msgs/Reply.STALE_ID

ns = types.SimpleNamespace


class Params(object):
    """Timings (simulated seconds; the deployment's defaults scaled down together) and fixes."""

    def __init__(self, **overrides):
        self.hb_timeout = 0.05          # crash detector ~timeout (ROS: 0.03)
        self.ack_timeout = 0.2          # After ~ack_timeout (ROS: 1.0)
        self.join_period = 0.1          # After ~join_period (ROS: 0.5)
        self.apply_period = 0.01        # After ~apply_period
        self.resend_period = 0.15       # Proxy ~resend_period (ROS: 0.5)
        self.witness_timeout = 0.1      # WitnessClient timeout (ROS: 1.0)
        self.witness_retry = 0.1        # Recovery ~witness_retry (ROS: 0.5)
        self.server_timeout = 0.15      # Proceed ~server_timeout (ROS: 5.0)
        self.processing_timeout = 0.6   # Protocol ~processing_timeout (ROS: 30)
        self.take_over_wait = 0.4       # Protocol set_role waits this long for stored replies (ROS: 2.0)
        self.register_timeout = 0.5     # Recovery set-up: how long a site waits for the first primary
        self.startup = (0.005, 0.03)    # how long a node takes to set up
        self.cache_bytes = 64 << 20     # Protocol and After ~cache_bytes
        self.fence = 1.0                # probability that fail-silence reaches the failed site
        self.max_batch = 1              # Protocol ~max_batch (group commit; ROS: 16 for PBR not adaptable)
        self.chunk_items = 3            # After ~chunk_bytes: a state transfer in parts of this many request keys
        self.transfer_window = 2        # After ~transfer_window: parts sent and not yet acknowledged, at most
        self.catch_up = True            # After ~catch_up: replies go at once until the joiner holds the transfer
        # Fixes of adapter rules that the simulation found to break a property, or liveness (see
        # tests/unit/test_replication_sim.py, which replays each finding with its flag off):
        # PbrAfterNode._on_set_role, PRIMARY -> ALONE (Recovery's AFTER_ALONE): raise the 'alone' alarm.
        self.fix_alone_alarm = True
        # ... and BACKUP -> ALONE (a promotion after the primary failed, not the first primary's): raise
        # 'took_over' (session 40: a promoted backup served with no backup silently, a log line only).
        self.fix_promoted_alone_alarm = True
        # ProceedNode and ProtocolNode (hung server, request overdue) in a site that serves alone: wait for
        # the late answer with an alarm rather than fail-stop the only replica holding the state.
        self.fix_wait_alone = True
        # ... and do nothing if a backup joins (sender.joiner) or was admitted since (epoch < sender.epoch).
        self.fix_stale_exclusion = True
        # PbrAfterNode._on_join: capture the state transfer with the Protocol suspended and quiescent.
        self.fix_quiescent_join = True
        # ProtocolNode/PbrAfterNode: a refusal passes through After (checkpointed) before it is answered.
        self.fix_replicated_refusal = True
        # RecoveryNode._on_failure: a retry (witness unreachable) runs the plan of the role the first try
        # had, not the one a configuration (its own promotion, granted late) gave it meanwhile.
        self.fix_retry_role = True
        # PbrAfterNode._ask_to_join: a backup that has not heard of its admission asks the witness (STATUS)
        # before it gives its state up: the configuration it heard last may be stale (a partition).
        self.fix_confirm_not_admitted = True
        # CrashDetectorNode._on_configuration: a peer watched again counts as heard now, so that one dead
        # already (its ADMIT granted late) is declared failed after ~timeout, not never.
        self.fix_rewatch_heard = True
        # ProceedNode, ProtocolNode (aft_ftm.ros.peer_check.HangRule): a hang fail-stops the site only if its
        # crash detector hears the peer able to take over now, not on a configuration naming a backup alone
        # (the 1000-fault --adapt campaign, seed 15, segment 20); Proceed asks again every recheck while it waits.
        self.fix_ask_detector = True
        self.recheck = 0.02             # Proceed: how often a hang waited out for the peer is decided again (ROS: 0.1)
        # RecoveryNode._on_own_fail_stop: a site that fail-stopped refuses a verdict about its peer afterwards.
        self.fix_own_fail_stop = True
        # ProtocolNode._on_set_role: a Protocol that lacks stored replies (ProtocolCore counts stored checkpoints
        # without a gap) asks its After for every reply it holds (~stored_replies) before it takes over; else it
        # waits for the messages that were lost, and the take-over is refused.
        self.fix_stored_gap = True
        # ProtocolNode._quiescent, _resumed: a Protocol found quiescent for a suspension starts nothing until it
        # is resumed, even if promoted meanwhile (an After's state transfer is captured under that suspension).
        self.fix_hold_when_suspended = True
        for name, value in overrides.items():
            if not hasattr(self, name):
                raise AttributeError('no parameter %r' % name)
            setattr(self, name, value)


def copy_reply(reply):
    return ns(**vars(reply)) if reply is not None else None


def copy_msg(msg):
    """What a message is after serialisation: nothing shared with the sender."""
    m = ns(**vars(msg))
    if getattr(m, 'reply', None) is not None:
        m.reply = copy_reply(m.reply)
    if getattr(m, 'cache', None):
        m.cache = [copy_reply(r) for r in m.cache]
    if isinstance(getattr(m, 'batch', None), list):   # a checkpoint's batch (a request's is a pair)
        m.batch = [copy_reply(r) for r in m.batch]
    return m


class Server(object):
    """The application: its state is the list of request keys applied, in order."""

    def __init__(self):
        self.log = []
        self.hung = False
        self.waiters = []           # what to do once a hang ends (the calls it holds)
        self.capture_failures = 0   # the next get_state calls that fail
        self.apply_failures = 0     # the next set_state calls that fail

    def execute(self, request_key):
        self.log.append(request_key)
        return len(self.log)

    def thaw(self):
        """The hang ends: the calls it held are carried out."""
        self.hung = False
        waiters, self.waiters = self.waiters, []
        for waiter in waiters:
            waiter()

    def get_state(self):
        if self.hung:
            return None, 'get_state timed out (the server hangs)'
        if self.capture_failures:
            self.capture_failures -= 1
            return None, 'get_state failed (injected)'
        return tuple(self.log), None

    def set_state(self, state):
        if self.hung:
            return 'cannot set the server state: set_state timed out'
        if self.apply_failures:
            self.apply_failures -= 1
            return 'the server refused the state: injected'
        self.log = list(state)
        return ''


class Node(Process):
    """A node of a replica site."""

    def __init__(self, site, kind):
        super(Node, self).__init__(site.env.world, site, '/%s/%s' % (site.name, kind), site.name)
        self.env = site.env
        self.incarnation = site.incarnation_id

    def alarm(self, kind, detail, key=None):
        self.env.alarm(self, kind, detail, key)

    def fail_stop(self, problem):
        """aft_ftm.ros.fail_stop.fail_stop: a Failure to the site's crash detector (and its Recovery, which
        follows the same topic), and an alarm."""
        self.alarm('fail_stop', 'site %s stops serving: %s' % (self.site.name, problem))
        detector = self.site.node('detector')
        self.world.send(self, detector, 'fail_stop', detector.on_fail_stop if detector else None, problem)
        recovery = self.site.node('recovery')
        if recovery is not None and recovery is not self:
            self.world.send(self, recovery, 'fail_stop', recovery.on_own_fail_stop, problem)

    def peer_alive(self):
        """aft_ftm.ros.peer_check.PeerCheck.alive: the site's crash detector, asked (None: no answer)."""
        detector = self.site.node('detector')
        if detector is None:
            return None
        return detector.state == PeerState.ALIVE

    def hang_rule(self):
        """What a hang does now (HangRule.on_hang), as the adapters' rule is set."""
        return self.site_role.on_hang(self.peer_alive if self.env.params.fix_ask_detector else None)

    def own(self, kind):
        return self.site.node(kind)

    def peer(self, kind):
        return self.env.node(self.site.peer, kind)


# -- Protocol --------------------------------------------------------------------------------------

class ProtocolModel(Node):
    """ProtocolNode: a backup (every node starts as one with a witness), ``requests`` unbound until Recovery
    binds it at its set-up; set_role waits for the stored replies (releasing its lock meanwhile)."""

    def __init__(self, site):
        super(ProtocolModel, self).__init__(site, 'protocol')
        p = self.env.params
        self.core = ProtocolCore(Role.BACKUP, cache_bytes=p.cache_bytes, max_batch=p.max_batch)
        self.bound = False
        self.hung = None
        self.site_role = SiteRole(site.name)
        self.waiting = []
        self.suspended = False      # ~suspend: requests held, answered once nothing executes
        self.held = []
        self.quiescence = []        # the ~suspend calls waiting for it
        self.timer(min(1.0, p.processing_timeout / 4), self.check_overdue,
                   lambda: self.core.current is not None and self.hung is None)

    def on_request(self, request):
        if not self.bound:
            return
        if self.suspended:
            self.held.append(request)
            return
        self.act(self.core.on_request(request, self.world.now))

    def setup(self):
        self.env.witness.subscribe(self, self.on_configuration)

    def on_configuration(self, conf):
        self.site_role.on_configuration(conf.epoch, conf.primary, conf.backup)

    def on_result(self, reply):
        if self.hung is not None and key(self.hung) == key(reply):
            self.hung = None   # its outcome is known after all (a site alone waited for it)
        if not reply.ok and reply.refusal:
            # fix_replicated_refusal: the After released a refusal (its backup holds it): ProtocolNode
            # keeps it as the request's answer and answers it.
            self.act(self.core.on_refusal(reply, self.world.now))
        else:
            self.act(self.core.on_result(reply, self.world.now))
        self._check_quiescence()

    def quiescent(self):
        """ProtocolNode._quiescent."""
        return self.core.current is None and (self.core.role == Role.BACKUP or not self.core.queue)

    def _check_quiescence(self):
        if self.quiescence and self.quiescent():
            if self.env.params.fix_hold_when_suspended:
                self.core.hold()   # ProtocolNode._quiescent: nothing starts until resumed
            waiters, self.quiescence = self.quiescence, []
            for respond in waiters:
                respond(Answer(True, 'quiescent'))

    def srv_suspend(self, respond, kwargs):
        self.suspended = True
        self.quiescence.append(respond)
        self._check_quiescence()
        self.world.after(kwargs['timeout'], self.receive, self._suspend_timeout, (respond,), True)

    def _suspend_timeout(self, respond):
        if respond in self.quiescence:
            self.quiescence.remove(respond)
            respond(Answer(False, 'not quiescent'))

    def srv_resume(self, respond, kwargs):
        self.suspended = False
        self.act(self.core.release(self.world.now))
        held, self.held = self.held, []
        for request in held:
            self.act(self.core.on_request(request, self.world.now))
        respond(Answer(True, 'resumed'))

    def on_stored(self, cp):
        if cp.full:
            self.core.on_state_transfer(cp.cache, cp.seq, cp.sender, getattr(cp, 'first_seq', 0))
        else:   # ProtocolNode._on_stored: a group commit's batch, then its last reply
            for reply in list(getattr(cp, 'batch', None) or []) + [cp.reply]:
                self.core.on_stored(reply, cp.seq, cp.sender, getattr(cp, 'first_seq', 0))
        self.core.epoch = max(self.core.epoch, cp.epoch)
        for waiting in list(self.waiting):
            if self.core.can_take_over(waiting[0]['last_seq']):
                self.waiting.remove(waiting)
                self._set_role(*waiting)

    def check_overdue(self):
        request = self.core.overdue(self.world.now, self.env.params.processing_timeout)
        if request is None or self.hung is not None:
            return
        self.hung = request
        problem = 'no result for %s/%d: its outcome is unknown' % (request.origin, request.id)
        if self.hang_rule() == OnHang.FAIL_STOP or not self.env.params.fix_wait_alone:
            self.fail_stop(problem)
        else:
            self.alarm('request_hangs', problem + ': site %s serves alone, it waits' % self.site.name)

    def srv_set_role(self, respond, kwargs):
        waiting = (kwargs, respond)
        if self.core.can_take_over(kwargs['last_seq']):
            self._set_role(*waiting)
            return
        self.waiting.append(waiting)
        if self.env.params.fix_stored_gap:
            self.spawn(self._fetch_stored(kwargs['last_seq']))
        self.world.after(self.env.params.take_over_wait, self.receive, self._give_up, (waiting,), True)

    def _fetch_stored(self, last_seq):
        """ProtocolNode._fetch_stored: every reply the After holds (the messages that stored some were lost)."""
        answer = yield Call(self.own('after'), 'stored_replies')
        if answer.success and answer.seq >= last_seq:
            self.on_stored(ns(full=True, cache=answer.cache, seq=answer.seq, sender=answer.sender,
                              epoch=answer.epoch))

    def _give_up(self, waiting):
        if waiting in self.waiting:
            self.waiting.remove(waiting)
            waiting[1](Answer(False, 'replies up to checkpoint %d not stored (have %d)'
                              % (waiting[0]['last_seq'], self.core.last_stored_seq)))

    def _set_role(self, kwargs, respond):
        try:
            actions = self.core.set_role(kwargs['role'], self.world.now, kwargs.get('epoch', 0))
        except RoleError as e:
            respond(Answer(False, str(e)))
            return
        self.act(actions)
        self.world.log('%s role %s epoch %d', self.name, kwargs['role'].name, self.core.epoch)
        respond(Answer(True, 'role %s' % kwargs['role'].name, self.core.last_stored_seq))

    def srv_rebind(self, respond, kwargs):
        self.bound = True
        for proxy in self.env.proxies:     # Proxy._ResendOnConnect: a new subscriber gets every pending request
            self.world.after(self.world.delay(CLIENTS, self.host), proxy.receive, proxy.resend, (True,))
        respond(Answer(True, 'bound'))

    def act(self, actions):
        for action in actions:
            if isinstance(action, Forward):
                proceed = self.own('proceed')
                self.world.send(self, proceed, 'pro2bfr', proceed.on_request if proceed else None,
                                copy_msg(action.request))
            elif isinstance(action, AnswerAction):
                if not action.cached:
                    self.env.checker.new_answer(self, action.reply)
                self.answer(action.reply)
            elif isinstance(action, Refuse):
                r = action.request
                refusal = ns(id=r.id, origin=r.origin, client=r.client, attempt=r.attempt,
                             oldest_pending=r.oldest_pending, ok=False, value=None, error=action.reason,
                             epoch=self.core.epoch, refusal=True, status=NOT_EXECUTED, batch=getattr(r, 'batch', (0, 0)))
                if not self.env.params.fix_replicated_refusal:
                    self.answer(refusal)
                elif self.core.role != Role.BACKUP:
                    # Proposed fix: a refusal is the request's outcome, so it is replicated like a result:
                    # through After (held until the backup has it), then kept in the reply cache.
                    after = self.own('after')
                    self.world.send(self, after, 'prd2aft', after.handle if after else None, refusal)
                # A backup (being promoted) refuses nothing yet: the request waits for its promotion.
            elif isinstance(action, Renumber):   # ProtocolNode: a STALE_ID reply, straight to the Proxies
                r = action.request
                self.answer(ns(id=r.id, origin=r.origin, client=r.client, attempt=r.attempt,
                               oldest_pending=action.first_id, ok=False, value=None, error='renumber',
                               epoch=self.core.epoch, status=STALE_ID, batch=getattr(r, 'batch', (0, 0))))

    def answer(self, reply):
        self.world.log('%s answers %s/%d epoch %d %s', self.name, reply.origin, reply.id, reply.epoch,
                       reply.value if reply.ok else reply.error[:30])
        for proxy in self.env.proxies:
            self.world.send(self, proxy, 'pro2pxy', proxy.on_reply, copy_reply(reply))


# -- Proceed and the server ------------------------------------------------------------------------

class ProceedModel(Node):
    """ProceedNode in a replica (``~site`` set): a hung server is a fail-stop past ~server_timeout,
    unless the site serves alone (its SiteRole, from the witness's configurations, heard on a thread
    of their own: even while a call blocks): then it waits for the late answer, with an alarm. The
    server carries out the call once its hang ends, whether Proceed still waits for it or not."""

    def __init__(self, site):
        super(ProceedModel, self).__init__(site, 'proceed')
        self.failed = None
        self.site_role = SiteRole(site.name)
        self.call = None     # the server call in progress: [request, abandoned]

    def setup(self):
        self.env.witness.subscribe(self, self.on_configuration)

    def receive(self, fn, args, response=False):
        # rospy: each subscription has its own thread; the configuration's is not held by a call.
        super(ProceedModel, self).receive(fn, args, response or fn == self.on_configuration)

    def on_configuration(self, conf):
        self.site_role.on_configuration(conf.epoch, conf.primary, conf.backup)

    def on_request(self, request):
        if self.failed:
            return
        server = self.site.server
        if server.hung:
            # The call hangs: Proceed waits for it (handling nothing else) up to its timeout.
            self.busy = True
            call = self.call = [request, False]
            server.waiters.append(lambda: self.world.after(0.0, self.receive, self._answered, (call,), True))
            self.world.after(self.env.params.server_timeout, self.receive, self._timed_out, (call,), True)
            return
        self._execute(request)

    def _execute(self, request):
        value = self.site.server.execute(key(request))
        self.world.log('%s executes %s/%d -> %d', self.name, request.origin, request.id, value)
        after = self.own('after')
        self.world.send(self, after, 'prd2aft', after.handle if after else None,
                        ns(id=request.id, origin=request.origin, client=request.client, attempt=request.attempt,
                           oldest_pending=request.oldest_pending, ok=True, value=value, error='', epoch=0,
                           refusal=False, status=0, batch=getattr(request, 'batch', (0, 0))))

    def _answered(self, call):
        request, abandoned = call
        if abandoned or self.failed:
            # Abandoned past the timeout: the server still applies it (the request sat in its socket).
            value = self.site.server.execute(key(request))
            self.world.log('%s: abandoned %s/%d applied late -> %d', self.name, request.origin, request.id, value)
            return
        if call is self.call:
            self.call = None
            self.busy = False
            self._execute(request)
            self.drain()

    def _timed_out(self, call):
        if call is not self.call:
            return   # answered in time
        request = call[0]
        if self.hang_rule() == OnHang.WAIT and self.env.params.fix_wait_alone:
            self.alarm('server_hangs', 'the server did not answer %s/%d (it hangs): site %s serves alone or its '
                       'peer cannot take over, waits' % (request.origin, request.id, self.site.name))
            if self.env.params.fix_ask_detector:
                self.world.after(self.env.params.recheck, self.receive, self._recheck, (call,), True)
            return   # still busy: _answered ends it
        self._give_up(call)

    def _recheck(self, call):
        """Waiting out a hang: a peer that can take over now does, this site fail-stopping."""
        if call is not self.call or self.failed:
            return
        if self.hang_rule() == OnHang.FAIL_STOP:
            self._give_up(call)
        else:
            self.world.after(self.env.params.recheck, self.receive, self._recheck, (call,), True)

    def _give_up(self, call):
        request = call[0]
        call[1] = True
        self.call = None
        self.busy = False
        self.failed = 'the server did not answer %s/%d (it hangs)' % (request.origin, request.id)
        self.fail_stop(self.failed)
        self.drain()


# -- After ------------------------------------------------------------------------------------------

class ObservedSender(CheckpointSender):
    """The real sender; the checker sees each PRIMARY -> ALONE (a primary going on without its backup)."""

    def go_alone(self):
        was = self.role
        released = super(ObservedSender, self).go_alone()
        if was == Role.PRIMARY:
            self.observer.transition(self.owner, 'alone', None)
        return released


class ObservedReceiver(CheckpointReceiver):
    """The real receiver; the checker sees each refusal and each loss of the state it mirrored."""

    def decide(self, *args, **kwargs):
        decision = super(ObservedReceiver, self).decide(*args, **kwargs)
        if decision in (Decision.GAP, Decision.STRAY, Decision.STALE, Decision.FENCED):
            self.observer.transition(self.owner, decision.name.lower(), args[1])
        return decision

    def promote(self, initial=False):
        last_seq = super(ObservedReceiver, self).promote(initial=initial)
        if not initial:   # it serves from now on with no backup
            self.observer.transition(self.owner, 'promoted_alone', None)
        return last_seq

    def failed(self, seq, reason):
        was = self.state
        super(ObservedReceiver, self).failed(seq, reason)
        if was == Follow.FOLLOWING:
            self.observer.transition(self.owner, 'stops_mirroring', None)


class AfterModel(Node):
    """PbrAfterNode with a witness (every site starts as a backup and joins, or is promoted)."""

    def __init__(self, site):
        super(AfterModel, self).__init__(site, 'after')
        p = self.env.params
        self.role = Role.BACKUP
        # Numbered from the clock, so that a new incarnation numbers above the one before.
        self.first_seq = int(self.world.now * 1e6) + 1
        self.sender = None
        self.receiver = self._observed(ObservedReceiver(join=True))
        self.receiver.expect = '/%s/' % site.peer
        self.recent = DuplicateCache(max_bytes=p.cache_bytes)
        self.group = GroupCommit()
        self.joiner = None
        self.asking = False          # witness_lock: one witness request at a time
        self.transferring = False    # fix_quiescent_join: a state transfer is being prepared
        self.configuration_seen = None   # the witness's newest configuration
        self.followed_since = 0.0    # when the last state transfer was accepted
        self.confirming = False      # fix_confirm_not_admitted: a STATUS asked
        self.pending_state = None
        self.outgoing = None         # the state transfer in parts being sent (aft_ftm.transfer)
        self.outgoing_template = None
        self.deferred = []           # checkpoints made while its parts are sent
        self.incoming = Incoming()   # the parts of the state transfer being received
        self.told = set()
        self.timer(min(0.1, p.ack_timeout / 4), self.check_acks, self._acks_to_check)
        self.timer(p.join_period, self.ask_to_join, self._to_join)
        if p.apply_period > 0:
            self.timer(p.apply_period, self.apply_locked, lambda: self.pending_state is not None)

    def _observed(self, obj):
        obj.observer, obj.owner = self.env.checker, self
        return obj

    def setup(self):
        self.env.witness.subscribe(self, self.on_configuration)

    # -- helpers ---------------------------------------------------------------------------------
    def tell(self, kind, detail, key=None):
        if key is not None:
            if (kind, key) in self.told:
                return
            self.told.add((kind, key))
        self.alarm(kind, detail, key)

    def remember(self, reply):
        self.recent.forget_below(reply.origin, reply.oldest_pending)
        self.recent.store(reply)

    def capture(self):
        """_capture: tried twice."""
        error = None
        for _ in range(2):
            state, error = self.site.server.get_state()
            if state is not None:
                return state, None
        return None, error

    def send_peer(self, topic, handler, msg):
        peer = self.peer('after')
        self.world.send(self, peer, topic, getattr(peer, handler) if peer else None, msg)

    def ack(self, seq, ok, error, epoch, to, partial=False, part=0):
        self.send_peer('peer_acks', 'on_ack', ns(seq=seq, ok=ok, error=error, epoch=epoch, to=to, partial=partial,
                                                 part=part))

    def send_checkpoint(self, cp):
        """PbrAfterNode._send_checkpoint: queued behind the parts of a state transfer still to send."""
        if self.transfer_live() and not self.outgoing.all_sent():
            self.deferred.append(cp)
        else:
            self.send_peer('checkpoints', 'on_checkpoint', cp)

    def transfer_live(self):
        if self.outgoing is not None and (self.sender is None or self.sender.join_seq != self.outgoing.seq):
            self.outgoing, self.deferred = None, []
        return self.outgoing is not None

    def send_parts(self):
        out, template = self.outgoing, self.outgoing_template
        for part in out.next_parts():
            last = part == out.count - 1
            self.send_peer('checkpoints', 'on_checkpoint', ns(
                seq=out.seq, first_seq=self.first_seq, sender=self.name, replaces='', reply=None,
                state=out.parts[part], epoch=template.epoch, full=True, part=part, parts=out.count,
                cache=[copy_reply(r) for r in template.cache] if last else []))
        if out.all_sent():
            deferred, self.deferred = self.deferred, []
            for cp in deferred:
                self.send_peer('checkpoints', 'on_checkpoint', cp)

    def on_part_ack(self, ack):
        if self.sender is None or not self.transfer_live() or ack.seq != self.outgoing.seq or not ack.ok:
            return
        try:
            progress = self.outgoing.acknowledged(ack.part)
        except TransferError as e:
            self.resolve(Need.EXCLUDE, 'the joiner acknowledged what was not sent: %s' % e)
            return
        if progress:
            self.sender.progress(ack.seq, self.world.now)
            self.send_parts()

    def release(self, replies):
        protocol = self.own('protocol')
        for reply in replies:
            self.world.send(self, protocol, 'aft2pro', protocol.on_result if protocol else None, copy_reply(reply))

    # -- primary ---------------------------------------------------------------------------------
    def handle(self, reply):
        """PbrAfterNode.handle, group commit included."""
        if self.sender is None or self.sender.deposed:
            return
        reply.epoch = self.sender.epoch
        self.remember(reply)
        if not self.sender.needs_checkpoint():
            self.release(self.group.flush() + [reply])
            return
        try:
            replies = self.group.add(reply)
        except BatchError as e:
            self.sender.depose('group commit broken: %s' % e)
            self.fail_stop('group commit broken: %s' % e)
            return
        if replies is None:
            return
        if all(is_refusal(r) for r in replies):
            # fix_replicated_refusal: a refusal changes no state, and the state now may already hold the
            # request executing (its reply not here yet): the checkpoint carries the reply alone.
            seq = self.sender.hold(replies[-1], self.world.now, replies[:-1])
            self.send_checkpoint(ns(
                seq=seq, first_seq=self.first_seq, sender=self.name, replaces='', reply=copy_reply(replies[-1]),
                batch=[copy_reply(r) for r in replies[:-1]], state=None, epoch=self.sender.epoch, full=False,
                cache=None))
            if self.sender.releases_at_once(seq):
                self.release(replies)
            return
        state, error = self.capture()
        if state is None:
            self.sender.depose('cannot capture the server state')
            self.fail_stop('cannot capture the server state after %s/%d: %s' % (reply.origin, reply.id, error))
            return
        seq = self.sender.hold(replies[-1], self.world.now, replies[:-1])
        self.env.batched += len(replies) > 1
        self.world.log('%s checkpoint %d (%s) epoch %d', self.name, seq,
                       ' '.join('%s/%d' % (r.origin, r.id) for r in replies), self.sender.epoch)
        self.send_checkpoint(ns(
            seq=seq, first_seq=self.first_seq, sender=self.name, replaces='', reply=copy_reply(replies[-1]),
            batch=[copy_reply(r) for r in replies[:-1]], state=state, epoch=self.sender.epoch, full=False,
            cache=None))
        if self.sender.releases_at_once(seq):
            self.env.caught_up += 1
            self.release(replies)

    def on_ack(self, ack):
        if ack.to and ack.to != self.name:
            return
        if getattr(ack, 'partial', False):
            self.on_part_ack(ack)
            return
        if self.sender is None:
            return
        if ack.ok and self.transfer_live() and ack.seq == self.outgoing.seq:
            self.env.parted_joined += 1
        released, need = self.sender.on_ack(ack.seq, ack.ok)
        self.release(released)
        if need:
            self.resolve(need, 'the backup refused checkpoint %d: %s' % (ack.seq, ack.error) if not ack.ok
                         else 'the backup holds the state transfer %d' % ack.seq)

    def _acks_to_check(self):
        s = self.sender
        return s is not None and not s.deposed and (
            bool(s.held) or s.join_since is not None or
            (s.role == Role.PRIMARY and not s.admitted and self.joiner is not None))

    def check_acks(self):
        need = Need.NOTHING
        if self.sender is not None and self.sender.overdue(self.world.now, self.env.params.ack_timeout):
            need = Need.EXCLUDE
        elif self.sender is not None and self.sender.ready_to_admit() and self.joiner is not None:
            need = Need.ADMIT
        if need == Need.EXCLUDE:
            self.resolve(need, 'no acknowledgment from the backup for %.2f s' % self.env.params.ack_timeout)
        elif need == Need.ADMIT:
            self.resolve(need, 'the backup holds the state transfer')

    def resolve(self, need, why):
        if self.asking:
            return
        self.asking = True
        self.spawn(self._resolve(need, why))

    def _resolve(self, need, why):
        if need == Need.EXCLUDE:
            yield from self._exclude(why)
        elif need == Need.ADMIT:
            yield from self._admit()
        self.asking = False

    def ask(self, op, **kwargs):
        return WitnessCall(self.env, op, self.site.name, self.incarnation, **kwargs)

    def _unreachable(self, op):
        self.alarm('witness_unreachable', '%s cannot reach the witness: %s not done' % (self.site.name, op.name))

    def _exclude(self, why):
        grant = yield self.ask(Op.EXCLUDE)
        if grant is None:
            self._unreachable(Op.EXCLUDE)
            return
        if not grant.granted:
            self.deposed(grant.message)
            return
        if self.sender is None or self.sender.role == Role.ALONE and not self.sender.held:
            return
        released = self.sender.excluded(grant.epoch)
        self.role = Role.ALONE
        self.joiner = None
        self.release(released)
        self.tell('alone', '%s goes on ALONE at epoch %d (%s); %s' % (self.site.name, grant.epoch, why, grant.message))

    def _admit(self):
        joiner = self.joiner
        if joiner is None:
            return
        grant = yield self.ask(Op.ADMIT, peer=joiner[0], peer_incarnation=joiner[1])
        if grant is None:
            self._unreachable(Op.ADMIT)
            return
        if not grant.granted:
            if grant.primary != self.site.name:
                self.deposed(grant.message)
            else:
                yield from self._exclude('the witness refused to admit %s: %s' % (joiner[0], grant.message))
            return
        if self.sender is not None:
            self.sender.admit(grant.epoch)
        self.joiner = None
        self.told.clear()

    def deposed(self, why):
        withheld = self.sender.depose(why) if self.sender is not None else 0
        self.fail_stop('deposed by the witness (%s): %d replies withheld' % (why, withheld))

    # -- joins (primary side) --------------------------------------------------------------------
    def on_join(self, join):
        if join.site == self.site.name:
            return
        sender = self.sender
        if sender is None or sender.deposed:
            return
        if sender.role == Role.PRIMARY:
            if sender.joiner != join.after and join.last_seq == 0:
                self.resolve(Need.EXCLUDE, '%s asks to join again: it restarted' % join.site)
            return
        if self.env.params.fix_quiescent_join:
            if not self.transferring:
                self.transferring = True
                self.spawn(self._quiescent_transfer(join))
            return
        self.transfer(join)

    def _quiescent_transfer(self, join):
        """Proposed fix: the state is captured while the Protocol is suspended and nothing executes, so
        that it holds exactly the requests whose replies the After has seen (and the transfer carries)."""
        protocol = self.own('protocol')
        answer = yield Call(protocol, 'suspend', timeout=self.env.params.server_timeout)
        sender = self.sender
        if answer.success and sender is not None and not sender.deposed and sender.role == Role.ALONE:
            self.transfer(join)
        elif not answer.success:
            self.tell('join_failed', 'cannot transfer the state to %s: %s' % (join.site, answer.message))
        yield Call(protocol, 'resume')
        self.transferring = False

    def transfer(self, join):
        sender = self.sender
        state, error = self.capture()
        if state is None:
            self.tell('join_failed', 'cannot transfer the state to %s: %s' % (join.site, error))
            return
        seq = sender.join(join.after, self.world.now, catch_up=self.env.params.catch_up)
        self.role = Role.PRIMARY
        self.joiner = (join.site, join.incarnation)
        cache = self.recent.replies()
        self.world.log('%s state transfer %d to %s (%d replies) epoch %d', self.name, seq, join.incarnation,
                       len(cache), sender.epoch)
        template = ns(seq=seq, first_seq=self.first_seq, sender=self.name, replaces='', reply=None, state=state,
                      epoch=sender.epoch, full=True, cache=[copy_reply(r) for r in cache])
        out = Outgoing(seq, state, self.env.params.chunk_items, self.env.params.transfer_window)
        self.outgoing, self.deferred = None, []
        if out.count == 1:
            self.send_peer('checkpoints', 'on_checkpoint', template)
        else:
            self.env.parted += 1
            self.outgoing, self.outgoing_template = out, template
            self.send_parts()

    # -- backup ----------------------------------------------------------------------------------
    def _to_join(self):
        if self.role != Role.BACKUP:
            return False
        conf = self.configuration_seen
        return self.receiver.state == Follow.JOINING or (
            self.receiver.state == Follow.FOLLOWING and conf is not None
            and self.site.name not in (conf.primary, conf.backup))

    def ask_to_join(self):
        """_ask_to_join: also a backup that joined but was never admitted joins again."""
        p = self.env.params
        if self.receiver.state == Follow.FOLLOWING:
            conf = self.configuration_seen
            waited = self.world.now - self.followed_since
            if conf is not None and self.site.name not in (conf.primary, conf.backup) \
                    and waited > max(2 * p.ack_timeout, 4 * p.join_period):
                if not p.fix_confirm_not_admitted:
                    self.give_up_state(conf.epoch)
                elif not self.confirming:
                    self.confirming = True
                    self.spawn(self._confirm_not_admitted(self.followed_since))
        if self.receiver.state != Follow.JOINING:
            return
        peer = self.peer('after')
        if peer is None:
            return   # no connection to the primary's checkpoints: the state transfer would be lost
        self.send_peer('join', 'on_join', ns(site=self.site.name, after=self.name, incarnation=self.incarnation,
                                             last_seq=0))

    def give_up_state(self, epoch):
        waited = self.world.now - self.followed_since
        self.receiver.failed(self.receiver.last_seq, 'not admitted by the witness %.2f s after its state transfer '
                             '(epoch %d)' % (waited, epoch))
        self.pending_state = None
        self.tell('backup_invalid', '%s: %s; it joins again' % (self.site.name, self.receiver.invalid))

    def _confirm_not_admitted(self, since):
        """Proposed fix: give the state up only if the witness says now that this site is not in its
        configuration (unreachable: keep it; ask again at the next tick)."""
        grant = yield self.ask(Op.STATUS)
        self.confirming = False
        if grant is not None and self.site.name not in (grant.primary, grant.backup) \
                and self.receiver.state == Follow.FOLLOWING and self.followed_since == since \
                and self.role == Role.BACKUP:
            self.give_up_state(grant.epoch)

    def on_checkpoint(self, cp):
        receiver = self.receiver
        decision = receiver.decide(cp.seq, cp.sender, cp.first_seq, cp.replaces, cp.epoch, cp.full)
        error = refused_transfer = ''
        if decision == Decision.APPLY_FULL and getattr(cp, 'parts', 0) > 1:
            cp.state, error = self.incoming.take(cp)
            if error:
                refused_transfer, decision = error, Decision.GAP
            elif cp.state is None:
                self.world.log('%s part %d/%d of transfer %d from %s', self.name, cp.part, cp.parts, cp.seq, cp.sender)
                self.ack(cp.seq, True, '', receiver.epoch, cp.sender, partial=True, part=cp.part)
                return
        if decision == Decision.GAP and not refused_transfer:
            error = 'checkpoint %d received after %d: one is missing' % (cp.seq, receiver.last_seq)
        elif decision == Decision.JOINING:
            error = '%s holds no state yet: it is joining' % self.name
        elif decision == Decision.STRAY:
            error = '%s does not follow %s' % (self.name, cp.sender)
        elif decision == Decision.STALE:
            error = 'checkpoint of epoch %d, older than epoch %d' % (cp.epoch, receiver.epoch)
        elif decision == Decision.FENCED:
            error = '%s is no longer a backup of %s' % (self.name, cp.sender)
        tell = None
        if decision in HARMLESS:
            tell = ('%s_checkpoint' % decision.name.lower(), 'checkpoint %d from %s refused: %s'
                    % (cp.seq, cp.sender, error), cp.sender)
        elif error and decision != Decision.JOINING and receiver.state == Follow.FOLLOWING:
            receiver.failed(cp.seq, error)
            tell = ('backup_invalid', '%s cannot take over: %s; it joins again' % (self.site.name, error), None)
        elif error and decision == Decision.FENCED:
            tell = ('stale_checkpoint', 'checkpoint %d from %s refused: %s' % (cp.seq, cp.sender, error), cp.sender)
        elif refused_transfer:
            tell = ('join_failed', '%s: %s; it asks again' % (self.site.name, refused_transfer), None)
        epoch = receiver.epoch
        if decision in (Decision.APPLY, Decision.APPLY_FULL):
            receiver.accept(cp.seq, cp.sender, cp.epoch, cp.first_seq)
            epoch = receiver.epoch
        self.world.log('%s checkpoint %d from %s epoch %d: %s', self.name, cp.seq, cp.sender, cp.epoch, decision.name)
        self.ack(cp.seq, not error, error, epoch, cp.sender)
        protocol = self.own('protocol')
        stored = protocol.on_stored if protocol else None
        if decision == Decision.APPLY:
            batch = list(getattr(cp, 'batch', None) or [])
            for reply in batch + [cp.reply]:
                self.remember(reply)
            self.world.send(self, protocol, 'aft2pro_s', stored, ns(
                seq=cp.seq, first_seq=cp.first_seq, sender=cp.sender, reply=copy_reply(cp.reply),
                batch=[copy_reply(r) for r in batch], full=False, cache=None, epoch=cp.epoch))
        elif decision == Decision.APPLY_FULL:
            for reply in cp.cache:
                self.remember(reply)
            self.world.send(self, protocol, 'aft2pro_s', stored, ns(
                seq=cp.seq, sender=cp.sender, reply=None, full=True, cache=[copy_reply(r) for r in cp.cache],
                epoch=cp.epoch))
        if decision == Decision.APPLY_FULL:
            self.followed_since = self.world.now
        if decision in (Decision.APPLY, Decision.APPLY_FULL) and cp.state is not None:
            self.pending_state = (cp.seq, cp.state)
            if self.env.params.apply_period == 0 or decision == Decision.APPLY_FULL:
                self.apply_locked()
        if tell is not None:
            self.tell(*tell)

    def apply_locked(self):
        receiver = self.receiver
        if self.pending_state is None or receiver.state != Follow.FOLLOWING or receiver.invalid:
            return
        seq, state = self.pending_state
        error = self.site.server.set_state(state)
        self.pending_state = None
        if error:
            sender = receiver.sender
            receiver.failed(seq, error)
            self.ack(seq, False, receiver.invalid, receiver.epoch, sender or '')
            self.alarm('backup_invalid', '%s cannot take over: %s' % (self.site.name, receiver.invalid))

    # -- the witness's configuration -------------------------------------------------------------
    def on_configuration(self, conf):
        deposed = excluded = False
        if self.configuration_seen is None or conf.epoch >= self.configuration_seen.epoch:
            self.configuration_seen = conf
        if self.sender is not None and not self.sender.deposed and conf.epoch > self.sender.epoch \
                and conf.primary != self.site.name:
            deposed = True
        elif self.role == Role.BACKUP and conf.epoch > self.receiver.epoch \
                and self.site.name not in (conf.primary, conf.backup) and self.receiver.state == Follow.FOLLOWING:
            self.receiver.failed(self.receiver.last_seq, 'excluded by the witness at epoch %d' % conf.epoch)
            self.pending_state = None
            excluded = True
        if deposed:
            self.deposed('%s is the primary of epoch %d (%s)' % (conf.primary, conf.epoch, conf.reason))
        if excluded:
            self.tell('excluded', '%s was excluded at epoch %d (%s)' % (self.site.name, conf.epoch, conf.reason))

    # -- role changes ----------------------------------------------------------------------------
    def srv_stored_replies(self, respond, kwargs):
        """PbrAfterNode._on_stored_replies: every reply held, for the Protocol about to take over."""
        if self.receiver is None or not self.receiver.sender or self.receiver.state != Follow.PROMOTED:
            respond(ns(success=False, message='not taking over'))
            return
        respond(ns(success=True, message='', seq=self.receiver.last_seq, sender=self.receiver.sender,
                   epoch=self.receiver.epoch, cache=[copy_reply(r) for r in self.recent.replies()]))

    def srv_set_role(self, respond, kwargs):
        role, epoch, p = kwargs['role'], kwargs.get('epoch', 0), self.env.params
        went_alone, promoted = False, None
        try:
            if self.role == Role.BACKUP and role == Role.ALONE:
                self.apply_locked()
                last_seq = self.receiver.promote(initial=kwargs.get('initial', False))
                self.sender = self._observed(
                    ObservedSender(Role.ALONE, self.first_seq, max(epoch, self.receiver.epoch)))
                promoted = None if kwargs.get('initial', False) else self.sender.epoch
            elif self.role == Role.PRIMARY and role == Role.ALONE:
                if p.fix_stale_exclusion and (self.sender.joiner is not None or epoch < self.sender.epoch):
                    # Proposed fix: the exclusion Recovery obtained is older than a join under way (or
                    # a backup admitted since): this After asks the witness itself, serialised with
                    # ADMIT (its own overdue and refusal checks), instead of going alone on it.
                    respond(Answer(True, 'a backup joined since epoch %d: the After asks the witness itself'
                                   % epoch, self.sender.seq))
                    return
                self.release(self.sender.excluded(epoch))
                self.joiner = None
                last_seq = self.sender.seq
                went_alone = True
            elif self.role == role:
                if self.sender is not None:
                    self.sender.epoch = max(self.sender.epoch, epoch)
                last_seq = self.receiver.last_seq
            else:
                raise RoleError('role change %s -> %s is not allowed' % (self.role.name, role.name))
        except RoleError as e:
            respond(Answer(False, str(e)))
            return
        self.role = role
        if went_alone and p.fix_alone_alarm and not self.sender.deposed:
            self.tell('alone', '%s goes on ALONE at epoch %d (Recovery: the backup failed)' % (self.site.name, epoch))
        elif promoted is not None and p.fix_promoted_alone_alarm:
            self.tell('took_over', '%s is promoted at epoch %d and goes on ALONE: its primary failed' % (
                self.site.name, promoted))
        self.world.log('%s role %s epoch %d last_seq %d', self.name, role.name, epoch, last_seq)
        respond(Answer(True, 'role %s' % role.name, last_seq))


# -- crash detector ---------------------------------------------------------------------------------

class DetectorModel(Node):
    """CrashDetectorNode with ~follow_witness, heartbeats taken lazily: the peer's beats are modelled
    only where they stop (a SilenceCheck ~timeout after the last one) and start again (a Beat), see
    Deployment.heartbeats. A check finds the peer failed if no Beat came since its beats stopped:
    a stalled site, a stalled detector or a link down is then suspected, like a crashed one."""

    def __init__(self, site):
        super(DetectorModel, self).__init__(site, 'detector')
        self.state = PeerState.UNKNOWN
        self.heard = -1              # the generation of the peer's beats last heard
        self.heard_incarnation = None
        self.stopped = None
        self.peer_back_told = False

    def setup(self):
        self.env.witness.subscribe(self, self.on_configuration)
        self.env.heartbeats(self.site.name, self.site.peer)
        self.env.heartbeats(self.site.peer, self.site.name, hello=True)

    def beat(self, generation, incarnation):
        if self.state == PeerState.FAILED:
            if not self.peer_back_told:
                self.peer_back_told = True
                self.alarm('peer_back', 'site %s, declared failed, is heard again (%s)' % (self.site.peer, incarnation))
            return
        self.state = PeerState.ALIVE
        self.heard = max(self.heard, generation)
        self.heard_incarnation = incarnation

    def silence(self, generation):
        if self.state != PeerState.ALIVE or self.heard >= generation:
            return
        self.state = PeerState.FAILED
        if self.stopped is None:
            self.world.log('%s: %s failed (%s)', self.name, self.site.peer, self.heard_incarnation)
            recovery = self.own('recovery')
            self.world.send(self, recovery, 'failures', recovery.on_failure if recovery else None,
                            ns(site=self.site.peer, incarnation=self.heard_incarnation))

    def on_fail_stop(self, reason):
        if self.stopped is None:
            self.stopped = reason
            self.alarm('fail_stop', 'site %s stops heartbeating: %s' % (self.site.name, reason))
            self.env.heartbeats(self.site.name, self.site.peer)

    def on_configuration(self, conf):
        if self.site.peer not in (conf.primary, conf.backup) or self.state != PeerState.FAILED:
            return
        self.state = PeerState.UNKNOWN
        self.heard = -1
        self.peer_back_told = False
        self.alarm('peer_watched', 'site %s re-joined (epoch %d): watched again' % (self.site.peer, conf.epoch))
        if self.env.params.fix_rewatch_heard:
            self.env.heartbeats_heard_now(self.site.peer, self.site.name)
        self.env.heartbeats(self.site.peer, self.site.name, hello=True)


# -- Recovery ---------------------------------------------------------------------------------------

class RecoveryModel(Node):
    """RecoveryNode with a witness: REGISTER at set-up (a site that cannot set up stops), then the plan
    of its role on each failure verdict, under its lock; its role follows the configuration."""

    def __init__(self, site):
        super(RecoveryModel, self).__init__(site, 'recovery')
        self.role = Role.BACKUP
        self.claim = site.claims
        self.recovered = False
        self.epoch = 0
        self.granted = 0
        self.last_seq = None
        self.listening = False
        self.records = []
        self.stopped = None   # its own site's fail-stop, heard on the site's fail_stop topic
        # Recovery handles few messages, each starting slow work (service calls, killing processes):
        # where it stalls matters more than where the busy nodes do.
        self.hiccups = 10.0

    def setup(self):
        self.spawn(self._register(), blocking=True)

    def _register(self):
        # RecoveryNode.setup: the Protocol hears the clients from set-up (it queues as a backup), so that
        # no failover binds a topic (that needs the ROS master).
        # (Its answer is awaited before registering: modelled as done at once, it always succeeds.)
        self.own('protocol').srv_rebind(lambda answer: None, {})
        deadline = self.world.now + self.env.params.register_timeout
        while True:
            grant = yield WitnessCall(self.env, Op.REGISTER, self.site.name, self.incarnation, claim=self.claim)
            if grant is None:
                self.site.stop('Recovery cannot reach the witness at set-up')
                return
            if grant.granted or grant.primary or self.world.now > deadline:
                break
            yield Sleep(0.05)
        self.epoch = grant.epoch
        self.world.log('%s registered: %s', self.name, grant.message)
        if grant.granted and grant.primary == self.site.name:
            self.granted = grant.epoch
            record = {'steps': [], 'ok': True}
            yield from self._run_plan(start_plan(), None, record)
            if not record['ok']:
                self.site.stop('could not take the first primary role: %s' % record['steps'])
                return
            self.role = Role.ALONE
        self.listening = True
        self.env.witness.subscribe(self, self.on_configuration)

    def on_configuration(self, conf):
        if conf.epoch <= self.epoch:
            return
        self.epoch = conf.epoch
        before = self.role
        self.role = role_in(conf.primary, conf.backup, self.site.name)
        if self.role in (Role.PRIMARY, Role.BACKUP):
            self.recovered = False
        if self.role is None and before is not None:
            self.alarm('out_of_configuration', '%s is in no configuration of epoch %d' % (self.site.name, conf.epoch))

    def on_own_fail_stop(self, reason):
        self.stopped = self.stopped or reason

    def on_failure(self, failure, role=None):
        if not self.listening or self.recovered:
            return
        self.recovered = True
        if self.stopped is not None and self.env.params.fix_own_fail_stop:
            self.alarm('promotion_refused', '%s failed, but site %s fail-stopped itself (%s): it takes nothing over'
                       % (failure.site, self.site.name, self.stopped))
            return
        self.spawn(self._recover(failure, role), blocking=True)

    def _recover(self, failure, retried_role):
        if retried_role is not None and self.env.params.fix_retry_role:
            self.role = retried_role
        record = {'failed': failure.site, 'role_before': self.role, 'steps': [], 'ok': True}
        self.world.log('%s recovers from the failure of %s as %s', self.name, failure.incarnation, self.role)
        yield from self._run_plan(plan(self.role, True), failure, record)
        witness_steps = [s for s in record['steps'] if s[0] in GATES]
        retry = False
        if witness_steps and not witness_steps[0][1]:
            retry = 'unreachable' in witness_steps[0][2]
            self.recovered = not retry
        else:
            self.role = role_after(self.role) if self.role else None
        self.records.append(record)
        if record['role_before'] is None:
            # Excluded or deposed: the peer's failure leaves nobody with the state. Never silent.
            self.alarm('promotion_refused', '%s failed and %s cannot take over: it is in no configuration of the '
                       'witness (epoch %d)' % (failure.site, self.site.name, self.epoch))
        if retry:
            self.world.after(self.env.params.witness_retry, self.receive, self.on_failure,
                             (failure, record['role_before']))

    def _run_plan(self, waves, failure, record):
        for wave in waves:
            results = yield [self._step(step, failure) for step in wave]
            for step, (ok, detail) in zip(wave, results):
                record['steps'].append((step, ok, detail))
                record['ok'] = record['ok'] and ok
            if any(not ok for step, ok, _ in record['steps'] if step in GATES):
                return

    def _step(self, step, failure):
        return PlanStep(self, step, failure)


class PlanStep(object):
    """One step of a Recovery plan, run as a wait (the steps of a wave run in parallel)."""

    def __init__(self, recovery, step, failure):
        self.recovery = recovery
        self.step = step
        self.failure = failure

    def start(self, process, resume):
        process.spawn(self._run(resume))

    def _run(self, resume):
        r, step = self.recovery, self.step
        if step in (Step.WITNESS_PROMOTE, Step.WITNESS_EXCLUDE):
            op = Op.PROMOTE if step == Step.WITNESS_PROMOTE else Op.EXCLUDE
            grant = yield WitnessCall(r.env, op, r.site.name, r.incarnation)
            if grant is None:
                r.alarm('witness_unreachable', '%s cannot reach the witness: asked again' % r.site.name)
                resume((False, 'witness unreachable'))
                return
            if not grant.granted:
                r.alarm('promotion_refused' if op == Op.PROMOTE else 'deposed',
                        '%s: the witness refused %s: %s' % (r.site.name, op.name, grant.message))
                resume((False, 'the witness refused %s: %s' % (op.name, grant.message)))
                return
            r.granted = grant.epoch
            resume((True, 'epoch %d: %s' % (grant.epoch, grant.message)))
        elif step == Step.FAIL_SILENCE:
            resume((True, r.env.fence(r, self.failure)))
        elif step == Step.PROMOTE_AFTER:
            result = yield Call(r.own('after'), 'set_role', role=Role.ALONE, last_seq=0, epoch=r.granted,
                                initial=self.failure is None)
            if not result.success:
                resume((False, 'After refused: %s' % result.message))
                return
            r.last_seq = result.last_seq
            resume((True, 'last checkpoint %d' % result.last_seq))
        elif step == Step.PROMOTE_PROTOCOL:
            if r.last_seq is None:
                resume((False, 'not promoted: the After was not promoted'))
                return
            result = yield Call(r.own('protocol'), 'set_role', role=Role.ALONE, last_seq=r.last_seq, epoch=r.granted)
            resume((result.success, result.message))
        elif step == Step.AFTER_ALONE:
            result = yield Call(r.own('after'), 'set_role', role=Role.ALONE, epoch=r.granted)
            resume((result.success, result.message))
        else:
            raise ValueError(step)


# -- the witness and its client ---------------------------------------------------------------------

class WitnessModel(Process):
    """WitnessNode: the record (kept in memory: it is never restarted here), and the latched
    configuration topic."""

    def __init__(self, env, initial_primary, host=CLIENTS):
        super(WitnessModel, self).__init__(env.world, None, '/aft/witness', host)
        self.env = env
        self.witness = Witness(initial_primary)
        self.subscribers = []

    def request(self, op, site, incarnation, peer, peer_incarnation, claim, reply):
        before = self.witness.epoch
        grant = self.witness.request(op, site, incarnation, peer, peer_incarnation, claim)
        self.world.log('witness %s %s(%s) %s: %s', op.name, site, incarnation,
                       'GRANTED' if grant.granted else 'refused', grant.message)
        if self.witness.epoch != before:
            self.env.checker.configuration(self.witness)
            self.publish()
        reply(grant)

    def configuration(self):
        w = self.witness
        return ns(epoch=w.epoch, primary=w.primary, backup=w.backup, reason=w.reason)

    def subscribe(self, process, handler):
        self.subscribers = [(p, h) for p, h in self.subscribers if p.alive] + [(process, handler)]
        self.world.send(self, process, 'configuration', handler, self.configuration())

    def publish(self):
        conf = self.configuration()
        self.subscribers = [(p, h) for p, h in self.subscribers if p.alive]
        for process, handler in self.subscribers:
            self.world.send(self, process, 'configuration', handler, ns(**vars(conf)))


class WitnessCall(object):
    """WitnessClient.request: the Grant, or None once the call's time limit passed (unreachable; the
    witness may still carry the request out)."""

    def __init__(self, env, op, site, incarnation, peer='', peer_incarnation='', claim=False):
        self.env = env
        self.args = (op, site, incarnation, peer, peer_incarnation, claim)

    def start(self, process, resume):
        world, witness = self.env.world, self.env.witness
        done = []

        def answered(grant):
            if not done:
                done.append(grant)
                resume(grant)

        def timed_out():
            if not done:
                done.append(None)
                resume(None)

        def reply(grant):
            world.send(witness, process, 'witness_reply', answered, grant, response=True)
        world.send(process, witness, 'witness_request', witness.request, *(self.args + (reply,)))
        world.after(self.env.params.witness_timeout, process.receive, timed_out, (), True)


# -- the clients' Proxy -----------------------------------------------------------------------------

class ProxyModel(Process):
    """ProxyNode: calls wait for a definite outcome (~timeout 0); re-sends every ~resend_period and to a
    Protocol that subscribes; refuses replies of an epoch older than one already heard."""

    def __init__(self, env, name, first_id):
        super(ProxyModel, self).__init__(env.world, None, name, CLIENTS)
        self.env = env
        self.table = PendingTable(first_id)
        self.opened = []
        self.answered = None     # called with each call's first reply (a client that calls again)
        self.timer(env.params.resend_period / 2.0, self.resend, lambda: len(self.table) > 0)

    def call(self):
        entry = self.table.open('/client', b'', self.world.now)
        self.opened.append(entry)
        self.world.log('%s calls %d', self.name, entry.id)
        self.publish(entry)

    def publish(self, entry):
        request = ns(id=entry.id, origin=self.name, client=entry.client, attempt=0,
                     oldest_pending=self.table.oldest_pending(), epoch=self.table.epoch)
        for site in self.env.sites.values():
            protocol = site.node('protocol')
            if protocol is not None and protocol.bound:
                self.world.send(self, protocol, 'pxy2pro', protocol.on_request, ns(**vars(request)))

    def on_reply(self, reply):
        if reply.origin != self.name:
            return
        if not self.table.fresh(reply.epoch):
            self.env.alarm(self, 'stale_reply', 'reply to %d from epoch %d refused: epoch %d answers now'
                           % (reply.id, reply.epoch, self.table.epoch))
            return
        if getattr(reply, 'status', None) == STALE_ID:   # no outcome: sent again under a new id
            entry = self.table.renumber(reply.id, reply.oldest_pending)
            if entry is not None:
                self.env.alarm(self, 'ids_behind', '%d sent again as %d' % (reply.id, entry.id))
                self.publish(entry)
                return
            why = self.table.unrenumbered(reply.id, reply.oldest_pending)   # (as the node: never silent)
            if why is not None:
                self.env.alarm(self, 'ids_refused', why)
            return
        entry = self.table.close(reply.id, reply)
        self.env.checker.accepted(self, reply, entry is not None)
        if entry is not None and self.answered is not None:
            self.answered(self, entry)

    def resend(self, all_pending=False):
        for entry in self.table.due(self.world.now, 0 if all_pending else self.env.params.resend_period):
            self.publish(entry)

    def unanswered(self):
        return [e.id for e in self.opened if e.reply is None]
