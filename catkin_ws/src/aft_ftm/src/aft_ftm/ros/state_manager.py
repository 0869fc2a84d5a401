"""The state-manager interface a replicated server offers (paper section 5.2.3)."""
import threading

import rospy
from aft_msgs.srv import GetState, GetStateResponse, SetState, SetStateResponse

from ..errors import StateError


class StateManager(object):
    """Mixin for a server: implement get_state() -> bytes and set_state(bytes) (raising
    StateError on a bad state, leaving the state unchanged), then call
    advertise_state_services(). Hold ``self.state_lock`` while handling a request so that a
    state is never captured or replaced half-way through one.

    Services:
        ~get_state (aft_msgs/GetState), ~set_state (aft_msgs/SetState)
    """

    def advertise_state_services(self, get_name='~get_state', set_name='~set_state'):
        if not hasattr(self, 'state_lock'):
            self.state_lock = threading.RLock()
        self._get_srv = rospy.Service(get_name, GetState, self._handle_get_state)
        self._set_srv = rospy.Service(set_name, SetState, self._handle_set_state)

    def _handle_get_state(self, _req):
        with self.state_lock:
            return GetStateResponse(state=self.get_state())

    def _handle_set_state(self, req):
        with self.state_lock:
            try:
                self.set_state(req.state)
            except StateError as e:
                rospy.logerr('%s: state refused: %s', rospy.get_name(), e)
                return SetStateResponse(success=False, message=str(e))
        return SetStateResponse(success=True, message='')

    def get_state(self):
        raise NotImplementedError

    def set_state(self, data):
        raise NotImplementedError
