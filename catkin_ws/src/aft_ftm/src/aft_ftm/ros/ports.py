"""Rebindable ports: the dynamic binding service every FTM node offers (paper Fig. 7), and the
suspension (``~suspend``/``~resume``) the Adaptation Engine uses, with its lease and its bounded
buffer (:mod:`aft_ftm.suspension`)."""
import threading
import time
import warnings

import rosgraph
import rospy
from aft_msgs.msg import Alarm
from aft_msgs.srv import Rebind, RebindResponse, Suspend, SuspendResponse
import roslib.message

from .. import config
from .. import ports as rules
from ..errors import RebindError
from ..suspension import MAX_LEASE, Gate, GateState, SuspendError
from .params import param
from .spillover import spill_over

# The suspension's parameters, the same for every FTM node: name -> (default, converter, doc).
SUSPENSION_PARAMS = {
    'suspend_lease': (10.0, config.number_in(0.001, MAX_LEASE),
                      'lease of a suspension asked with lease 0 (s, at most 600): resumes by itself (and raises an '
                      'alarm) unless resumed or renewed within it'),
    'suspend_buffer_bytes': (64 * 1024 * 1024, config.positive_int,
                             'bound of the held buffer (bytes, estimated from the messages\' fields): the '
                             'message that would exceed it ends the suspension early (alarm), none is dropped'),
}
ALARMS_TOPIC = '/aft/alarms'   # where a node without an ``alarms`` port raises its suspension alarms
NOT_SUSPENDED = 'was not suspended'   # how ~resume begins its answer when the node was not suspended


class Ports(object):
    """The publishers and subscribers of a node, each bound to a topic or unbound.

    Publishers and subscribers use tcp_nodelay. ``listeners`` maps publish ports to a
    rospy.SubscribeListener. A rebind is validated fully before anything changes.

    By default (``queue_size=None``) nothing is ever dropped by a queue: publishers write
    synchronously to their connections (a rospy publisher queue drops its oldest message when
    full) and subscriber queues are unbounded. It also saves a thread hand-off per hop.

    The suspension's ROS interface, common to every FTM node (read once, here, at construction):

    Parameters:
        ~suspend_lease (float > 0, default 10 s): the lease of a ~suspend asked with lease 0.
            A suspended node resumes by itself unless resumed or renewed within its lease.
        ~suspend_buffer_bytes (int > 0, default 67108864 = 64 MiB): bound of the messages held
            while suspended (their size estimated from their fields): the message that would
            exceed it ends the suspension early, delivering every held message in order; none
            is dropped.
    Publishes:
        alarms (aft_msgs/Alarm), the node's ``alarms`` port if it has one, else /aft/alarms:
            mechanism ``suspension``, kind ``lease_expired`` or ``buffer_full``, when the node
            ends a suspension on its own (also logged).
    Services:
        ~suspend, ~resume (aft_msgs/Suspend): see :meth:`advertise_service`.
    """

    CHECK_VALID = 10.0   # s: how long a dry run's type check stands for the same rebind

    def __init__(self, specs, callbacks, queue_size=None, listeners=None):
        self.specs = {s.name: s for s in specs}
        self._callbacks = callbacks
        self._listeners = listeners or {}
        self._default_queue = queue_size
        self._queues = {}   # port -> the queue size it was bound with: a rebind keeps it
        self._spill = set()   # ports whose publisher's writes never block (bind(spill=True)): kept too
        self._latched = set()   # ports whose publisher latches (bind(latch=True)): kept too
        self._latch_lock = threading.Lock()
        self._last_latched = {}   # port -> the last message published on a latched port (published again on a rebind)
        self._handles = {}
        self._topics = {}
        self._lock = threading.RLock()
        self.unbound_publishes = 0
        values = {name: param(name, convert, default) for name, (default, convert, _) in SUSPENSION_PARAMS.items()}
        self.suspend_lease = values['suspend_lease']
        # Every subscriber goes through the gate, which holds the inputs while the node is suspended.
        self.gate = Gate(callbacks, log_error=rospy.logerr, max_bytes=values['suspend_buffer_bytes'],
                         on_self_resume=self._self_resumed)
        self._alarm_pub = None   # created by advertise_service() if the node has no alarms port
        self._lease_wakeup = threading.Event()
        self._hold = []   # by default ~suspend holds nothing and waits until no handler runs
        self._quiescent = lambda: True
        self._before_suspend = None
        self._resumed = lambda: None
        self._checked = {}   # (port, topic, direction, activate) -> when a dry run accepted it

    def suspension(self, hold, quiescent=None, before_suspend=None, resumed=None):
        """Say what ~suspend holds (input port names) and when the node is quiescent. The ports
        not held keep flowing while the node is suspending, so that what is inside can finish.
        ``before_suspend()`` runs first (e.g. apply a pending checkpoint); ``resumed()`` runs once the
        suspension ended, by ~resume or by the node itself (its lease ran out, its buffer filled)."""
        unknown = [n for n in hold if n not in self.specs]
        if unknown:
            raise ValueError('cannot hold unknown ports %s' % unknown)
        self._hold = list(hold)
        self._quiescent = quiescent or (lambda: True)
        self._before_suspend = before_suspend
        self._resumed = resumed or (lambda: None)

    def bind(self, name, topic=None, queue_size=0, spill=False, latch=False):
        """Bind port name to topic (default: the port's own name, so it can be remapped). A queue_size
        given (0: none) stays the port's for later binds that give none (a rebind). ``spill``: a
        publisher without a queue whose writes never block (aft_ftm.ros.spillover), kept on rebinds too.
        ``latch``: a publisher whose last message each new subscriber gets, kept on rebinds too (its last
        message is published again on the new topic: rebound, the watchdog's word on the primary board
        was lost for every subscriber that came later; review of session 51)."""
        spec = self.specs[name]
        resolved = rospy.resolve_name(topic if topic else name)
        cls = roslib.message.get_message_class(spec.msg_type)
        if queue_size:
            self._queues[name] = queue_size
        if spill:
            self._spill.add(name)
        if latch:
            self._latched.add(name)
        qs = self._queues.get(name) or self._default_queue
        with self._lock:
            if self._topics.get(name) == resolved:
                return 'port %s already bound to %s' % (name, resolved)
            self._unbind_locked(name)
            if spec.direction == rules.PUBLISH:
                with warnings.catch_warnings():   # rospy warns about queue_size=None: it is chosen
                    warnings.simplefilter('ignore')
                    handle = rospy.Publisher(resolved, cls, queue_size=qs, tcp_nodelay=True,
                                             subscriber_listener=self._listeners.get(name),
                                             latch=name in self._latched)
                if name in self._spill:
                    spill_over(handle, warn=rospy.logwarn)
            else:
                handle = rospy.Subscriber(resolved, cls, self._deliver, callback_args=name, queue_size=qs,
                                          tcp_nodelay=True)
            self._handles[name] = handle
            self._topics[name] = resolved
        if spec.direction == rules.PUBLISH and name in self._latched:
            with self._latch_lock:
                if name in self._last_latched and self._handles.get(name) is handle:
                    handle.publish(self._last_latched[name])
        return 'port %s bound to %s' % (name, resolved)

    def _deliver(self, msg, name):
        self.gate.deliver(name, msg)

    def unbind(self, name):
        with self._lock:
            return self._unbind_locked(name)

    def _unbind_locked(self, name):
        handle = self._handles.pop(name, None)
        topic = self._topics.pop(name, None)
        if handle is not None:
            handle.unregister()
            return 'port %s unbound from %s' % (name, topic)
        return 'port %s was not bound' % name

    def topic(self, name):
        return self._topics.get(name)

    def publisher(self, name):
        return self._handles.get(name)

    def publish(self, name, msg):
        """Publish on a port; returns False (and counts it) if the port is unbound."""
        if name in self._latched:
            # Not under the port-wide lock (a bind holds it while the master registers, for as long as the
            # master is away): a lock of the latched messages' own, which bind takes once its new
            # publisher is installed, so the newest message is the one latched on the new topic.
            with self._latch_lock:
                self._last_latched[name] = msg
                return self._publish(name, msg)
        return self._publish(name, msg)

    def _publish(self, name, msg):
        handle = self._handles.get(name)
        if handle is None:
            self.unbound_publishes += 1
            rospy.logerr('cannot publish on port %s: it is not bound to any topic', name)
            return False
        handle.publish(msg)
        return True

    def connections(self, name):
        handle = self._handles.get(name)
        return handle.get_num_connections() if handle is not None else 0

    def publisher_of(self, name):
        """The node name of a publisher a subscribed port is connected to (from its connection header;
        no call to the master), or None."""
        impl = getattr(self._handles.get(name), 'impl', None)
        callers = publisher_callers(impl, live_only=True) if impl is not None else {}
        return next(iter(callers.values()), None)

    def rebind(self, port, topic, direction, activate, queue_size=0, dry_run=False, connect_timeout=0.0):
        """Validate then apply a rebind; raises RebindError with nothing changed.

        Returns (message, previous topic). With dry_run, only validates. With connect_timeout > 0,
        answers once the port is connected to every current peer of the topic (the subscribers of
        a publish port, the publishers of a subscribe port), or restores the previous binding and
        refuses past it: a message sent right after the rebind then reaches the new peer.
        """
        resolved = rospy.resolve_name(topic) if topic else ''
        t0 = time.monotonic()
        master = rosgraph.Master(rospy.get_name())
        key = (port, resolved, direction, activate)
        checked = self._checked.get(key)
        if not dry_run and checked is not None and t0 - checked < self.CHECK_VALID:
            # The same rebind passed a dry run moments ago (an adaptation checks everything before
            # its pause): the master is not asked again in the pause.
            spec = rules.check_rebind(self.specs, port, direction, resolved, {}, activate)
        else:
            try:
                types = dict(master.getTopicTypes())
            except Exception as e:   # the master cannot be asked: refuse rather than guess
                raise RebindError('cannot check topic types with the ROS master: %s' % e)
            spec = rules.check_rebind(self.specs, port, direction, resolved, types, activate)
        self._checked.pop(key, None)
        previous = self._topics.get(port, '')
        if dry_run:
            self._checked[key] = t0
            return 'rebind of port %s to %s would be accepted' % (port, resolved or '(none)'), previous
        if not activate:
            return self.unbind(port), previous
        stale = {}
        if connect_timeout > 0 and spec.direction == rules.SUBSCRIBE:
            # What each publisher writes to this node now, before the new connection: a connection of a
            # binding undone a moment ago may still be listed (its publisher has not seen it closed yet).
            stale = _outbound_to(master, resolved, rospy.get_name(), connect_timeout)
        message = self.bind(port, resolved, queue_size)
        if connect_timeout > 0:
            missing = self._wait_peers(master, port, spec, resolved, connect_timeout, stale)
            if missing:
                if previous:
                    self.bind(port, previous, queue_size)
                else:
                    self.unbind(port)
                raise RebindError('port %s bound to %s but not connected to %s within %.2f s: binding undone'
                                  % (port, resolved, ', '.join(missing), connect_timeout))
            message += ', connected'
        return message, previous

    def _wait_peers(self, master, port, spec, topic, timeout, stale=None):
        """Wait until the port's handle counts as many connections as the topic has peers (a subscribe
        port: until each publisher lists a connection to it newer than those in ``stale``,
        {publisher: highest connection id it listed before the binding})."""
        me = rospy.get_name()
        try:
            pubs, subs, _ = master.getSystemState()
        except Exception as e:
            return ['the master (%s)' % e]
        table = subs if spec.direction == rules.PUBLISH else pubs
        peers = sorted({n for t, nodes in table if t == topic for n in nodes} - {me})
        deadline = time.monotonic() + timeout
        while self.connections(port) < len(peers):
            if time.monotonic() >= deadline:
                return ['%d of %s' % (len(peers) - self.connections(port), peers)]
            time.sleep(0.001)
        if spec.direction == rules.PUBLISH:
            return []
        # A subscriber counts its connection once the publisher has answered its header, but the
        # publisher adds the connection to those it writes to only after answering: a message
        # published in between never reaches this port (adaptation.test under load: the request
        # Before passed on right after the pause reached nobody, and hung for good). So each
        # publisher is asked until it lists this node among the subscribers it writes to, on a
        # connection newer than any it listed before the binding: the connection of a binding undone
        # a moment ago (a rollback's restore_binding) was still listed, closed, and took the first
        # request after the resume (CI, stop 38: it hung 30 s, then its site fail-stopped).
        stale = stale or {}
        waiting = list(peers)
        while waiting:
            waiting = [p for p in waiting if not _writes_to(master, p, me, topic, deadline, stale.get(p, 0))]
            if waiting and time.monotonic() >= deadline:
                return ['%s (it does not write to %s yet)' % (p, me) for p in waiting]
            if waiting:
                time.sleep(0.001)
        return []

    def advertise_service(self):
        """Offer ~rebind (aft_msgs/Rebind), ~suspend and ~resume (aft_msgs/Suspend).

        ~suspend holds the inputs and answers once quiescent, under a lease (the request's, or
        ``~suspend_lease`` for 0); with ``renew`` it only extends the lease of a suspended node
        (refused if the node is not suspended: its lease expired, say). A thread of the node's
        own, on the wall clock (a node on simulated time must resume too when its clock stands),
        resumes it when the lease runs out."""
        if 'alarms' not in self.specs:   # created now, so that subscribers are connected by the time it speaks
            self._alarm_pub = rospy.Publisher(ALARMS_TOPIC, Alarm, queue_size=10, tcp_nodelay=True)
        threading.Thread(target=self._watch_lease, name='suspend_lease', daemon=True).start()
        self._suspend_srv = rospy.Service('~suspend', Suspend, self._handle_suspend)
        self._resume_srv = rospy.Service('~resume', Suspend, self._handle_resume)
        return rospy.Service('~rebind', Rebind, self._handle_rebind)

    def _handle_rebind(self, req):
        try:
            message, previous = self.rebind(req.port, req.topic, req.direction, req.activate, req.queue_size,
                                            req.dry_run, req.connect_timeout)
        except RebindError as e:
            rospy.logerr('rebind refused: %s', e)
            return RebindResponse(success=False, message=str(e))
        if not req.dry_run:
            rospy.loginfo('rebind: %s', message)
        return RebindResponse(success=True, message=message, previous_topic=previous)

    def suspend(self, timeout, lease=None, owner=''):
        """Hold the inputs and wait until quiescent; returns the messages held. Raises SuspendError.
        ``lease`` (s): resume by itself unless resumed or renewed within it (None: ~suspend_lease);
        ``owner``: who suspends (aft_ftm.suspension.Gate)."""
        if self._before_suspend is not None:
            self._before_suspend()
        held = self.gate.close(self._hold, self._quiescent, timeout, lease=lease or self.suspend_lease, owner=owner)
        self._lease_wakeup.set()
        return held

    def _handle_suspend(self, req):
        if req.probe:
            return SuspendResponse(success=True, message=self.gate.state.name, held=self.gate.held)
        lease = req.lease if req.lease > 0 else self.suspend_lease
        if not lease <= MAX_LEASE:
            return SuspendResponse(success=False, message='a lease of %r s: at most %g s (a suspension must end by '
                                   'itself if its suspender dies)' % (lease, MAX_LEASE))
        if req.renew:
            try:
                held = self.gate.renew(lease, time.monotonic(), req.owner)
            except SuspendError as e:
                rospy.logwarn('%s: lease renewal refused: %s', rospy.get_name(), e)
                return SuspendResponse(success=False, message=str(e))
            self._lease_wakeup.set()
            return SuspendResponse(success=True, message='lease renewed: %.3g s' % lease, held=held)
        timeout = req.timeout if req.timeout > 0 else 5.0
        try:
            held = self.suspend(timeout, lease, req.owner)
        except SuspendError as e:
            rospy.logerr('%s: suspend refused: %s', rospy.get_name(), e)
            return SuspendResponse(success=False, message=str(e))
        rospy.loginfo('%s: suspended (quiescent; holding %s; lease %.3g s)', rospy.get_name(),
                      ', '.join(self._hold) or 'nothing', lease)
        return SuspendResponse(success=True, message='suspended, quiescent, lease %.3g s' % lease, held=held)

    def _watch_lease(self):
        """Resume the node when its lease runs out. Sleeps until the deadline (woken when a
        suspension starts or is renewed); an idle node wakes once a second, to see rospy shut down."""
        while not rospy.is_shutdown():
            self._lease_wakeup.clear()
            left = self.gate.lease_left(time.monotonic())
            if left is None:
                self._lease_wakeup.wait(1.0)
            elif left > 0:
                self._lease_wakeup.wait(min(left, 1.0))
            else:
                try:
                    self.gate.expire(time.monotonic())
                except Exception as e:   # the watch must go on: a later suspension needs it too
                    rospy.logerr('%s: resuming on an expired lease failed: %s', rospy.get_name(), e)

    def _self_resumed(self, event, detail):
        """The gate ended a suspension on its own (lease expired, buffer full): log and alarm."""
        rospy.logerr('%s: suspension ended by the node itself: %s', rospy.get_name(), detail)
        self._resumed()
        msg = Alarm(source=rospy.get_name(), mechanism='suspension', kind=event.value, detail=detail,
                    stamp=rospy.Time.now())
        try:
            if self._alarm_pub is not None:
                self._alarm_pub.publish(msg)
            else:
                self.publish('alarms', msg)
        except Exception as e:   # rospy shutting down: the log above still says it
            rospy.logerr('%s: cannot publish the alarm: %s', rospy.get_name(), e)

    def _handle_resume(self, req):
        if req.probe:
            return SuspendResponse(success=True, message=self.gate.state.name, held=self.gate.held)
        before = self.gate.state
        try:
            delivered = self.gate.open(req.owner)
        except SuspendError as e:
            rospy.logwarn('%s: resume refused: %s', rospy.get_name(), e)
            return SuspendResponse(success=False, message=str(e))
        self._resumed()
        if before in (GateState.CLOSED, GateState.CLOSING):
            rospy.loginfo('%s: resumed, %d held messages delivered', rospy.get_name(), delivered)
            return SuspendResponse(success=True, message='resumed', held=delivered)
        # Harmless for whoever named no owner (a rollback resumes every node it may have suspended),
        # but said; refused for an owner: the suspension it relied on had ended before its resume.
        ended = ': the last suspension ended so: %s' % self.gate.last_end if self.gate.last_end else ''
        return SuspendResponse(success=not req.owner, message='%s (%s)%s' % (NOT_SUSPENDED, before.name, ended),
                               held=delivered)

    def shutdown(self):
        with self._lock:
            for name in list(self._handles):
                self._unbind_locked(name)


def _outbound_ids(master, publisher, subscriber, topic, deadline):
    """The ids of the outbound connections of topic to subscriber the publisher node lists (getBusInfo;
    a node's connection ids only grow), or None where it cannot be asked in time."""
    from .fencing import node_api
    try:
        uri = master.lookupNode(publisher)
        code, _, info = node_api(uri, max(0.05, min(1.0, deadline - time.monotonic()))).getBusInfo(subscriber)
    except Exception:
        return None
    if code != 1:
        return None
    return [c[0] for c in info if len(c) > 4 and c[1] == subscriber and c[2] == 'o' and c[4] == topic
            and isinstance(c[0], int)]


def _writes_to(master, publisher, subscriber, topic, deadline, above=0):
    """Whether the publisher node lists an outbound connection of topic to subscriber with an id above
    ``above``; True where it cannot be asked in time (it answered the subscriber a moment ago: it lives)."""
    ids = _outbound_ids(master, publisher, subscriber, topic, deadline)
    return ids is None or any(i > above for i in ids)


def _outbound_to(master, topic, subscriber, timeout):
    """{publisher of topic: the highest id of the connections of topic to subscriber it lists now}."""
    deadline = time.monotonic() + timeout
    try:
        pubs, _, _ = master.getSystemState()
    except Exception:   # not asked: the wait after the binding asks again (no worse than before)
        return {}
    listed = {}
    for publisher in sorted({n for t, nodes in pubs if t == topic for n in nodes} - {subscriber}):
        ids = _outbound_ids(master, publisher, subscriber, topic, deadline)
        if ids:
            listed[publisher] = max(ids)
    return listed


def publisher_callers(impl, live_only=False):
    """{publisher URI: its node name} from the headers of a subscription's transports (no master call)."""
    callers = {}
    for connection in list(impl.connections):
        caller = (getattr(connection, 'header', None) or {}).get('callerid')
        if caller and not (live_only and connection.done):
            callers[connection.endpoint_id] = caller
    return callers


def wait_for_connections(ports, names, timeout):
    """Wait until every named port has at least one connection. Returns the names still missing.

    On the wall clock: a node on simulated time sets up before the simulation's clock runs (ROS
    time stands at 0 and rospy.sleep would never return)."""
    deadline = time.monotonic() + timeout
    missing = list(names)
    while not rospy.is_shutdown():
        missing = [n for n in names if ports.connections(n) < 1]
        if not missing or time.monotonic() >= deadline:
            return missing
        time.sleep(0.01)
    return missing
