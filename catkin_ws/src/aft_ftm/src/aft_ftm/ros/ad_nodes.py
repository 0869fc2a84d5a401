"""Assertion & Duplex (paper Table II: Before, Compute, Assert): user safety assertions on each
request (before it is executed) and on each reply; a violation is an error reply and an alarm."""
import threading

import rospy
from aft_msgs.msg import Reply

from .. import assertions, config
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import key
from .alarms import alarm
from .bpa_nodes import AfterNode, BeforeNode
from .envelope import deserialize, service_class
from .params import param


def _app_request(request):
    return deserialize(service_class(request.service_type)._request_class, request.payload)


def _error(msg, detail):
    return Reply(id=msg.id, origin=msg.origin, client=msg.client, oldest_pending=msg.oldest_pending,
                 attempt=msg.attempt, batch=msg.batch, status=Reply.ERROR, error=detail)


class AdBeforeNode(BeforeNode):
    """A&D's Before: checks the request assertions before the request is executed, and gives
    After the request so that reply assertions can look at both.

    Parameters: ~request_assertions (list of package.module:function, default none); ~reply_assertions
        (the After's, read here only to refuse an A&D that checks nothing: both lists empty is a
        ConfigError, not a mechanism that passes everything; review of session 34)
    Subscribes: pro2bfr (aft_msgs/Request), port ``inp``.
    Publishes: bfr2prd (aft_msgs/Request), port ``out``; bfr2aft (aft_msgs/Request), port ``to_after``;
        aft2pro (aft_msgs/Reply), port ``errors``: refused requests; alarms (aft_msgs/Alarm), port ``alarms``.
    Services: ~rebind (aft_msgs/Rebind)
    """
    MECHANISM = 'ad'
    WAIT_OUTPUTS = ('to_after', 'errors')

    def __init__(self):
        self.checks = assertions.load_all(param('request_assertions', config.name_list, []),
                                          rospy.resolve_name('~request_assertions'))
        if not self.checks and not param('reply_assertions', config.name_list, []):
            raise config.ConfigError('%s: Assertion & Duplex with no assertion at all (~request_assertions and '
                                     '~reply_assertions both empty) would check nothing: name at least one '
                                     '(package.module:function)' % rospy.get_name())
        super(AdBeforeNode, self).__init__(extra_ports=[PortSpec('to_after', PUBLISH, 'aft_msgs/Request'),
                                                        PortSpec('errors', PUBLISH, 'aft_msgs/Reply'),
                                                        PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')])

    def setup(self, timeout):
        self.ports.bind('to_after', 'bfr2aft')
        self.ports.bind('errors', 'aft2pro')
        self.ports.bind('alarms')
        return super(AdBeforeNode, self).setup(timeout)

    def handle(self, request):
        if self.checks:
            try:
                violations = assertions.check(self.checks, _app_request(request))
            except Exception as e:   # undecodable request: refused, not executed
                violations = [('decoding', str(e))]
            if violations:
                detail = '; '.join('request assertion %s violated: %s' % v for v in violations)
                alarm(self.ports, 'ad', 'assertion_violated', detail, request)
                self.ports.publish('errors', _error(request, detail))
                return None
        self.ports.publish('to_after', request)
        return request


class AdAfterNode(AfterNode):
    """A&D's After: checks the reply assertions on (request, response); a violated assertion turns
    the reply into an error reply and raises an alarm. It never lets an unchecked reply through.

    Parameters: ~reply_assertions (list of package.module:function, default none)
    Subscribes: prd2aft (aft_msgs/Reply), port ``inp``; bfr2aft (aft_msgs/Request), port ``requests``.
    Publishes: aft2pro (aft_msgs/Reply), port ``out``; alarms (aft_msgs/Alarm), port ``alarms``.
    Services: ~rebind (aft_msgs/Rebind)
    """
    MECHANISM = 'ad'

    def __init__(self):
        self.checks = assertions.load_all(param('reply_assertions', config.name_list, []),
                                          rospy.resolve_name('~reply_assertions'))
        super(AdAfterNode, self).__init__(extra_ports=[PortSpec('requests', SUBSCRIBE, 'aft_msgs/Request'),
                                                       PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm')],
                                          extra_callbacks={'requests': self._on_request})
        self.lock = threading.Lock()
        self.requests = {}   # key -> request, until its reply comes
        self.replies = {}    # key -> reply that came before its request

    def setup(self, timeout):
        self.ports.bind('requests', 'bfr2aft')
        self.ports.bind('alarms')
        return super(AdAfterNode, self).setup(timeout)

    def _on_request(self, request):
        k = key(request)
        with self.lock:
            reply = self.replies.pop(k, None)
            if reply is None:
                self.requests[k] = request
        if reply is not None:
            self.ports.publish('out', self._checked(request, reply))

    def handle(self, reply):
        k = key(reply)
        with self.lock:
            request = self.requests.pop(k, None)
            if request is None:
                self.replies[k] = reply    # checked when its request arrives
                return None
        return self._checked(request, reply)

    def _checked(self, request, reply):
        if reply.status != Reply.OK or not self.checks:
            return reply
        try:
            cls = service_class(request.service_type)
            args = (deserialize(cls._request_class, request.payload), deserialize(cls._response_class, reply.payload))
            violations = assertions.check(self.checks, *args)
        except Exception as e:   # an undecodable reply cannot be shown safe
            violations = [('decoding', str(e))]
        if not violations:
            return reply
        detail = '; '.join('reply assertion %s violated: %s' % v for v in violations)
        alarm(self.ports, 'ad', 'assertion_violated', detail, reply)
        return _error(reply, detail)
