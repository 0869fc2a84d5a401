"""A replica's side of the witness: its site's incarnation and calls with a deadline."""
import os
import threading
import time

import rospy
from aft_msgs.msg import Configuration
from aft_msgs.srv import Witness as WitnessSrv

from ..errors import AftError
from ..process_start import started
from ..site_guard import OWNERS_ENV, GuardError, parse_owners
from ..witness import Grant, Op
from .deadline import CallTimeout, Deadline
from .persistent_service import open_service

DEFAULT_WITNESS = '/aft/witness/request'


def configuration_topic(service):
    """The topic of the configurations the witness serving ``service`` publishes: its node's
    ``~configuration`` beside its ``~request`` (``/aft/witness/configuration`` for the default witness).
    Each replicated service on one ROS master has a witness of its own, and its nodes must hear that
    witness's configurations only: another service's name other sites, and would depose this one's."""
    return service.rsplit('/', 1)[0] + '/configuration' if '/' in service else 'configuration'


CONFIGURATION_TOPIC = configuration_topic(DEFAULT_WITNESS)


class WitnessUnreachable(AftError):
    """The witness did not answer: nothing may be assumed granted."""


def site_launcher_pid():
    """The pid of this node's site launcher: the first owner of AFT_SITE_OWNERS when set (a node an
    adaptation launched into a site, see aft_ftm.site_guard), else the parent process (the site's
    roslaunch). So a replacement After speaks to the witness as the same incarnation of its site."""
    owners = os.environ.get(OWNERS_ENV, '')
    if owners:
        try:
            return parse_owners(owners)[0].pid
        except GuardError:
            pass
    return os.getppid()


def boot_id(path='/proc/sys/kernel/random/boot_id'):
    """This boot of the machine (the kernel's random id, new at each boot), '' if it cannot be read."""
    try:
        with open(path) as f:
            return f.read().strip()
    except OSError:
        return ''


def incarnation(pid):
    """One start of a site: its launcher's pid and start time, on the boot clock, so that every process
    of the site (Recovery, the After, an After an adaptation starts later) tells the same one across a
    wall-clock step ('' if it is gone); and this boot's id: a machine that boots the same way again
    (systemd starting the site's launch with the same pid in the same 10 ms) told the witness the
    incarnation it had before, and a lone primary started again blank was told to serve (review of
    session 35)."""
    start = started(pid, zombie=True)
    return '' if start is None else '%d@%.2f@%s' % (pid, start, boot_id()[:8])


class WitnessClient(object):
    """Calls ``service`` (aft_msgs/Witness) for ``site`` over a persistent connection opened at set-up,
    each call limited to ``timeout`` (a frozen witness must not freeze the replica). A call needs no
    ROS master: the connection is open, and one that broke is opened again to the witness's last known
    address when the master cannot be asked."""

    def __init__(self, service, site, site_pid, timeout=1.0):
        self.service = service
        self.site = site
        self.incarnation = incarnation(site_pid)
        self.timeout = timeout
        self.deadline = Deadline('witness')
        self.proxy = None
        self.known = 0          # the newest epoch heard from the witness (told with every request)
        self.seen = {}          # epoch -> (primary, backup) heard for it (configurations and answers; the last 16)
        self._seen_lock = threading.Lock()

    def setup(self, timeout):
        try:
            self.proxy = open_service(self.service, WitnessSrv, timeout)
        except (rospy.ROSException, rospy.ServiceException) as e:
            rospy.logerr('%s: the witness %s is not available within %.1f s: %s', rospy.get_name(), self.service,
                         timeout, e)
            return False
        return True

    def request(self, op, peer='', peer_incarnation='', claim=False, epoch=0):
        """One request; returns a Grant, or raises WitnessUnreachable. ``epoch`` (ADMIT): the epoch the
        state transfer was made in."""
        try:
            answer = self.deadline.call(self._call, self.timeout, op, peer, peer_incarnation, claim, epoch)
        except CallTimeout as e:
            self.proxy = self.proxy.fresh()   # the call that timed out may still hold the old connection
            raise WitnessUnreachable('witness %s: %s' % (self.service, e))
        except (rospy.ServiceException, rospy.ROSException) as e:   # its connection is closed: opened again next
            raise WitnessUnreachable('witness %s: %s' % (self.service, e))
        self.known = max(self.known, answer.epoch)
        self._saw(answer.epoch, answer.primary, answer.backup)
        return Grant(answer.granted, answer.message, answer.epoch, answer.primary, answer.backup)

    def _saw(self, epoch, primary, backup):
        """Remember what epoch named; returns what it named before if that was something else (two
        configurations of one epoch, which only a witness whose record was rolled back, restored from
        an older copy, grants), else None."""
        with self._seen_lock:   # (the configuration thread and every caller of request())
            before = self.seen.setdefault(epoch, (primary, backup))
            while len(self.seen) > 16:
                del self.seen[min(self.seen)]
        return before if before != (primary, backup) else None

    def _call(self, op, peer, peer_incarnation, claim, epoch):
        return self.proxy(op=op.value, site=self.site, peer=peer, incarnation=self.incarnation,
                          peer_incarnation=peer_incarnation, claim=claim, epoch=epoch, known_epoch=self.known)

    def subscribe(self, callback, report=None):
        """callback(aft_msgs/Configuration) on every configuration of the witness's own node (the latest
        at once: latched; another sender's are refused, see :func:`from_witness_only`). A
        configuration older than one heard before means the witness lost or rolled back its record
        (restarted without its state file): it is told at once, with a STATUS saying the epoch heard,
        so that it grants nothing from then on (witness_behind), before a site that restarts claims it."""
        def on_configuration(conf):
            # Told at every older configuration, not once per epoch number: a witness restarted again
            # without its record publishes the same older epoch, and forgot it was told (review of the
            # witness, session 33). Configurations come only at changes and at a (re)start: no flood.
            diverged = self._saw(conf.epoch, conf.primary, conf.backup)
            if diverged:
                # Epoch e granted twice (review of the witness, session 33: a witness restored from an
                # older record granted e again to the other site; both served in e, and nothing noticed).
                # The witness is told it is behind e, so it grants nothing more until it is restored.
                rospy.logerr('%s: the witness names primary %r, backup %r for epoch %d, which named %r, %r before: '
                             'its record was rolled back; it is told so', rospy.get_name(), conf.primary,
                             conf.backup, conf.epoch, *diverged)
                self.known = max(self.known, conf.epoch + 1)
            if conf.epoch < self.known:
                threading.Thread(target=self._tell_behind, args=(conf.epoch,), daemon=True,
                                 name='witness-behind').start()
            self.known = max(self.known, conf.epoch)
            callback(conf)
        return rospy.Subscriber(configuration_topic(self.service), Configuration,
                                from_witness_only(self.service, on_configuration, report), tcp_nodelay=True)

    def _tell_behind(self, epoch):
        # (A configuration overtaken by a newer grant's answer comes older too: the witness then answers.)
        for _ in range(10):   # bounded: the connection to the witness's old process broke, and opens again
            try:
                self.request(Op.STATUS)
                return
            except WitnessUnreachable as e:
                if 'lost or rolled back' in str(e):   # told: it refuses everything now (witness_behind)
                    rospy.logerr('%s: the witness published epoch %d, older than epoch %d heard before: %s',
                                 rospy.get_name(), epoch, self.known, e)
                    return
                if rospy.is_shutdown():
                    return
                time.sleep(0.2)


def witness_node(service):
    """The node that offers a witness's service and publishes its configurations beside it:
    /NS/witness/request -> /NS/witness."""
    return service.rsplit('/', 1)[0] or '/'


def from_witness_only(service, callback, report=None):
    """callback wrapped so that it sees only the configurations the witness's own node published (the
    connection's caller id; a message handed over without one, as a unit test does, passes). Anyone
    may publish on the topic: one forged configuration with a higher epoch deposed a serving primary
    and made Recovery ask for a promotion with it as its known epoch, after which the witness took
    its record for behind and granted nothing (review of session 41). Under TLS a node's name is
    bound to its party, so the caller id is the sender's; without it this keeps out a misconfigured
    or careless publisher, not a determined one. A refused sender is reported once (``report``:
    detail -> None, e.g. an alarm; else logged)."""
    expected = witness_node(service)
    told = set()

    def guarded(conf):
        sender = (getattr(conf, '_connection_header', None) or {}).get('callerid')
        if sender is None or sender == expected:
            callback(conf)
            return
        if sender not in told and len(told) < 64:
            told.add(sender)
            detail = ('a configuration of epoch %d (primary %r, backup %r) came from %s, not from the witness %s: '
                      'refused' % (conf.epoch, conf.primary, conf.backup, sender, expected))
            if report is not None:
                report(detail)
            else:
                rospy.logerr('%s: %s', rospy.get_name(), detail)
    return guarded


def follow_site_role(site_role, witness, report=None, on_change=None):
    """Keep an aft_ftm.recovery.SiteRole up to date with the configurations of the witness serving
    ``witness`` (a replica's node, ``site_role.site`` set), then call on_change(epoch, primary, backup)
    if given; returns the subscriber, or None outside a replica or without a witness ('')."""
    if not site_role.site or not witness:
        return None

    def heard(c):
        site_role.on_configuration(c.epoch, c.primary, c.backup)
        if on_change is not None:
            on_change(c.epoch, c.primary, c.backup)
    return rospy.Subscriber(configuration_topic(witness), Configuration, from_witness_only(witness, heard, report),
                            tcp_nodelay=True)


__all__ = ['Op', 'WitnessClient', 'follow_site_role', 'from_witness_only', 'witness_node', 'WitnessUnreachable', 'incarnation', 'site_launcher_pid',
           'CONFIGURATION_TOPIC', 'DEFAULT_WITNESS', 'configuration_topic']
