"""What the After of a duplex replica (PBR or LFR) does with the outside world beside its mechanism:
asking the witness, raising alarms once, quiescing its Protocol for a state transfer, fail-stop."""
import threading
import time

import rospy
from aft_msgs.srv import Suspend

from ..checkpoint import UncheckedAdmission
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..suspension import MAX_LEASE
from ..witness import Grant, Op
from .alarms import alarm
from .deadline import CallTimeout, Deadline
from .fail_stop import fail_stop
from .peer_check import PeerCheck
from .witness_client import WitnessClient, WitnessUnreachable


# The ports every duplex replica's After has beside its mechanism's: joins, fail-stop, alarms.
SIDE_PORTS = (PortSpec('join', PUBLISH, 'aft_msgs/Join'),
              PortSpec('join_requests', SUBSCRIBE, 'aft_msgs/Join'),
              PortSpec('fail_stop', PUBLISH, 'aft_msgs/Failure'),
              PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm'))


class ReplicaSide(object):
    """One replica After's links: ``witness`` the witness's service ('' : none), ``protocol`` its
    Protocol's node name ('' : never suspended), ``mechanism`` the alarms' mechanism field."""

    def __init__(self, ports, mechanism, site, site_pid, witness, protocol, state_timeout):
        self.ports = ports
        self.mechanism = mechanism
        self.site = site
        self.state_timeout = state_timeout
        self.witness = WitnessClient(witness, site, site_pid) if witness else None
        self.protocol = protocol
        self.protocol_calls = Deadline('protocol')
        self._protocol_proxies()
        self.told = set()           # alarms raised once per kind and key
        # This site's crash detector, asked before a joiner of the peer site is admitted.
        self.detector = PeerCheck(site) if site else None
        # The admission of a joiner this detector could not vouch for, said (and not once per re-ask).
        self.unchecked = UncheckedAdmission(lambda detail: self.tell('admission_unchecked', detail))
        self.deciding = threading.Lock()   # one witness decision (or state transfer) at a time

    def _protocol_proxies(self):
        self.protocol_suspend = rospy.ServiceProxy(self.protocol + '/suspend', Suspend, persistent=True) \
            if self.protocol else None
        self.protocol_resume = rospy.ServiceProxy(self.protocol + '/resume', Suspend, persistent=True) \
            if self.protocol else None

    @property
    def name(self):
        return rospy.get_name()

    def tell(self, kind, detail, key=None):
        """An alarm, once per (kind, key) when a key is given: a flood of stray messages raises one."""
        if key is not None:
            if (kind, key) in self.told:
                return
            self.told.add((kind, key))
        alarm(self.ports, self.mechanism, kind, detail)

    def ask(self, op, **kwargs):
        """The witness's Grant (granted locally without a witness), or None if it cannot be reached
        (an alarm says so: the caller asks again later)."""
        if self.witness is None:
            return Grant(True, 'no witness', 0, self.site, '')
        try:
            return self.witness.request(op, **kwargs)
        except WitnessUnreachable as e:
            alarm(self.ports, self.mechanism, 'witness_unreachable', '%s cannot reach the witness (%s): %s not '
                  'done, replies stay held and it is asked again' % (self.site or self.name, e, op.name))
            return None

    def joiner_unheard(self, joiner):
        """Why the site ``joiner`` must not be admitted yet: this site's crash detector does not hear it
        (its beats stopped, or it announced its fail-stop: a site stopping, whose After still joins).
        Admitted, it would be watched afresh and declared failed a timeout later, over and over. None
        if it is heard, or if that cannot be known (no detector here, no answer): then as before."""
        if self.detector is None:
            return None
        heard, why = self.detector.heard(joiner)
        if heard is None:
            self.unchecked.say(joiner, why, time.monotonic())
        return why if heard is False else None

    def join_waits(self, gate, lock, join):
        """Whether a join request (aft_msgs/Join) is left unanswered for now: its site is not heard by this
        site's crash detector (gate: an aft_ftm.checkpoint.AdmissionGate, kept under lock). The joiner asks
        again; once the gate gives the join up, that is said (join_failed)."""
        unheard = self.joiner_unheard(join.site)
        with lock:
            admit, give_up = gate.decide((join.site, join.incarnation), unheard, time.monotonic())
        if give_up:
            self.tell('join_failed', '%s asks to join, but is not admitted: %s; it asks again' % (join.site, give_up))
        return not admit

    def alone(self, decision, *args):
        """Run decision(*args) unless another one is under way (then do nothing: the caller's timer or
        the peer asks again). Returns whether it ran."""
        if not self.deciding.acquire(blocking=False):
            return False
        try:
            decision(*args)
        finally:
            self.deciding.release()
        return True

    def exclusion(self, deposed):
        """Ask the witness to exclude this primary's peer: its Grant if granted; None if not, after an
        alarm (unreachable: asked again later) or deposed(why) (refused: this replica was deposed)."""
        grant = self.ask(Op.EXCLUDE)
        if grant is not None and not grant.granted:
            deposed(grant.message)
            return None
        return grant

    def quiesce_protocol(self, suspend):
        """Suspend (quiescent: nothing executing, new requests held) or resume the Protocol; False with
        a ``join_failed`` alarm if it cannot be done."""
        if self.protocol_suspend is None:
            return True
        try:
            if suspend:
                request = dict(timeout=self.state_timeout, lease=min(MAX_LEASE, max(2.0, 2 * self.state_timeout)))
                answer = self.protocol_calls.call(lambda: self.protocol_suspend(**request), self.state_timeout + 1.0)
            else:
                answer = self.protocol_calls.call(self.protocol_resume, self.state_timeout)
        except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
            answer = None
            error = str(e)
            self._protocol_proxies()
        else:
            error = answer.message
        if answer is None or not answer.success:
            self.tell('join_failed', 'cannot %s the Protocol for a state transfer: %s'
                      % ('suspend' if suspend else 'resume', error))
            if suspend:
                # A suspension that went through after the call gave up would hold the Protocol's
                # requests (and any start) until its lease ran out: resumed now, whatever happened.
                try:
                    self.protocol_calls.call(self.protocol_resume, self.state_timeout)
                except Exception:   # (a timeout, no proxy): it resumes by itself when its lease runs out, with an alarm
                    pass
            return False
        return True

    def hold_protocol(self, lease):
        """The Protocol suspended by quiesce_protocol kept suspended ``lease`` seconds more (its lease
        renewed): None if it is, else why not (its lease ran out and it resumed by itself, or it cannot
        be reached). A state transfer checks it before it counts on the Protocol having run nothing."""
        if self.protocol_suspend is None:
            return None
        try:
            answer = self.protocol_calls.call(lambda: self.protocol_suspend(renew=True, lease=lease),
                                              self.state_timeout)
        except (CallTimeout, rospy.ServiceException, rospy.ROSException) as e:
            self._protocol_proxies()
            return 'the Protocol cannot be reached: %s' % e
        return None if answer.success else answer.message

    def fail_stop(self, problem):
        """This replica falls silent: its site fail-stops (Recovery's peer takes over), or, outside a
        site, the node stops."""
        if self.site:
            fail_stop(self.ports, self.site, problem)
        else:
            rospy.logfatal('%s: %s: stopping this replica', self.name, problem)
            rospy.signal_shutdown(problem)
