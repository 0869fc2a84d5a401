"""Proxy: stands in for the server, with the application's own service type."""
import collections
import threading
import time
import traceback

import rospy
from aft_msgs.msg import Reply, Request

from .. import config, health, service_errors
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..proxy import Full, PendingTable
from .alarms import alarm
from .diagnostics import Diagnostics
from .envelope import deserialize, serialize, service_class
from .params import param
from .ports import Ports, wait_for_connections


class _ResendOnConnect(rospy.SubscribeListener):
    """A new Protocol subscribed (e.g. a backup taking over): re-send what is pending at once."""

    def __init__(self, proxy):
        super(_ResendOnConnect, self).__init__()
        self.proxy = proxy

    def peer_subscribe(self, topic_name, topic_publish, peer_publish):
        self.proxy.resend(all_pending=True)


class ServerError(Exception):
    """The server failed with an exception other than ServiceException: raised again here, so that
    rospy words it for the client as it did for the Proxy (``error processing request: ...``)."""


REQUEST_QUEUE = 1000


class ProxyNode(object):
    """Offers the application's service to an unmodified client and forwards each call as an
    aft_msgs/Request, re-sending it until a reply comes back.

    A call is answered only with a definite outcome: the reply, an error the server (or a mechanism)
    returned, or "not executed" (nothing changed, safe to retry). A reply from a configuration
    older than one already heard (a deposed primary) is refused with an alarm, and the request
    keeps waiting for the replica that serves.

    Parameters:
        ~service_type (str, required): the application's service type, e.g. aft_msgs/Account.
        ~resend_period (float, 0.5 s): re-send a request not answered for this long.
        ~timeout (float, 0 = none): give up a call after this long; the client then gets an error
            saying the outcome is UNKNOWN (the request may still execute). 0 waits for the outcome.
        ~max_pending_bytes (int, 64 MiB): bound of the requests waiting for replies; past it a call is
            answered "not executed" at once instead of the Proxy growing.
    Services:
        service (the application's type): remap it to the name the client calls.
        ~rebind (aft_msgs/Rebind)
    Publishes:
        requests (aft_msgs/Request), port ``requests``: queued per subscriber (1000 messages), so a
            subscriber whose host died never holds the others back; a request dropped is re-sent.
    Subscribes:
        replies (aft_msgs/Reply), port ``replies``
    """

    def __init__(self):
        self.service_type = param('service_type', config.service_type, required=True)
        self.resend_period = param('resend_period', config.positive_float, 0.5)
        self.timeout = param('timeout', config.non_negative_float, 0.0)
        self.cls = service_class(self.service_type)
        self.table = PendingTable(first_id=int(time.time() * 1e6),
                                  max_bytes=param('max_pending_bytes', config.non_negative_int, 64 << 20))
        self.name = rospy.get_name()
        self.told = collections.OrderedDict()   # requests an ids_refused alarm was raised for (64 at most)
        self.told_lock = threading.Lock()
        self.told_at = float('-inf')   # when the last of those alarms was raised
        self.ports = Ports(
            [PortSpec('requests', PUBLISH, 'aft_msgs/Request'),
             PortSpec('replies', SUBSCRIBE, 'aft_msgs/Reply'),
             PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
            {'replies': self._on_reply}, listeners={'requests': _ResendOnConnect(self)})
        self.calls = 0
        self.errors = 0

    def setup(self, timeout):
        self.ports.bind('replies')
        # Queued: a Protocol whose host lost power (no FIN, no RST) stops acknowledging, and a
        # synchronous write to it blocks once about 20 messages fill the socket's send buffer: every
        # call, and the re-sends to the Protocol that took over, would wait behind it (seen on
        # emulated hosts). A request a queue drops is re-sent (~resend_period).
        self.ports.bind('requests', queue_size=REQUEST_QUEUE)
        self.ports.bind('alarms', '/aft/alarms')
        self.ports.advertise_service()
        missing = wait_for_connections(self.ports, ['requests'], timeout)
        if missing:
            rospy.logwarn('%s: no Protocol subscribed to %s yet; requests will be re-sent when one does',
                          self.name, self.ports.topic('requests'))
        self.timer = rospy.Timer(rospy.Duration(self.resend_period / 2.0), lambda _: self._resend_on_timer())
        self.service = rospy.Service('service', self.cls, self._on_call, error_handler=self._on_error)
        self.diagnostics = Diagnostics(self._health)
        rospy.loginfo('%s: offering %s (%s)', self.name, self.service.resolved_name, self.service_type)
        return True

    def _request(self, entry):
        return Request(id=entry.id, origin=self.name, client=entry.client, service_type=self.service_type,
                       oldest_pending=self.table.oldest_pending(), payload=entry.payload, epoch=self.table.epoch)

    def _on_call(self, req):
        client = req._connection_header.get('callerid', '') if hasattr(req, '_connection_header') else ''
        try:
            entry = self.table.open(client, serialize(req), time.monotonic())
        except Full as e:
            self.errors += 1
            rospy.logwarn_throttle(5, '%s: %s' % (self.name, e))
            raise rospy.ServiceException(str(e))
        self.calls += 1
        self.ports.publish('requests', self._request(entry))
        if not entry.done.wait(self.timeout or None):
            if self.table.abandon(entry) is None:
                entry.done.wait()   # its reply came at the deadline: closed, being handed over now
        if not entry.done.is_set():
            self.errors += 1
            raise rospy.ServiceException('outcome UNKNOWN: no reply to request %d within %.1f s (it may still '
                                         'execute; is a Protocol bound to %s?)'
                                         % (entry.id, self.timeout, self.ports.topic('requests')))
        reply = entry.reply
        if reply.status != Reply.OK:
            self.errors += 1
            kind, text = service_errors.to_raise(reply.error or 'the request failed')
            raise rospy.ServiceException(text) if kind == 'service' else ServerError(text)
        return deserialize(self.cls._response_class, reply.payload)

    def _on_error(self, e, exc_type, exc_value, tb):
        """rospy's log of an exception a call raised, which goes to /rosout, in clear. A server's failure
        (ServerError) carries the server's words about the request, which SEC seals on the wire: the
        caller gets them (rospy answers it "error processing request: ..."), the log says only that it
        failed (review of session 42: rospy logged the text with a traceback). Anything else raised
        here is this node's fault, logged whole."""
        if isinstance(e, ServerError):
            rospy.logerr('%s: a call failed in the server (its error went to the caller only)' % self.name)
        else:
            rospy.logerr('%s: error processing a call: %s\n%s' % (
                self.name, e, ''.join(traceback.format_exception(exc_type, exc_value, tb))))

    def _on_reply(self, reply):
        if reply.origin != self.name:
            return   # another Proxy's reply on a shared topic
        if not self.table.fresh(reply.epoch):
            alarm(self.ports, 'pbr', 'stale_reply', 'reply to %d from epoch %d refused: epoch %d answers now'
                  % (reply.id, reply.epoch, self.table.epoch))
            return
        if reply.status == Reply.STALE_ID:
            entry = self.table.renumber(reply.id, reply.oldest_pending)
            if entry is not None:
                alarm(self.ports, 'proxy', 'ids_behind', '%s numbered request %d below the ids its replicas '
                      'answered already (started again with a clock behind): not executed; sent again as %d'
                      % (self.name, reply.id, entry.id))
                self.ports.publish('requests', self._request(entry))
                return
            why = self.table.unrenumbered(reply.id, reply.oldest_pending)
            if why is not None and self._told_once(reply.id):
                alarm(self.ports, 'proxy', 'ids_refused', '%s: %s' % (self.name, why))
            return
        self.table.close(reply.id, reply)

    def _told_once(self, request_id):
        """Whether to raise the alarm about request_id: once per request (a refusal repeats at every re-send;
        at most 64 requests are remembered, the oldest forgotten first), and at most once a second in all
        (a forged watermark refuses every new call: one alarm per call would flood at the call rate)."""
        now = time.monotonic()
        with self.told_lock:
            if request_id in self.told or now - self.told_at < 1.0:
                return False
            self.told[request_id] = True
            self.told_at = now
            while len(self.told) > 64:
                self.told.popitem(last=False)
            return True

    def _health(self):
        table = self.table
        return health.proxy(self.service.resolved_name, len(table), table.oldest_age(time.monotonic()), table.resends,
                            table.refused, table.bytes, table.max_bytes, table.epoch,
                            patience=max(4 * self.resend_period, self.timeout or 0.0))

    def _resend_on_timer(self):
        """resend(), never raising: rospy's Timer ends its thread on an exception, and the pending calls
        were then re-sent only when a new subscriber came (review of session 36: a publish racing a
        rebind of the requests port raises)."""
        try:
            self.resend()
        except Exception as e:
            rospy.logerr_throttle(5.0, '%s: re-sending the pending requests failed (tried again): %s: %s'
                                  % (self.name, type(e).__name__, e))

    def resend(self, all_pending=False):
        for entry in self.table.due(time.monotonic(), 0 if all_pending else self.resend_period):
            self.ports.publish('requests', self._request(entry))
