"""Protocol: duplicate detection and sequencing, the entry of a replica's FTM graph."""
import threading
import time

import rospy
from aft_msgs.msg import Reply
from aft_msgs.srv import SetRole, SetRoleResponse, StoredReplies

from .. import config, health
from ..errors import RoleError
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import Answer, Forward, ProtocolCore, Refuse, Renumber, Role
from ..recovery import OnHang
from ..suspension import GateState
from .alarms import alarm
from .deadline import Deadline
from .diagnostics import Diagnostics
from .fail_stop import fail_stop
from .params import param
from .ports import Ports, wait_for_connections
from .peer_check import HangRule
from .persistent_service import PersistentService
from .witness_client import follow_site_role

ROLES = {'primary': Role.PRIMARY, 'backup': Role.BACKUP, 'alone': Role.ALONE}
STORED_REPLIES_SEARCH = 60.0   # s a backup looks for its After's ~stored_replies after set-up
STORED_REPLIES_TIMEOUT = 1.0   # s for one call, when taking over
TAKE_OVER_WAIT = 2.0           # s a take-over waits for the stored replies it lacks (asked, or their messages)


class ProtocolNode(object):
    """Answers duplicate requests from its reply cache and hands the others, one at a time (or one
    batch at a time, ~max_batch), to Before. As a backup it executes nothing and stores the replies
    checkpoints carry.

    Parameters:
        ~role (primary | backup | alone, default primary): a backup starts with ``requests`` unbound; a
            replica's Recovery binds it at its set-up (a backup queues requests and executes none), so that
            a failover needs no new subscription, hence no ROS master.
        ~processing_timeout (float, 30 s): an executing request with no result after this long has an
            unknown outcome: in a replica (~site set) the replica fail-stops, so that its peer takes
            over and executes it once; elsewhere, and in a site that serves alone (the witness's
            configuration names no backup: a fail-stop would stop the service), an alarm is raised and
            the request stays unanswered until its result comes. A backstop: Proceed's
            ~server_timeout normally acts first.
        ~site (str, default ''): the replica site this Protocol belongs to.
        ~witness (str, default '' : none; the launch files give the replica's, one for all its nodes): the service of the witness whose configurations it
            follows in a replica ('' : none); its node's ~configuration beside it.
        ~detector (str, default /<site>/crash_detector): asked whether the peer may take over before
            the processing timeout fail-stops the site: a peer that cannot (failed a moment ago, the
            witness not told yet) leaves the request waiting, with the alarm (aft_ftm.recovery.SiteRole).
        ~cache_capacity (int, 100000): bound of the reply cache (entries; 0: none): once reached, new
            requests are refused (not executed), with the alarm cache_full; no reply is ever forgotten.
        ~cache_bytes (int, 64 MiB): bound of the reply cache in bytes; at it, new requests are answered
            "not executed" (the client may retry) until clients confirm replies, never forgotten.
        ~replicate_refusals (bool, false): a replica's Protocol: a request refused (not executed, the
            reply cache full) is answered through After, which replicates the refusal to the backup like
            a result, so that a copy of the request sent after a failover gets the same answer and is
            never executed. A backup refuses nothing (the request waits for a promotion).
        ~max_batch (int, 1): group commit (PBR): the requests queued while a batch executes go as the next
            batch, up to this many, back to back, each numbered (aft_msgs/Request ``batch``) so that PBR's
            After checkpoints the batch once, after its last. 1: one request at a time, as every other
            mechanism needs (LFR's Before and After take one request at a time).
        ~listen_as_backup (bool, false): bind ``requests`` even as a backup (queued, not executed,
            until promoted): for a Protocol behind an entry node (a SEC gate, which Recovery binds).
        ~bind_input (bool, true): false starts with ``requests`` unbound, whatever the role (a
            mechanism the Adaptation Engine launches ahead and binds in the pause).
        ~suspend_lease (float, 10 s), ~suspend_buffer_bytes (int, 64 MiB): the lease of a suspension
            and the bound of what it holds (every FTM node: see aft_ftm.ros.ports.Ports).
    Subscribes:
        pxy2pro (aft_msgs/Request), port ``requests``: from the Proxies.
        aft2pro (aft_msgs/Reply), port ``from_after``: results of executed requests (and refusals).
        aft2pro_s (aft_msgs/Checkpoint), port ``stored``: replies carried by checkpoints (backup).
        <witness>'s configuration (aft_msgs/Configuration), in a replica: whether its site serves alone.
    Publishes:
        pro2pxy (aft_msgs/Reply), port ``replies``: to the Proxies.
        pro2bfr (aft_msgs/Request), port ``to_before``.
        prd2aft (aft_msgs/Reply), port ``refusals``: with ~replicate_refusals, refusals to After.
        fail_stop (aft_msgs/Failure), port ``fail_stop``; alarms (aft_msgs/Alarm), port ``alarms``.
        /diagnostics (diagnostic_msgs/DiagnosticArray): role, epoch, cached replies, queue (aft_ftm.health).
    Services:
        ~rebind (aft_msgs/Rebind), ~set_role (aft_msgs/SetRole), ~suspend and ~resume (aft_msgs/Suspend):
        suspended, it holds the requests arriving and answers once nothing is executing.
    Calls:
        <its After>/stored_replies (aft_msgs/StoredReplies), a backup taking over that lacks some stored replies
        (counted per checkpoint, without a gap): every reply its After holds (PBR's After offers it; the
        connection is made at set-up, named by the header of the After's connection on ``from_after``).
    """

    def __init__(self):
        role_name = param('role', config.choice(*ROLES), 'primary')
        self.processing_timeout = param('processing_timeout', config.positive_float, 30.0)
        self.site = param('site', config.optional_name, '')
        self.witness = param('witness', config.witness_service, '')
        capacity = param('cache_capacity', config.non_negative_int, 100000)
        cache_bytes = param('cache_bytes', config.non_negative_int, 64 << 20)
        self.listen_as_backup = param('listen_as_backup', config.flag, False)
        self.bind_input = param('bind_input', config.flag, True)
        self.replicate_refusals = param('replicate_refusals', config.flag, False)
        max_batch = param('max_batch', config.positive_int, 1)
        self.core = ProtocolCore(ROLES[role_name], capacity, cache_bytes, max_batch)
        self.hung = None   # the request whose outcome is unknown, once one is
        self.full_told = False   # the cache_full alarm of the episode under way was raised
        self.hung_waits = False   # ... waited for because the peer could not take over then (asked again)
        self.hang = HangRule(self.site, param('detector', config.optional_name, '') or None)
        self.lock = threading.Condition()
        self.stored_replies = None   # backup: its After's ~stored_replies, connected at set-up (no master then)
        self.after_calls = Deadline('stored-replies')
        self.ports = Ports(
            [PortSpec('requests', SUBSCRIBE, 'aft_msgs/Request'),
             PortSpec('replies', PUBLISH, 'aft_msgs/Reply'),
             PortSpec('to_before', PUBLISH, 'aft_msgs/Request'),
             PortSpec('from_after', SUBSCRIBE, 'aft_msgs/Reply'),
             PortSpec('refusals', PUBLISH, 'aft_msgs/Reply'),
             PortSpec('stored', SUBSCRIBE, 'aft_msgs/Checkpoint'),
             PortSpec('fail_stop', PUBLISH, 'aft_msgs/Failure'),
             PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
            {'requests': self._on_request, 'from_after': self._on_result, 'stored': self._on_stored})
        # Suspended (adaptation), it holds new requests and is quiescent once nothing executes.
        self.ports.suspension(hold=['requests'], quiescent=self._quiescent, resumed=self._resumed)
        self.name = rospy.get_name()

    def _quiescent(self):
        with self.lock:
            # A backup's queue waits for a promotion, not for this component: it is not "inside".
            quiet = self.core.current is None and (self.core.role == Role.BACKUP or not self.core.queue)
            if quiet:
                # Found quiescent, it stays so until resumed: a promotion meanwhile queues, and executes
                # nothing under the state transfer its After captures (the simulation, loss,local, seed 39848).
                self.core.hold()
            return quiet

    def _resumed(self):
        with self.lock:
            if self.ports.gate.state in (GateState.CLOSING, GateState.CLOSED):
                return   # a newer suspension already (a late or stray resume): its hold stays
            self._act(self.core.release(time.monotonic()))

    def setup(self, timeout):
        # Every Proxy hears the replies. One whose host lost power (no FIN, no RST) stops reading: a
        # plain write to it would block, under this node's lock, every client's replies once its socket's
        # buffers fill (a client host's power loss on emulated hosts). What it cannot take waits in a
        # buffer of its own connection (aft_ftm.ros.spillover); the others' replies go on at once.
        self.ports.bind('replies', 'pro2pxy', spill=True)
        self.ports.bind('to_before', 'pro2bfr')
        self.ports.bind('from_after', 'aft2pro')
        self.ports.bind('stored', 'aft2pro_s')
        self.ports.bind('fail_stop')
        self.ports.bind('alarms', '/aft/alarms')
        self.configuration = follow_site_role(self.hang.site_role, self.witness, report=lambda detail: alarm(self.ports, 'witness', 'forged_configuration', detail))
        self.hang.start()
        linked = ['to_before', 'from_after']
        if self.replicate_refusals:
            self.ports.bind('refusals', 'prd2aft')
            linked.append('refusals')
        missing = wait_for_connections(self.ports, linked, timeout)
        if missing:
            rospy.logerr('%s: Before/After not connected within %.1f s (ports %s)', self.name, timeout, missing)
            return False
        if self.bind_input and (self.core.role != Role.BACKUP or self.listen_as_backup):
            self.ports.bind('requests', 'pxy2pro')
        self.timer = rospy.Timer(rospy.Duration(min(1.0, self.processing_timeout / 4)), self._check_overdue)
        rospy.Service('~set_role', SetRole, self._on_set_role)
        self.ports.advertise_service()
        self.diagnostics = Diagnostics(self._health, self.site)
        if self.core.role == Role.BACKUP:
            threading.Thread(target=self._find_stored_replies, args=(STORED_REPLIES_SEARCH,), daemon=True,
                             name='stored-replies').start()
        rospy.loginfo('%s: ready as %s', self.name, self.core.role.name)
        return True

    def _health(self):
        with self.lock:
            core = self.core
            hung = '%s/%d' % (self.hung.origin, self.hung.id) if self.hung is not None else None
            return health.protocol(self.site, core.role, core.epoch, len(core.cache), core.cache.bytes,
                                   core.cache.max_bytes, len(core.queue), hung, core.stats.refused)

    def _act(self, actions):
        for action in actions:
            if isinstance(action, Forward):
                self.ports.publish('to_before', action.request)
            elif isinstance(action, Answer):
                self.ports.publish('replies', action.reply)
            elif isinstance(action, Refuse):
                self._refuse(action)
            elif isinstance(action, Renumber):
                r = action.request
                self.ports.publish('replies', Reply(id=r.id, origin=r.origin, client=r.client,
                                                    oldest_pending=action.first_id, attempt=r.attempt, batch=r.batch,
                                                    status=Reply.STALE_ID, epoch=self.core.epoch,
                                                    error='id below those answered already: renumber'))
                alarm(self.ports, 'protocol', 'stale_request', 'request %d of %s is below the ids answered '
                      'already (its Proxy started again with a clock behind?): not executed; it is told to '
                      'number from %d on' % (r.id, r.origin, action.first_id), r)

    def _refuse(self, action):
        r = action.request
        refusal = Reply(id=r.id, origin=r.origin, client=r.client, oldest_pending=r.oldest_pending,
                        attempt=r.attempt, batch=r.batch, status=Reply.NOT_EXECUTED, error=action.reason,
                        epoch=self.core.epoch)
        if not self.replicate_refusals:
            self.ports.publish('replies', refusal)
        elif self.core.role != Role.BACKUP:
            self.ports.publish('refusals', refusal)   # answered once After has replicated it
        else:
            # A backup cannot tell "not executed": its primary may have run the request. Its Proxy
            # sends it again to whichever replica serves next.
            rospy.logwarn_throttle(5, '%s: %s/%d not answered by a backup (%s)' % (self.name, r.origin, r.id,
                                                                                  action.reason))
            return
        rospy.logwarn_throttle(5, '%s: %s/%d %s' % (self.name, r.origin, r.id, action.reason))

    def _on_request(self, request):
        with self.lock:
            self._act(self.core.on_request(request, time.monotonic()))
            full = self.core.cache.full() and self.core.role != Role.BACKUP
            told, self.full_told = self.full_told, full
        if full and not told:   # once per episode: every request refused meanwhile is answered so
            alarm(self.ports, 'protocol', 'cache_full', '%s refuses new requests: %s (a Proxy that never '
                  'confirms its replies, or many origins)' % (self.name, self.core.cache.why_full()))

    def _on_result(self, reply):
        with self.lock:
            if self.hung is not None and (self.hung.origin, self.hung.id) == (reply.origin, reply.id):
                self.hung = None   # its outcome is known after all (a site alone waited for it)
                self.hung_waits = False
        if reply.status == Reply.NOT_EXECUTED:
            with self.lock:
                self._act(self.core.on_refusal(reply, time.monotonic()))
            return
        with self.lock:
            before = self.core.stats.stray_results
            self._act(self.core.on_result(reply, time.monotonic()))
            stray = self.core.stats.stray_results > before
        if stray:
            rospy.logwarn('%s: result of %s/%d matches no executing request', self.name, reply.origin, reply.id)

    def _on_stored(self, checkpoint):
        with self.lock:
            gap = self.core.stored_gap
            if checkpoint.full:
                self.core.on_state_transfer(checkpoint.cache, checkpoint.seq, checkpoint.sender, checkpoint.first_seq)
            else:   # a group commit's batch, then its last reply
                for reply in list(checkpoint.batch) + [checkpoint.reply]:
                    self.core.on_stored(reply, checkpoint.seq, checkpoint.sender, checkpoint.first_seq)
            self.core.epoch = max(self.core.epoch, checkpoint.epoch)
            now_gap = self.core.stored_gap
            self.lock.notify_all()
        if now_gap is not None and gap is None:
            rospy.logwarn('%s: the replies of checkpoint %d of %s never came (checkpoint %d did): taking over, this '
                          'Protocol asks its After for every reply it holds', self.name, now_gap, checkpoint.sender,
                          checkpoint.seq)

    def _check_overdue(self, _event):
        with self.lock:
            request = self.core.overdue(time.monotonic(), self.processing_timeout)
            if request is None:
                return
            first, self.hung = self.hung is None, self.hung or request
            waiting = self.hung_waits
        problem = 'no result for %s/%d after %.1f s: its outcome is unknown' % (
            request.origin, request.id, self.processing_timeout)
        if not first:
            # Waiting because the peer could not take over then: decided again at each tick, once it can.
            if waiting and self.hang.on_hang() == OnHang.FAIL_STOP:
                self.hung_waits = False
                fail_stop(self.ports, self.site, '%s; its peer can take over now' % problem)
            return
        if self.hang.on_hang() == OnHang.FAIL_STOP:
            fail_stop(self.ports, self.site, problem)
        else:
            self.hung_waits = bool(self.site) and not self.hang.site_role.alone()
            alarm(self.ports, 'protocol', 'request_hangs', problem + ': it stays unanswered until it is known%s'
                  % (' (%s)' % self.hang.why_wait() if self.site else ''), request)

    def _connect_stored_replies(self, wait):
        """A connection to the ~stored_replies service of the After that publishes this Protocol's results
        (named by its connection's header), if it offers one (PBR's After does); else None."""
        after = self.ports.publisher_of('from_after')
        if not after:
            return None
        name = after + '/stored_replies'
        current = self.stored_replies
        if current is not None and current.resolved_name == name:
            return current
        try:
            rospy.wait_for_service(name, wait)
            service = PersistentService(name, StoredReplies)
            service.connect()
        except (rospy.ROSException, rospy.ServiceException, OSError):
            return None   # not offered (yet), or the master is away
        self.stored_replies = service
        return service

    def _find_stored_replies(self, within):
        """Connected at set-up, in the background: a failover must not need the ROS master."""
        end = time.monotonic() + within
        while time.monotonic() < end and not rospy.is_shutdown():
            if self._connect_stored_replies(1.0) is not None:
                return
            time.sleep(0.5)

    def _fetch_stored(self, last_seq, end):
        """Every reply the After holds, stored before taking over: the messages that brought some of them
        may be lost (a connection inside the site broken, this Protocol restarted). Tried until ``end``
        (monotonic); an answer that does not cover checkpoint last_seq is not taken."""
        why = 'no After offering ~stored_replies found'
        while time.monotonic() < end:
            # the one connected at set-up, or the current After's if an adaptation replaced it
            service = self._connect_stored_replies(min(0.5, max(0.0, end - time.monotonic()))) or self.stored_replies
            if service is None:
                break   # an After that offers none: the messages are waited for
            try:
                answer = self.after_calls.call(service, max(0.05, min(STORED_REPLIES_TIMEOUT, end - time.monotonic())))
            except Exception as e:   # a timeout, a broken connection: once more, on a new connection
                why = 'asking %s failed: %s' % (service.resolved_name, e)
                self.stored_replies = service.fresh()   # (knows its address: no master needed)
                time.sleep(0.05)
                continue
            if not answer.success or answer.seq < last_seq:
                why = '%s: %s' % (service.resolved_name, answer.message or 'its replies are as of checkpoint %d only'
                                  % answer.seq)
                break
            with self.lock:
                have, gap = self.core.last_stored_seq, self.core.stored_gap
                self.core.on_state_transfer(answer.cache, answer.seq, answer.sender)
                self.core.epoch = max(self.core.epoch, answer.epoch)
                self.lock.notify_all()
            rospy.logwarn('%s: replies stored up to checkpoint %d%s, %d asked: %d replies taken from its After (%s, as '
                          'of checkpoint %d) before taking over', self.name, have,
                          ' (a gap: later ones came)' if gap is not None else '', last_seq, len(answer.cache),
                          answer.sender, answer.seq)
            return
        rospy.logwarn('%s: replies up to checkpoint %d not stored; %s: the messages are waited for', self.name,
                      last_seq, why)

    def _on_set_role(self, req):
        role = Role(req.role)
        end = time.monotonic() + TAKE_OVER_WAIT
        with self.lock:
            complete = self.core.can_take_over(req.last_seq)
        if not complete:
            self._fetch_stored(req.last_seq, end)
        with self.lock:
            if not self.lock.wait_for(lambda: self.core.can_take_over(req.last_seq),
                                      timeout=max(0.0, end - time.monotonic())):
                return SetRoleResponse(success=False, message='replies up to checkpoint %d not stored (have %d)'
                                       % (req.last_seq, self.core.last_stored_seq))
            try:
                actions = self.core.set_role(role, time.monotonic(), req.epoch)
            except RoleError as e:
                return SetRoleResponse(success=False, message=str(e))
            self._act(actions)
        rospy.loginfo('%s: role is now %s', self.name, role.name)
        return SetRoleResponse(success=True, message='role %s' % role.name, last_seq=self.core.last_stored_seq)
