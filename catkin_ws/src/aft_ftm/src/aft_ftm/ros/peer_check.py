"""A replica node asks its site's crash detector whether the peer may take over now
(aft_msgs/PeerStatus), before a hang of its server fail-stops the site (aft_ftm.recovery.SiteRole)."""
import threading
import time

import rosgraph
import rospy
from aft_msgs.srv import PeerStatus

from ..recovery import SiteRole
from .deadline import CallTimeout, Deadline
from .persistent_service import PersistentService


class HangRule(object):
    """What a hang of a replica node's server does (aft_ftm.recovery.SiteRole.on_hang): by its site's
    role (``site_role``, kept up to date from the witness's configurations by
    witness_client.follow_site_role) and its peer's liveness (the site's crash detector, asked)."""

    def __init__(self, site, detector=None):
        self.site_role = SiteRole(site)
        self.peer = PeerCheck(site, detector) if site else None

    def start(self):
        """At the node's set-up: the connection to the detector, opened on a thread of its own."""
        if self.peer is not None:
            threading.Thread(target=self.peer.connect, name='peer-status', daemon=True).start()

    def on_hang(self):
        return self.site_role.on_hang(self.peer.alive if self.peer else None)

    def why_wait(self):
        return self.site_role.why_wait(self.peer.why if self.peer else '')


class PeerCheck(object):
    """``alive()``: True, False, or None when the detector does not answer within ``timeout``; ``why``:
    the last answer in words. A site whose launch runs no crash detector (none registered under
    ``detector``) keeps the rule from before the detector was asked: the peer is assumed there.

    ``connect()`` (at set-up, on a thread of its own) opens the connection once the detector is up, so
    that it is asked without the ROS master (a persistent connection remembers the address), as the
    failover itself is. Thread-safe; a question left unanswered (a frozen detector) is not asked again
    until it returns: meanwhile the answer is None at once, with no new thread."""

    def __init__(self, site, detector=None, timeout=0.5):
        self.service = (detector or '/%s/crash_detector' % site) + '/peer_status'
        self.timeout = timeout
        self.proxy = PersistentService(self.service, PeerStatus)
        self.deadline = Deadline('peer-status', exclusive=True)
        self.lock = threading.Lock()
        self.why = 'not asked yet'

    def connect(self, period=0.5, patience=120.0):
        """Open the connection once the detector offers the service (until it does, shutdown, or
        patience seconds: then it is opened at the first question)."""
        given_up = time.monotonic() + patience
        while not rospy.is_shutdown() and time.monotonic() < given_up:
            proxy = PersistentService(self.service, PeerStatus)
            try:
                proxy.connect()
            except (rospy.ServiceException, rospy.ROSException, OSError):
                time.sleep(period)
                continue
            with self.lock:
                self.proxy = proxy
            return True
        return False

    def alive(self):
        return self._question(self._ask)[0]

    def heard(self, site):
        """(heard, why): does the detector hear the site ``site`` (its beats within its timeout, even after
        it was declared failed: the site runs)? True, False, or None when unknown (no answer in time, or
        the detector watches another site). A site that runs no crash detector keeps the rule from
        before the gate: True, as ``alive`` assumes the peer there."""
        return self._question(lambda: self._ask_heard(site))

    def _question(self, ask):
        """(answer, why) of ask() within ``timeout``; ``why`` is kept as the last answer in words."""
        with self.lock:
            try:
                answer, self.why = self.deadline.call(ask, self.timeout)
            except CallTimeout:   # CallPending too: the last question has not returned yet
                self.proxy = self.proxy.fresh()
                self.why = 'the crash detector (%s) did not answer within %.1f s' % (self.service, self.timeout)
                return None, self.why
            return answer, self.why

    def _call(self):
        """(the detector's answer, ''), or (None, why) and whether a detector is registered at all."""
        try:
            return self.proxy(), '', True
        except (rospy.ServiceException, rospy.ROSException, OSError) as e:
            self.proxy = self.proxy.fresh()
            if not self._registered():
                return None, 'no crash detector offers %s' % self.service, False
            return None, 'the crash detector (%s) cannot be asked: %s' % (self.service, e), True

    def _ask(self):
        answer, why, registered = self._call()
        if not registered:
            return True, why + ': the peer is assumed able to take over'
        if answer is None:
            return None, why
        return answer.alive, answer.why

    def _ask_heard(self, site):
        answer, why, registered = self._call()
        if not registered:
            return True, why + ': the joiner is assumed heard'
        if answer is None:
            return None, why
        if answer.peer != site:
            return None, 'the crash detector (%s) watches %r, not %s' % (self.service, answer.peer, site)
        if answer.heard:
            return True, 'site %s heard by %s' % (site, self.service)
        return False, ('%s hears no beat of site %s within its timeout, or that site announced its fail-stop (%s)'
                       % (self.service, site, answer.why))

    def _registered(self):
        try:
            rosgraph.Master(rospy.get_name()).lookupService(self.service)
        except rosgraph.MasterError:
            return False
        except Exception:   # the master cannot be reached: no conclusion, so not "no detector"
            return True
        return True
