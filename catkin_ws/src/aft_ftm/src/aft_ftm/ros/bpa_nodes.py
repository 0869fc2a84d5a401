"""Before, Proceed and After: the nodes a mechanism specialises (paper Table II).

Each node has one input port and one output port of the generic graph. Before and
After default to pass-through; Proceed calls the real server. Mechanism-specific
behaviours subclass them (see :mod:`aft_ftm.ros.pbr_nodes`).
"""
import concurrent.futures
import threading
import time

import rospy
import rosservice
from aft_msgs.msg import Reply

from .. import config, health, service_errors
from ..errors import ConfigError
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..recovery import OnHang
from .alarms import alarm
from .deadline import CallTimeout, Deadline
from .diagnostics import Diagnostics
from .envelope import deserialize, serialize, service_class
from .fail_stop import fail_stop
from .params import param
from .persistent_service import PersistentService
from .peer_check import HangRule
from .ports import Ports, wait_for_connections
from .witness_client import follow_site_role


class StageNode(object):
    """A stage of the Before-Proceed-After pipeline: ``inp`` -> handle() -> ``out``.

    Subclasses set IN_TYPE, OUT_TYPE, IN_TOPIC, OUT_TOPIC and override handle(msg),
    which returns the message to send on, or None if it will send it later itself.
    Every stage reads ~bind_input (bool, default true): false starts it with ``inp`` unbound, as
    the Adaptation Engine launches a replacement that it binds in the pause. ~suspend holds ``inp``.
    Once set up, it publishes health() on /diagnostics, marked degraded while suspended.
    """
    IN_TYPE = OUT_TYPE = IN_TOPIC = OUT_TOPIC = None
    MECHANISM = ''   # the mechanism a subclass belongs to ('' for the generic stages)
    STAGE = ''       # before | proceed | after | relay
    # Other outputs a request or its result may take (bound by the subclass before setup()): heard too
    # before any input is taken (A&D's Before gives After each request: one lost there hung it for good).
    WAIT_OUTPUTS = ()

    def __init__(self, extra_ports=(), extra_callbacks=None):
        callbacks = {'inp': self._on_input}
        callbacks.update(extra_callbacks or {})
        self.ports = Ports([PortSpec('inp', SUBSCRIBE, self.IN_TYPE),
                            PortSpec('out', PUBLISH, self.OUT_TYPE)] + list(extra_ports), callbacks)
        self.ports.suspension(hold=['inp'], quiescent=self.quiescent, before_suspend=self.before_suspend)
        self.bind_input = param('bind_input', config.flag, True)
        self.name = rospy.get_name()
        self.diagnostics = None

    def quiescent(self):
        """True when no request is inside this node (checked by ~suspend)."""
        return True

    def before_suspend(self):
        """Called when ~suspend is asked, before waiting for quiescence."""

    def setup(self, timeout):
        # Output first, input only once the output is heard: rospy delivers input at once but drops what
        # is published before a subscriber connected, so a stage that took input earlier could lose a
        # request for good (campaign --adapt, seed 15, segment 13: a relaunched follower's TR After
        # published a decided reply before its Protocol's connection came, and the pair never healed).
        # Chained stage by stage, a Protocol whose to_before is connected has its whole pipeline connected
        # (up to a nested Protocol standing in for a Proceed, which takes requests once its own pipeline is).
        deadline = time.monotonic() + timeout
        self.ports.bind('out', self.OUT_TOPIC)
        missing = wait_for_connections(self.ports, ['out'] + list(self.WAIT_OUTPUTS), timeout)
        if not missing and self.bind_input:
            self.ports.bind('inp', self.IN_TOPIC)
            missing = wait_for_connections(self.ports, ['inp'], max(0.0, deadline - time.monotonic()))
        if missing:
            rospy.logerr('%s: ports %s not connected within %.1f s', self.name, missing, timeout)
            return False
        self.connected()
        self.ports.advertise_service()
        self.diagnostics = Diagnostics(self._report)
        return True

    def connected(self):
        """Called once the pipeline is connected, before ~rebind and ~suspend are offered (which tell an
        adaptation that this node is ready): a subclass binds here what must not be heard earlier."""

    def health(self):
        """This node's health (an aft_ftm.health.Report); subclasses with state say more."""
        return health.stage(self.MECHANISM, self.STAGE)

    def _report(self):
        return health.with_suspension(self.health(), self.ports.gate.state.name, self.ports.gate.held)

    def _on_input(self, msg):
        out = self.handle(msg)
        if out is not None:
            self.ports.publish('out', out)

    def handle(self, msg):
        return msg


class BeforeNode(StageNode):
    """Before, pass-through (PBR has no Before action).

    Subscribes: pro2bfr (aft_msgs/Request), port ``inp``.  Publishes: bfr2prd (aft_msgs/Request), port ``out``.
    Services: ~rebind (aft_msgs/Rebind)
    """
    IN_TYPE, OUT_TYPE, IN_TOPIC, OUT_TOPIC = 'aft_msgs/Request', 'aft_msgs/Request', 'pro2bfr', 'bfr2prd'
    STAGE = 'before'


# rospy's words (and persistent_service's) for a call that failed before its request was written: no
# connection could be made, the service has no provider, the master cannot tell where it is.
_UNSENT = ('unable to connect', 'unavailable', 'no provider', 'cannot be reached', 'unable to contact master')


def unsent(problem):
    """Whether a failed server call's error says the request was never written, so the server cannot
    have it. Any other break leaves its outcome unknown. (A connection its server closed before the
    call is opened again first: aft_ftm.ros.persistent_service.)"""
    low = problem.lower()
    return any(words in low for words in _UNSENT)


class ProceedNode(StageNode):
    """Proceed: calls the real server with the application's request and passes the reply on.

    The persistent connection to the server is opened as soon as the server is up (its type is asked
    of it), not at the first request: a backup's Proceed first calls its server at a failover, when
    the ROS master may be dead.

    A call that fails without an answer from the server (it hangs past ``~server_timeout``, or its
    connection broke: the server died or was replaced) has an unknown outcome: the server may
    apply the request later, or its state may be gone. Proceed then never answers an error. In a
    replica (``~site`` set) the replica fail-stops: the site stops heartbeating, its peer fences it
    (which kills the hung server) and executes the request, once. Outside a replica it raises an
    alarm and answers only when the call returns. So does a replica whose site serves alone (the
    witness's configuration names no backup): it holds the only copy of the state, and a fail-stop
    would turn a slow server into a stopped service (aft_ftm.recovery.SiteRole). So does a replica
    whose peer cannot take over now, as its site's crash detector says (failed a moment ago, the
    witness not told yet; silent): it waits, asking again every 0.1 s, and fail-stops once the peer
    can. Alone, a connection that breaks (the server died, its state with it) still fail-stops the replica.
    Outside a replica, a connection that broke once the request was written is answered "outcome
    unknown" with a ``server_unavailable`` alarm (the server may have applied it: never called again);
    one that could not be made is waited for (``~server_timeout``) and the request sent then.

    Parameters:
        ~server_timeout (float, 5 s): the longest a call of the server may take.
        ~site (str, default ''): the replica site this Proceed belongs to ('' : none).
        ~witness (str, default '' : none; the launch files give the replica's, one for all its nodes): the service of the witness whose configurations it
            follows in a replica ('' : none); its node's ~configuration beside it.
        ~detector (str, default /<site>/crash_detector): the site's crash detector, asked whether the
            peer may take over (aft_msgs/PeerStatus ``peer_status``).
    Services called:
        server (the application's type): remap to the server replica's service (paper: prd2srv);
        <detector>/peer_status, in a replica, when the server hangs.
    Subscribes: bfr2prd (aft_msgs/Request), port ``inp``; <witness>'s configuration
        (aft_msgs/Configuration), in a replica: whether its site serves alone.  Publishes: prd2aft (aft_msgs/Reply), port ``out``;
        fail_stop (aft_msgs/Failure), port ``fail_stop`` (to the site's crash detector); alarms
        (aft_msgs/Alarm), port ``alarms`` (/aft/alarms).
    Services: ~rebind (aft_msgs/Rebind)
    """
    IN_TYPE, OUT_TYPE, IN_TOPIC, OUT_TOPIC = 'aft_msgs/Request', 'aft_msgs/Reply', 'bfr2prd', 'prd2aft'
    STAGE = 'proceed'

    def __init__(self):
        self.server_timeout = param('server_timeout', config.positive_float, 5.0)
        self.site = param('site', config.optional_name, '')
        self.witness = param('witness', config.witness_service, '')
        super(ProceedNode, self).__init__(extra_ports=[PortSpec('fail_stop', PUBLISH, 'aft_msgs/Failure'),
                                                       PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')])
        self.server_name = rospy.resolve_name('server')
        self._proxies = {}
        self.server_type = None   # the server's service type, once _open_server has asked it
        self._lock = threading.Lock()
        self._deadline = Deadline('server-call')
        self.failed = None    # why this replica fail-stopped: nothing more is executed
        self.calling_since = None   # monotonic time the server call in progress started
        # Asked before a hang fail-stops the site, and again every recheck seconds while it waits.
        self.hang = HangRule(self.site, param('detector', config.optional_name, '') or None)
        self.recheck = 0.1

    def health(self):
        since = self.calling_since
        return health.stage(self.MECHANISM, self.STAGE, None if since is None else time.monotonic() - since,
                            self.server_timeout, self.failed)

    def setup(self, timeout):
        self.ports.bind('fail_stop')
        self.ports.bind('alarms', '/aft/alarms')
        self.configuration = follow_site_role(self.hang.site_role, self.witness, report=lambda detail: alarm(self.ports, 'witness', 'forged_configuration', detail))
        self.hang.start()
        if not super(ProceedNode, self).setup(timeout):
            return False
        threading.Thread(target=self._open_server, name='open-server', daemon=True).start()
        return True

    def _open_server(self, period=0.5):
        """Open the persistent connection to the server once it is up (asking the server its type)."""
        while not rospy.is_shutdown():
            try:
                type_name = rosservice.get_service_type(self.server_name)
                if type_name:
                    self.server_type = (type_name, service_class(type_name)._md5sum)
                    proxy = self._proxies.setdefault(type_name, PersistentService(self.server_name,
                                                                                  service_class(type_name)))
                    proxy.connect()
                    rospy.loginfo('%s: connected to the server %s (%s)', self.name, self.server_name, type_name)
                    return
            except (rosservice.ROSServiceException, rospy.ServiceException, rospy.ROSException, ConfigError,
                    OSError) as e:
                rospy.logdebug('%s: the server %s cannot be connected yet: %s', self.name, self.server_name, e)
            time.sleep(period)

    def _proxy(self, type_name):
        proxy = self._proxies.get(type_name)
        if proxy is None:
            proxy = self._proxies.setdefault(type_name, PersistentService(self.server_name, service_class(type_name)))
        return proxy

    def handle(self, request):
        reply = Reply(id=request.id, origin=request.origin, client=request.client,
                      oldest_pending=request.oldest_pending, attempt=request.attempt, batch=request.batch)
        with self._lock:
            if self.failed:
                return None   # fail-stopped: the next primary executes it
            try:
                cls = service_class(request.service_type)
                app_request = deserialize(cls._request_class, request.payload)
            except Exception as e:   # a malformed request is answered (not executed), not dropped
                reply.status, reply.error = Reply.ERROR, 'not executed: cannot decode the request: %s' % e
                return reply
            if self.server_type is not None and cls._md5sum != self.server_type[1]:
                # Not the server's type (a Proxy set up for another service, or a forged request): the
                # server refuses the connection, which read as the server gone, and fail-stopped this
                # site, then the backup with the same request (review of session 36). Answered instead.
                reply.status, reply.error = Reply.ERROR, ('not executed: the request is a %s, the server %s takes %s'
                                                          % (request.service_type, self.server_name,
                                                             self.server_type[0]))
                alarm(self.ports, 'proceed', 'wrong_type', reply.error, request)
                return reply
            try:
                response = self._call(request, app_request)
            except rospy.ServiceException as e:
                # The server answered, with an application error: that is the request's outcome, kept as
                # the server wrote it (without this replica's service name).
                reply.status, reply.error = Reply.ERROR, service_errors.as_written(str(e))
                return reply
            finally:
                self.calling_since = None
            if response is None:
                return None
            reply.payload = serialize(response)
        return reply

    def _call(self, request, app_request):
        """The server's response; raises ServiceException for the server's own error answer; None when
        the outcome is unknown and this replica fail-stopped (or is shutting down)."""
        self.calling_since = time.monotonic()
        try:
            return self._deadline.call(self._proxy(request.service_type), self.server_timeout, app_request)
        except CallTimeout as e:
            problem = 'the server %s did not answer %s/%d within %.3f s (it hangs)' % (
                self.server_name, request.origin, request.id, self.server_timeout)
            late, written = e.future, True
        except rospy.ServiceException as e:
            if 'responded with an error' in str(e):
                raise
            problem = 'the connection to the server %s broke during %s/%d: %s' % (
                self.server_name, request.origin, request.id, e)
            late, written = None, not unsent(str(e))
        except rospy.ROSException as e:   # raised before the request is written (no such service)
            problem = 'the server %s cannot be called for %s/%d: %s' % (
                self.server_name, request.origin, request.id, e)
            late, written = None, False
        broken = self._proxies.get(request.service_type)
        if broken is not None:   # a new connection next time, to the address known (the call may still run)
            self._proxies[request.service_type] = broken.fresh()
        if rospy.is_shutdown():
            # This replica is going down: stay silent (fail-silent); the Proxy re-sends the
            # request to whichever replica takes over.
            rospy.logwarn('%s: shutting down, %s/%d left to the next primary', self.name, request.origin, request.id)
            return None
        if late is not None and self.hang.on_hang() == OnHang.WAIT:
            return self._wait_late(request, late, problem)
        if self.site:
            return self._fail_stop(problem)
        if written:
            # The request was written and the connection broke: the server may have applied it (then
            # restarted, or reset the connection). Called again, it would run twice; "not executed"
            # would be a lie. The client is told the truth, and an alarm says it.
            alarm(self.ports, 'proceed', 'server_unavailable', '%s: outcome unknown, not called again' % problem,
                  request)
            raise rospy.ServiceException('outcome unknown: %s' % problem)
        # Never written (no connection could be made: a server restarting): once it is back, called.
        try:
            rospy.wait_for_service(self.server_name, self.server_timeout)
        except rospy.ROSException:
            alarm(self.ports, 'proceed', 'server_unavailable', '%s; not back within %.1f s: not executed'
                  % (problem, self.server_timeout), request)
            raise rospy.ServiceException('not executed: server %s unavailable (%s)' % (self.server_name, problem))
        return self._proxy(request.service_type)(app_request)

    def _fail_stop(self, problem):
        self.failed = problem
        fail_stop(self.ports, self.site, problem)
        return None

    def _wait_late(self, request, late, problem):
        """The late call's response, once the server answers (nobody else can execute the request):
        alarmed when the wait starts and when it ends. While it waits, the peer is asked again: one
        that can take over now (heard again after a stall, say) does, this site fail-stopping."""
        who = self.hang.why_wait()
        alarm(self.ports, 'proceed', 'server_hangs', '%s (%s): the request is answered once the server does'
              % (problem, who), request)
        while not late.done():   # (not late.result(timeout): a call that itself timed out looks the same)
            concurrent.futures.wait([late], self.recheck)
            if late.done():
                break
            if rospy.is_shutdown():
                return None
            if self.site and self.hang.on_hang() == OnHang.FAIL_STOP:
                return self._fail_stop('%s; its peer can take over now (%s)' % (problem, self.hang.peer.why))
        try:
            response = late.result()
        except Exception as e:   # the late call's own outcome, whatever it raised
            if not self.site or (isinstance(e, rospy.ServiceException) and 'responded with an error' in str(e)):
                raise
            # The hung call's connection broke: the server died, and the only state with it.
            return self._fail_stop('%s; then the call failed: %s' % (problem, e))
        alarm(self.ports, 'proceed', 'server_answered_late', 'the server %s answered %s/%d after %.3f s' % (
            self.server_name, request.origin, request.id, time.monotonic() - self.calling_since), request)
        return response


class AfterNode(StageNode):
    """After, pass-through.

    Subscribes: prd2aft (aft_msgs/Reply), port ``inp``.  Publishes: aft2pro (aft_msgs/Reply), port ``out``.
    Services: ~rebind (aft_msgs/Rebind)
    """
    IN_TYPE, OUT_TYPE, IN_TOPIC, OUT_TOPIC = 'aft_msgs/Reply', 'aft_msgs/Reply', 'prd2aft', 'aft2pro'
    STAGE = 'after'


class RelayNode(StageNode):
    """A plain relay, for baselines: republishes every message of ~type from inp to out.

    Parameters: ~type (str, required): aft_msgs/Request or aft_msgs/Reply.
    Subscribes: inp, port ``inp``.  Publishes: out, port ``out``.
    """
    IN_TOPIC, OUT_TOPIC = 'inp', 'out'

    def __init__(self):
        self.IN_TYPE = self.OUT_TYPE = param('type', config.service_type, required=True)
        super(RelayNode, self).__init__()
