"""A software fault injector for any ROS service: relays calls to the real server and corrupts
results (bit flip, offset, stuck value) at random or on command."""
import threading

import rospy
from aft_msgs.msg import Alarm
from aft_msgs.srv import InjectFault, InjectFaultResponse

from .. import config
from ..corruption import MODES, Corruptor
from ..errors import ConfigError
from .envelope import service_class
from .params import param


class ServiceFaultInjectorNode(object):
    """Offers ``service`` with the server's type, calls ``server`` and passes its response on,
    corrupted with ~probability or for the next N calls asked through ~inject. Application code
    is not changed: remap the caller (e.g. a Proceed) to ``service``.

    Parameters:
        ~service_type (str, required); ~mode (bitflip | offset | stuck, default bitflip);
        ~probability (float in [0, 1], default 0); ~magnitude (float, default 1: the offset);
        ~seed (int, optional)
    Services: service (~service_type), ~inject (aft_msgs/InjectFault)
    Services called: server (~service_type)
    Publishes: ~injected (aft_msgs/Alarm): one per corrupted result
    """

    def __init__(self):
        self.service_type = param('service_type', config.service_type, required=True)
        self.cls = service_class(self.service_type)
        probability = param('probability', config.number_in(0.0, 1.0), 0.0)
        try:
            self.corruptor = Corruptor(param('mode', config.choice(*MODES), 'bitflip'),
                                       probability, param('magnitude', config.number, 1.0),
                                       param('seed', config.non_negative_int, None))
        except ConfigError as e:
            raise ConfigError('%s: %s' % (rospy.get_name(), e))
        self.lock = threading.Lock()

    def setup(self, timeout):
        try:
            rospy.wait_for_service('server', timeout)
        except rospy.ROSException:
            rospy.logerr('%s: server %s not available', rospy.get_name(), rospy.resolve_name('server'))
            return False
        self.server = rospy.ServiceProxy('server', self.cls, persistent=True)
        self.injected = rospy.Publisher('~injected', Alarm, queue_size=100)
        rospy.Service('~inject', InjectFault, self._on_inject)
        rospy.Service('service', self.cls, self._on_call)
        return True

    def _on_inject(self, req):
        try:
            with self.lock:
                if req.field:   # check the field now, not when the next result comes
                    self.corruptor.corrupt(self.cls._response_class(), 'offset', 1, req.field)
                self.corruptor.arm(req.count, req.mode, req.magnitude if req.mode == 'offset' else None, req.field)
        except ConfigError as e:
            return InjectFaultResponse(success=False, message=str(e))
        return InjectFaultResponse(success=True, message='the next %d results will be corrupted' % req.count)

    def _on_call(self, req):
        response = self.server(req)
        with self.lock:
            before = self.corruptor.injected
            out = self.corruptor.relay(response)
            corrupted = self.corruptor.injected > before
        if corrupted:
            self.injected.publish(Alarm(source=rospy.get_name(), mechanism='injector', kind='value_fault_injected',
                                        detail='result corrupted', stamp=rospy.Time.now()))
        return out
