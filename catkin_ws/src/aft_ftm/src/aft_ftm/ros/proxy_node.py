"""Proxy: stands in for the server, with the application's own service type."""
import time

import rospy
from aft_msgs.msg import Reply, Request

from .. import config
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..proxy import PendingTable
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


class ProxyNode(object):
    """Offers the application's service to an unmodified client and forwards each call as an
    aft_msgs/Request, re-sending it until a reply comes back.

    Parameters:
        ~service_type (str, required): the application's service type, e.g. aft_msgs/Account.
        ~resend_period (float, 0.5 s): re-send a request not answered for this long.
        ~timeout (float, 30 s): give up a call (the client gets an error) after this long.
    Services:
        service (the application's type): remap it to the name the client calls.
        ~rebind (aft_msgs/Rebind)
    Publishes:
        requests (aft_msgs/Request), port ``requests``
    Subscribes:
        replies (aft_msgs/Reply), port ``replies``
    """

    def __init__(self):
        self.service_type = param('service_type', config.service_type, required=True)
        self.resend_period = param('resend_period', config.positive_float, 0.5)
        self.timeout = param('timeout', config.positive_float, 30.0)
        self.cls = service_class(self.service_type)
        self.table = PendingTable(first_id=int(time.time() * 1e6))
        self.name = rospy.get_name()
        self.ports = Ports(
            [PortSpec('requests', PUBLISH, 'aft_msgs/Request'),
             PortSpec('replies', SUBSCRIBE, 'aft_msgs/Reply')],
            {'replies': self._on_reply}, listeners={'requests': _ResendOnConnect(self)})
        self.calls = 0
        self.errors = 0

    def setup(self, timeout):
        self.ports.bind('replies')
        self.ports.bind('requests')
        self.ports.advertise_service()
        missing = wait_for_connections(self.ports, ['requests'], timeout)
        if missing:
            rospy.logwarn('%s: no Protocol subscribed to %s yet; requests will be re-sent when one does',
                          self.name, self.ports.topic('requests'))
        self.timer = rospy.Timer(rospy.Duration(self.resend_period / 2.0), lambda _: self.resend())
        self.service = rospy.Service('service', self.cls, self._on_call)
        rospy.loginfo('%s: offering %s (%s)', self.name, self.service.resolved_name, self.service_type)
        return True

    def _request(self, entry):
        return Request(id=entry.id, origin=self.name, client=entry.client, service_type=self.service_type,
                       oldest_pending=self.table.oldest_pending(), payload=entry.payload)

    def _on_call(self, req):
        client = req._connection_header.get('callerid', '') if hasattr(req, '_connection_header') else ''
        entry = self.table.open(client, serialize(req), time.monotonic())
        self.calls += 1
        self.ports.publish('requests', self._request(entry))
        if not entry.done.wait(self.timeout):
            self.table.abandon(entry.id)
            self.errors += 1
            raise rospy.ServiceException('no reply to request %d within %.1f s (is a Protocol bound to %s?)'
                                         % (entry.id, self.timeout, self.ports.topic('requests')))
        reply = entry.reply
        if reply.status != Reply.OK:
            self.errors += 1
            raise rospy.ServiceException(reply.error or 'the request failed')
        return deserialize(self.cls._response_class, reply.payload)

    def _on_reply(self, reply):
        if reply.origin != self.name:
            return   # another Proxy's reply on a shared topic
        self.table.close(reply.id, reply)

    def resend(self, all_pending=False):
        for entry in self.table.due(time.monotonic(), 0 if all_pending else self.resend_period):
            self.ports.publish('requests', self._request(entry))
