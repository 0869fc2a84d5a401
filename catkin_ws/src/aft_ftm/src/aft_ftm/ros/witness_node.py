"""The witness node: the configuration record of aft_ftm.witness, offered as a service."""
import threading
import time

import rospy
from aft_msgs.msg import Alarm, Configuration
from aft_msgs.srv import Witness as WitnessSrv, WitnessResponse

from .. import config, health
from ..errors import ConfigError
from ..state_store import StateStore
from ..witness import Op, Witness, WitnessBehind, speaks_for
from . import tls_transport
from .diagnostics import Diagnostics


class WitnessNode(object):
    """Grants each configuration epoch to at most one primary (see aft_ftm.witness). Run it on the
    clients' machine or a third one, never on a replica's: a replica that loses its peer must still
    be able to reach it, and a site that cannot reach it stops serving rather than guess.

    Parameters:
        ~initial_primary (str, default ''): the site that serves first; '' : the first site that
            registers claiming it (replica.launch role:=primary).
        ~state_file (str, default ''): where the record is kept (written, with a checksum, before
            each grant is answered), so that a witness that restarts never grants an epoch twice.
            '' keeps it in memory only: do not restart such a witness while replicas run. A file
            that exists but is corrupt stops the witness at start (exit 2) rather than forget.
    Services:
        ~request (aft_msgs/Witness)
    Publishes:
        ~configuration (aft_msgs/Configuration, latched): the current configuration, on every change.
        /aft/alarms (aft_msgs/Alarm): ``witness witness_behind`` once a caller has seen a newer epoch than
            the record (lost or rolled back): every request is then refused with a ServiceException.
    """

    def __init__(self):
        from .params import param
        initial = param('initial_primary', config.optional_name, '')
        path = param('state_file', config.optional_name, '')
        store = StateStore(path, check=self._check) if path else None
        try:
            self.witness = Witness(initial, store)   # the record read once (Witness._load)
        except ConfigError as e:
            raise ConfigError('witness state file %s: %s' % (path, e))
        self.persistent = store is not None
        self.lock = threading.Lock()
        self.diagnostics = None
        self.told_behind = 0
        self.forged_at = {}   # caller -> when its last refused request was alarmed
        self.unsaved = None   # why the record could not be saved at the last request that changed it

    @staticmethod
    def _check(state):
        if not isinstance(state.get('epoch'), int) or state['epoch'] < 0:
            return 'epoch %r' % (state.get('epoch'),)
        if not isinstance(state.get('incarnations'), dict):
            return 'incarnations %r' % (state.get('incarnations'),)
        return None

    def setup(self, timeout):
        self.alarms = rospy.Publisher('/aft/alarms', Alarm, queue_size=10)
        self.publisher = rospy.Publisher('~configuration', Configuration, queue_size=10, latch=True)
        self._publish()
        rospy.Service('~request', WitnessSrv, self._on_request)
        self.diagnostics = Diagnostics(self._health)
        rospy.loginfo('%s: ready at epoch %d (%s)', rospy.get_name(), self.witness.epoch, self.witness.reason)
        return True

    def _forged_told(self, caller):
        """Whether a refused request of caller is to be alarmed now: once per caller every 10 s (a
        flood of them is one alarm), at most 256 callers remembered."""
        told = self.forged_at
        now = time.monotonic()
        if now - told.get(caller, -1e9) < 10.0:
            return False
        if len(told) >= 256:
            told.clear()
        told[caller] = now
        return True

    def _health(self):
        with self.lock:
            w = self.witness
            return health.witness(w.epoch, w.primary, w.backup, w.reason, self.persistent, w.behind, self.unsaved)

    def _publish(self):
        w = self.witness
        self.publisher.publish(Configuration(epoch=w.epoch, primary=w.primary, backup=w.backup, reason=w.reason,
                                             stamp=rospy.Time.now()))

    def _on_request(self, req):
        try:
            op = Op(req.op)
        except ValueError:
            with self.lock:   # (outside it, an epoch half made: e+1 paired with the old primary and backup)
                return WitnessResponse(granted=False, message='unknown operation %d' % req.op,
                                       epoch=self.witness.epoch, primary=self.witness.primary,
                                       backup=self.witness.backup)
        caller = (getattr(req, '_connection_header', None) or {}).get('callerid')
        if caller is not None and tls_transport.active():   # (a caller id is its sender's only under TLS)
            with self.lock:
                refused = speaks_for(op, req.site, caller, req.known_epoch, self.witness.epoch)
                if refused and self._forged_told(caller):
                    rospy.logerr('%s: %s', rospy.get_name(), refused)
                    self.alarms.publish(Alarm(source=rospy.get_name(), mechanism='witness', kind='forged_request',
                                              detail=refused + ': refused, nothing changed', stamp=rospy.Time.now()))
                if refused:
                    return WitnessResponse(granted=False, message=refused, epoch=self.witness.epoch,
                                           primary=self.witness.primary, backup=self.witness.backup)
        with self.lock:
            before, saves = self.witness.epoch, self.witness.saves
            try:
                grant = self.witness.request(op, req.site, req.incarnation, req.peer, req.peer_incarnation,
                                             req.claim, req.epoch, req.known_epoch)
            except WitnessBehind as e:   # lost or rolled back: nothing is granted, and it is said
                if self.told_behind != self.witness.behind:
                    self.told_behind = self.witness.behind
                    rospy.logerr('%s: %s', rospy.get_name(), e)
                    self.alarms.publish(Alarm(source=rospy.get_name(), mechanism='witness', kind='witness_behind',
                                              detail=str(e), stamp=rospy.Time.now()))
                raise rospy.ServiceException(str(e))
            except OSError as e:   # the record could not be saved: nothing was granted or changed
                why = '%s could not save its record (%s): %s of %s not granted, nothing changed; ask again' % (
                    rospy.get_name(), e, op.name, req.site)
                rospy.logerr(why)
                if self.unsaved is None:   # the callers only see the witness unreachable: said here, once
                    self.alarms.publish(Alarm(source=rospy.get_name(), mechanism='witness', kind='witness_unsaved',
                                              detail=why, stamp=rospy.Time.now()))
                self.unsaved = str(e)
                raise rospy.ServiceException(why)
            if self.witness.saves != saves:
                self.unsaved = None   # saved again
            if self.witness.epoch != before:
                self._publish()
        log = rospy.loginfo if grant.granted else rospy.logwarn
        if op != Op.STATUS:
            log('%s: %s %s: %s (%s)', rospy.get_name(), op.name, req.site, 'granted' if grant.granted else 'refused',
                grant.message)
        return WitnessResponse(granted=grant.granted, message=grant.message, epoch=grant.epoch,
                               primary=grant.primary, backup=grant.backup)
