"""The state-manager interface a replicated server offers (paper section 5.2.3)."""
import threading

import rospy
from aft_msgs.srv import GetState, GetStateDelta, GetStateDeltaResponse, GetStateResponse, SetState, SetStateResponse

from ..errors import StateError


class StateManager(object):
    """Mixin for a server: implement get_state() -> bytes and set_state(bytes) (raising
    StateError on a bad state, leaving the state unchanged), then call
    advertise_state_services(). Hold ``self.state_lock`` while handling a request so that a
    state is never captured or replaced half-way through one.

    A server that knows what changed in its state may also implement state_changes(since) ->
    aft_ftm.delta.ServerChanges (the runs since the version ``since`` it named earlier, or the
    whole state when it does not know that version): it is then offered as ``<get_state>_delta``,
    and PBR's primary asks it instead of the whole state after each request.

    Services:
        ~get_state (aft_msgs/GetState), ~set_state (aft_msgs/SetState)
        ~get_state_delta (aft_msgs/GetStateDelta): where state_changes is implemented
    """

    def advertise_state_services(self, get_name='~get_state', set_name='~set_state'):
        if not hasattr(self, 'state_lock'):
            self.state_lock = threading.RLock()
        changes = getattr(self, 'state_changes', None)   # a server may set it None to not offer it
        if changes is not None and getattr(changes, '__func__', None) is not StateManager.state_changes:
            # Advertised first: once get_state is seen, its _delta is there too.
            self._delta_srv = rospy.Service(get_name + '_delta', GetStateDelta, self._handle_get_state_delta)
        self._get_srv = rospy.Service(get_name, GetState, self._handle_get_state)
        self._set_srv = rospy.Service(set_name, SetState, self._handle_set_state)

    def _handle_get_state(self, _req):
        with self.state_lock:
            return GetStateResponse(state=self.get_state())

    def _handle_get_state_delta(self, req):
        with self.state_lock:
            changes = self.state_changes(req.since)
        if changes.state is not None:
            return GetStateDeltaResponse(version=changes.version, whole=True, state=changes.state,
                                         size=len(changes.state))
        return GetStateDeltaResponse(
            version=changes.version, whole=False, starts=[r[0] for r in changes.runs],
            ends=[r[1] for r in changes.runs], lengths=[len(r[2]) for r in changes.runs],
            data=b''.join(bytes(r[2]) for r in changes.runs), size=changes.size, crc=changes.crc)

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

    def state_changes(self, since):
        raise NotImplementedError
