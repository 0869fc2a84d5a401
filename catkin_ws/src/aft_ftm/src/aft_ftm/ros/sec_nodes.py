"""SEC (paper section 5.3.2): a certification authority, and gates that cipher and sign requests
and replies between the client's Proxy and the server's FTM (SEC_C and SEC_S)."""
import collections
import json
import os
import threading
import time

import rospy
from aft_msgs.msg import CertificateStatus, Reply, Request
from aft_msgs.srv import Certificate, CertificateResponse, ReplayFloors, ReplayFloorsResponse

from .. import config, health, replay_log, sec_policy, security
from ..change_model import SEC_UNAVAILABLE
from ..health import Level, Report
from ..ports import PUBLISH, SUBSCRIBE, PortSpec
from ..protocol import Role
from ..recovery import SiteRole
from . import tls_transport
from .alarms import alarm
from .diagnostics import Diagnostics
from .fail_stop import fail_stop
from .params import param
from .persistent_service import open_service
from .ports import Ports, wait_for_connections
from .protocol_node import ROLES
from .proxy_node import REQUEST_QUEUE as REMOTE_QUEUE
from .witness_client import follow_site_role


class CertificationAuthorityNode(object):
    """Certifies the public keys of the parties it knows (files <party>.pub next to its ca.key), with
    a serial number and an expiry in its own time, and publishes its signed status (its time, the
    revoked serials) every ~status_period (security.Issuer, security.CertificateBook).

    Parameters: ~keys_dir (str, required), ~parties (list of party names, required),
        ~validity (float, 86400 s): a certificate's life; renewed past half of it,
        ~rotation_overlap (float, 10 s): a rotated key's old certificate stays valid this long,
        ~status_period (float, 0.5 s): how often the status is published, the key files re-read (a
            changed .pub is a key rotation: the old certificate is revoked) and the revocations re-read,
        ~revocations (str, <keys_dir>/revoked.yaml): ``revoked: [party, ...]``, written by the operator
            (its file permissions are its authentication); a missing file revokes nothing, a malformed
            one changes nothing (logged, naming the problem).
    State: <keys_dir>/ca_state.json (security.Issuer.state): the revoked and retiring serials, every
        serial issued and not expired with its expiry, the keys certified, the status number
        reserved; read at start (so a party revoked or rotated after a restart, or while the CA was
        down, has its older certificates revoked too, and the statuses stay newer whatever the clock
        did); a corrupt one stops the CA, naming the file and the entry.
    Services: ~certificate (aft_msgs/Certificate)
    Publishes: ~status (aft_msgs/CertificateStatus, latched)
    """

    def __init__(self):
        self.keys_dir = param('keys_dir', config.non_empty_str, required=True)
        self.parties = param('parties', config.some_names, required=True)
        self.status_period = param('status_period', config.positive_float, 0.5)
        self.revocations = param('revocations', config.non_empty_str, os.path.join(self.keys_dir, 'revoked.yaml'))
        self.issuer = security.Issuer(security.read_party(self.keys_dir, 'ca'),
                                      param('validity', config.positive_float, 86400.0),
                                      param('rotation_overlap', config.positive_float, 10.0))
        self.lock = threading.Lock()
        self.revocations_seen = None
        # The revoked serials, the serials issued and the status number outlive a restart of the CA.
        self.state_path = os.path.join(self.keys_dir, 'ca_state.json')
        self.saved = None
        if os.path.exists(self.state_path):
            try:
                with open(self.state_path) as f:
                    self.issuer.restore(json.load(f))
            except (OSError, ValueError) as e:
                raise config.ConfigError('the CA state %s cannot be used (%s): move it away to start afresh '
                                         '(the revocations and serials it held are then lost)' % (self.state_path, e))
        self._reload()

    def setup(self, timeout):
        self.status_pub = rospy.Publisher('~status', CertificateStatus, queue_size=1, latch=True)
        rospy.Service('~certificate', Certificate, self._on_certificate)
        self._publish_status()
        threading.Thread(target=self._loop, name='ca-status', daemon=True).start()
        rospy.loginfo('%s: certifying %s', rospy.get_name(), ', '.join(sorted(self.parties)))
        return True

    def _reload(self):
        """The parties' public keys (a changed one is a rotation) and the revocations file."""
        for name in self.parties:
            box, verify = security.read_public(self.keys_dir, name)
            with self.lock:
                rotated = self.issuer.set_keys(name, box, verify, time.time())
            if rotated:
                rospy.logwarn('%s: the keys of %s changed: a new certificate; the old one is revoked in %.1f s',
                              rospy.get_name(), name, self.issuer.overlap)
        try:
            barred = sec_policy.load_revocations(self.revocations)
        except config.ConfigError as e:
            if str(e) != self.revocations_seen:
                self.revocations_seen = str(e)
                rospy.logerr('%s: %s (the revocations in force are kept)', rospy.get_name(), e)
            return
        self.revocations_seen = None
        with self.lock:
            newly = self.issuer.bar(barred)
        if newly:
            rospy.logwarn('%s: revoked: %s', rospy.get_name(), ', '.join(newly))

    def _publish_status(self):
        with self.lock:
            ca_time, seq, revoked, signature = self.issuer.status(time.time())
            state = self.issuer.state()
        if state != self.saved:
            try:
                temporary = self.state_path + '.tmp'
                with open(temporary, 'w') as f:
                    json.dump(state, f)
                os.replace(temporary, self.state_path)
                self.saved = state
            except OSError as e:
                rospy.logerr_throttle(10.0, '%s: the CA state cannot be saved in %s: %s' % (rospy.get_name(),
                                                                                          self.state_path, e))
        self.status_pub.publish(CertificateStatus(ca_time=ca_time, seq=seq, revoked=revoked, signature=signature))

    def _loop(self):
        while not rospy.is_shutdown():
            time.sleep(self.status_period)
            try:
                self._reload()
            except config.ConfigError as e:   # a key file unreadable meanwhile: the last keys stay
                rospy.logerr_throttle(10.0, '%s: %s' % (rospy.get_name(), e))
            self._publish_status()

    def _on_certificate(self, req):
        try:
            with self.lock:
                cert, signature = self.issuer.certificate(req.party, time.time())
        except security.Rejected as e:
            return CertificateResponse(found=False, message=str(e))
        return CertificateResponse(found=True, box_public=cert.box_public, verify_public=cert.verify_public,
                                   serial=cert.serial, not_after=cert.not_after, signature=signature)


class SecGateNode(object):
    """SEC_C (~side client) or SEC_S (~side server).

    Client side: ciphers each request of the Proxy for ~server_party and signs it; checks and
    deciphers the replies. Server side: checks each request's signature against the sender's
    certified key, its signed header against the envelope (every field that affects processing:
    security.REQUEST_FIELDS, the party it is for, its direction and destination), that its
    ciphertext was sealed by its signer under that header, that its sender may speak for its origin
    (security.OriginBinding, from ~policy), and that it is not a replay; deciphers it for the
    Protocol; ciphers and signs the reply (security.REPLY_FIELDS) for the party bound to its
    origin. Rejected messages are dropped with an alarm (a forged message has nobody waiting for
    it); a client re-sends a request whose reply was rejected. A client gate passes over, without
    an alarm, a reply signed for another party (replies share one topic): that party's gate checks it.

    At set-up a gate waits (within the set-up's time) for the CA's first status: until one comes it
    takes no certificate (a revoked or expired one would pass), and refuses what needs one
    (``ca_unreachable``). Started without TLS (no AFT_TLS_DIR), it raises ``tls sec_without_tls``
    once and its diagnostics stay WARN: its plaintext side (the Protocol's or the Proxy's topics)
    is open to every node of the graph, which may read what it deciphers and publish requests that
    never cross SEC; mutual TLS closes it (README, Security).

    Parameters:
        ~side (client | server), ~party (this side's party name), ~keys_dir (its key files),
        ~ca_public (path of ca.pub, the CA's public keys: known to all), ~server_party (client side),
        ~role (server side: primary | backup; a backup starts with requests_in unbound: the replica's
            Recovery binds it at its set-up, so that a failover needs no new subscription)
        ~policy (server side, path, default none): the access-control policy file (aft_ftm.sec_policy):
            which party may send as which origin. Without it each origin is bound to the first party
            whose verified request used it (a warning in the log and in the diagnostics).
        ~party_quota (int, 10000; 0: none): server side, the requests one party may have outstanding
            (not confirmed by its Proxies), over all its origins; past it its new ones are dropped
            (``party_quota``, one alarm while it stays there) until its older calls are confirmed. Keep
            parties x quota within the Protocol's ~cache_capacity: then no party can fill the cache
        ~ca_timeout (float, 2 s): the longest wait for the CA's answer about a certificate; past it the
            message that needed it is refused (``ca_unreachable``) and sent again by its Proxy
        ~ca_silent_after (float, 3 s): the CA's status unheard this long raises ``ca_silent`` (revocations
            cannot reach this gate meanwhile)
        ~destination (str, default: the resolved name of the requests' shared topic: requests_out on the
            client side, requests_in on the server side, e.g. /ftm/pxy2pro): the service the requests
            and replies are signed for (``dest``); a message signed for another is refused
            (``misaddressed``). The client's and the server's gates must name the same. A message
            signed with no destination (a signer that names none) is taken, and counted.
        ~replay_log (str, server side, default <keys_dir>/replay/<this node's name, / as .>.log; 'none':
            none): the replay floors on stable storage (aft_ftm.replay_log). Each verified request's
            watermark and id are there before it goes on; a gate started again (its site re-launched,
            the whole deployment started again) refuses every request the earlier runs of this gate
            let through: below a watermark as a replay (told to renumber), the others as
            ``earlier_run`` (in flight then, or its Proxy's last: it may have executed; never
            executed again, and, while this site serves, answered ERROR "outcome unknown" so the
            call ends). A corrupt log, or one another process still holds after up to 5 s (the gate
            of a site started earlier may be ending), stops the gate at set-up, naming it; 'none'
            keeps the floors in memory only (a WARN in the diagnostics); a write that fails refuses
            the request (``replay_log`` alarm) and every one after it, its diagnostics ERROR, and
            fail-stops its site, once, through its crash detector (port fail_stop, bound with a
            replay log and ~site), so that its peer takes over; a site serving alone by the witness's
            configuration, or a gate with no ~site, stays, refusing.
        ~site (str, server side, default ''), ~witness (str, server side, default '': none): with a
            replay log, the site this gate fail-stops and the witness whose configurations say
            whether it serves: an ``earlier_run`` is answered (with the configuration's epoch) only
            then (a backup that re-joined leaves a call still in flight to the primary, which answers
            it). Without a witness it answers (no re-joins then).
        ~replay_sync (bool, true): each write group flushed to the device (fdatasync) before its
            requests go on, so a power loss keeps it too; false: a crash of the process only.
        Floors at a join (server side, with ~site and ~witness): each configuration of the witness that
            pairs this site with a peer makes this gate ask the peer's gate (/PEER/<this node's base
            name>/replay_floors) for its watermarks, and take the higher ones, on its replay log too
            (security.ReplayGuard.learn): replays of requests its Proxies sent while this site was down
            are refused here as well, even from a Proxy silent since. The answer is signed by the
            gates' party and ciphered for it; a forged or altered one is refused with its alarm, and a
            peer that does not answer within FLOOR_TRIES tries raises ``floors_unavailable`` (a WARN)
            and is asked again, FLOOR_LATER s apart (doubling up to FLOOR_LATER_MAX), for as long as
            the pairing lasts: a peer gate paused or slow through the join is heard once it answers.
        Freshness (server side): the first request of each origin in this gate's run is not let through;
            its signer is asked, sealed, to seal it again naming a nonce of this run (Reply CHALLENGE,
            answered by the client gate, never seen by the Proxy): a replay cannot (security.Freshness).
            An origin asked and unconfirmed CHALLENGE_WAIT s raises ``unanswered_challenge`` once.
    Services called: certificate (aft_msgs/Certificate): the CA's.
    Subscribes: requests_in (aft_msgs/Request), replies_in (aft_msgs/Reply),
        certificate_status (aft_msgs/CertificateStatus): the CA's; a revoked or expired certificate is
        dropped at once, and its party's messages refused (``revoked``, ``expired``)
    Publishes: requests_out (aft_msgs/Request), replies_out (aft_msgs/Reply), alarms (aft_msgs/Alarm),
        fail_stop (aft_msgs/Failure; server side: its site's fail-stop when its replay log fails)
    Services: ~rebind (aft_msgs/Rebind), ~replay_floors (aft_msgs/ReplayFloors; server side)
    Services called: the peer gate's ~replay_floors (server side, at a join)
    """

    def __init__(self):
        self.side = param('side', config.choice('client', 'server'), required=True)
        keys_dir = param('keys_dir', config.non_empty_str, required=True)
        self.me = security.read_party(keys_dir, param('party', config.non_empty_str, required=True))
        self.keys_dir = keys_dir
        self.previous_me = None   # the key before a rotation: replies sealed for it are still opened
        self.key_file = self._key_file_id()
        self.refetched = {}       # party -> when its certificate was last fetched again after a bad signature
        self.ca_lock = threading.Lock()
        self.ca_timeout = param('ca_timeout', config.positive_float, 2.0)
        ca_public = param('ca_public', config.non_empty_str, required=True)
        self.ca_verify = security.read_public(*_split(ca_public))[1]
        self.server_party = param('server_party', config.non_empty_str, 'server' if self.side == 'client' else '')
        self.destination = param('destination', config.optional_name, '') or rospy.resolve_name(
            'requests_out' if self.side == 'client' else 'requests_in')
        self.tls = tls_transport.active()
        self.role = ROLES[param('role', config.choice(*ROLES), 'primary')]
        self.ports = Ports([PortSpec('requests_in', SUBSCRIBE, 'aft_msgs/Request'),
                            PortSpec('requests_out', PUBLISH, 'aft_msgs/Request'),
                            PortSpec('replies_in', SUBSCRIBE, 'aft_msgs/Reply'),
                            PortSpec('replies_out', PUBLISH, 'aft_msgs/Reply'),
                            PortSpec('alarms', PUBLISH, 'aft_msgs/Alarm'),
                            PortSpec('fail_stop', PUBLISH, 'aft_msgs/Failure')],
                           {'requests_in': self._on_request, 'replies_in': self._on_reply},
                           listeners={'requests_out': _ResendOnConnect(self)})
        self.sent = {}            # client side: (origin, id) -> sealed request not answered yet
        self.unsealed = {}        # client side: (origin, id) -> the same request as its Proxy sent it
        self.challenges = {}      # client side: origin -> the last freshness challenge a server gate asked
        self.book = security.CertificateBook(self.ca_verify, param('ca_silent_after', config.positive_float, 3.0))
        self.ca_silent_told = False
        policy = param('policy', config.optional_name, '')
        self.policy = policy or None
        self.origins = security.OriginBinding(sec_policy.load(policy) if policy else None)   # server side
        self.not_for_me = 0       # client side: replies signed for another party, passed over
        self.replays = security.ReplayGuard()
        self.freshness = security.Freshness()   # server side: which origins proved fresh in this run
        self.replay_log = None
        if self.side == 'server':
            path = param('replay_log', config.non_empty_str, os.path.join(
                keys_dir, 'replay', '%s.log' % rospy.get_name().strip('/').replace('/', '.')))
            if path != 'none':
                self.replay_log = replay_log.ReplayLog(path, sync=param('replay_sync', config.flag, True))
        self.restored = 0         # origins whose floors an earlier run left (server side)
        self.floors_learned = 0   # origins whose watermark a peer gate's floors raised (server side)
        self.floors_asked = None    # the last (epoch, peer) whose floors were asked (server side; epochs only grow)
        self.floors_missing = None  # the peer whose floors could not be had, and why (server side)
        self.floor_calls = {}       # peer: an Event set once the last ask of its floors returned (server side)
        self.fail_stopped = False
        self.site_role = SiteRole(param('site', config.optional_name, '') if self.side == 'server' else '')
        self.witness = param('witness', config.witness_service, '') if self.side == 'server' else ''
        self.earlier_told = collections.OrderedDict()   # (origin, id) refused as earlier_run, alarmed once
        # Client side: per origin (a Proxy), the nonce of its run, signed into each request and named by its
        # reply, and the highest oldest_pending it sent: one lower is a new run of the Proxy (started again,
        # its clock behind: it uses ids again), which gets a new nonce. Server side: the nonce each pending
        # request came with, named by the reply sealed for it. A reply captured from an earlier run of a
        # Proxy (or of this gate), for an id used again, is refused (security.ReplyNonces).
        self.runs = security.ProxyRuns()
        self.nonces = security.ReplyNonces()
        # Server side: requests outstanding per party, bounded, so that no certified party fills the
        # Protocol's shared reply cache (which then refuses everyone).
        self.quota = security.PartyQuota(param('party_quota', config.non_negative_int, 10000), clock=time.monotonic)
        self.lock = threading.Lock()
        self.rejected = 0
        self.diagnostics = None

    def setup(self, timeout):
        if self.replay_log is not None:
            try:   # before any request: one an earlier run let through must not pass now (the gate of a
                floors = self.replay_log.open(wait=min(timeout, 5.0))   # site started again may still be ending)
            except (replay_log.CorruptReplayLog, OSError) as e:
                rospy.logerr('%s: the replay log (~replay_log) cannot be used: %s', rospy.get_name(), e)
                return False
            self.replays.restore(floors)
            self.restored = len(floors)
            if not self.replay_log.existed:
                rospy.logwarn('%s: no replay log at %s: a first start (else the log of an earlier run was lost, moved '
                              'or renamed, and every request that run took is taken again)', rospy.get_name(),
                              self.replay_log.path)
            rospy.loginfo('%s: replay floors of %d origin(s) restored from %s%s', rospy.get_name(), len(floors),
                          self.replay_log.path, ' (%d torn line(s) at its end dropped)' % self.replay_log.dropped
                          if self.replay_log.dropped else '')

        elif self.side == 'server':
            rospy.logwarn('%s: ~replay_log is none: the replay floors are in memory only; started again, this gate '
                          'takes requests an earlier run let through', rospy.get_name())
        try:   # opened now: a certificate asked later (a failover, a new client) needs no master
            self.certificate = open_service('certificate', Certificate, timeout)
        except (rospy.ROSException, rospy.ServiceException) as e:
            rospy.logerr('%s: the certification authority (%s) is not available: %s', rospy.get_name(),
                         rospy.resolve_name('certificate'), e)
            return False
        deadline = time.monotonic() + timeout
        self.ports.bind('alarms', queue_size=0)   # a status refused raises an alarm from now on
        if self.side == 'server':   # (after the alarms: a forged configuration is told there)
            rospy.Service('~replay_floors', ReplayFloors, self._serve_floors)
            self.configuration = follow_site_role(self.site_role, self.witness, report=lambda detail: alarm(
                self.ports, 'witness', 'forged_configuration', detail), on_change=self._on_configuration)
            if self.site_role.site and self.replay_log is not None:
                self.ports.bind('fail_stop')   # bound now: heard by the crash detector when it is needed
        # The CA's status first (latched: it comes at once from a running CA): no certificate is
        # taken before it says which are revoked and what time it is.
        self.status_sub = rospy.Subscriber('certificate_status', CertificateStatus, self._on_status, queue_size=10)
        if not self._wait_for_status(deadline):
            rospy.logwarn('%s: no status from the certification authority (%s) within %.1f s: every message that '
                          'needs a certificate is refused (ca_unreachable) until one comes', rospy.get_name(),
                          rospy.resolve_name('certificate_status'), timeout)
        if self.side == 'client':
            while True:   # a CA slow to answer (a loaded machine) is asked again within the set-up's time
                try:
                    self._peer(self.server_party)
                    break
                except security.Rejected as e:
                    if e.kind != 'ca_unreachable' or time.monotonic() > deadline:
                        rospy.logerr('%s: %s', rospy.get_name(), e)
                        return False
                    time.sleep(0.1)
        # What goes to another host is queued per connection (a dead host must not block the others:
        # see the Proxy's requests and the Protocol's replies): the client side's requests, the server
        # side's replies to the clients' gates. A message a queue drops is sent again (the Proxy re-sends).
        remote = 'requests_out' if self.side == 'client' else 'replies_out'
        for name in ('requests_out', 'replies_out', 'replies_in', 'alarms'):
            self.ports.bind(name, queue_size=REMOTE_QUEUE if name == remote else 0)
        if self.role != Role.BACKUP:
            self.ports.bind('requests_in')
        missing = wait_for_connections(self.ports, ['requests_out', 'replies_in'], timeout)
        if missing:
            rospy.logwarn('%s: %s not connected yet', rospy.get_name(), missing)
        self.ports.advertise_service()
        self.diagnostics = Diagnostics(self._health)
        threading.Thread(target=self._watch_ca, name='ca-watch', daemon=True).start()
        threading.Thread(target=self._watch_own_key, name='key-watch', daemon=True).start()
        if self.side == 'server':
            threading.Thread(target=self._watch_challenges, name='challenge-watch', daemon=True).start()
        if not self.tls:
            threading.Thread(target=self._tell_without_tls, args=(timeout,), name='tls-notice', daemon=True).start()
        if self.side == 'server' and self.policy is None:
            rospy.logwarn('%s: no SEC policy (~policy): each origin is bound to the first party whose signed request '
                          'uses it', rospy.get_name())
        return True

    def _health(self):
        with self.lock:
            report = health.sec_gate(self.side, self.me.name, self.role, len(self.book.peers), len(self.sent),
                                     self.rejected, policy=self.policy if self.side == 'server' else '',
                                     at_quota=self.quota.at_quota() if self.side == 'server' else ())
        values = list(report.values) + [('destination', self.destination),
                                        ('tls', 'on' if self.tls else 'off')]
        if self.side == 'server':
            log = self.replay_log
            with self.lock:
                confirmed, asked, sent = (len(self.freshness.confirmed), len(self.freshness.asked),
                                          self.freshness.sent)
            values += [('replay_log', log.path if log else 'none'), ('replay_origins_restored', self.restored),
                       ('replay_floors_learned', self.floors_learned), ('origins_fresh', confirmed),
                       ('origins_asked_fresh', asked), ('freshness_challenges', sent)]
            if log is not None and log.broken:
                report = Report(Level.ERROR, '%s: every request is refused' % log.broken, values)
            elif log is None:
                report = _warn(report, 'replay floors in memory only (~replay_log none)', values)
            missing = self.floors_missing
            if missing is not None:
                report = _warn(report, 'the replay floors of %s\'s gate not learned: %s' % missing, values)
        if self.tls:
            return Report(report.level, report.message, values)
        told = 'no TLS: its plaintext side is open to every node of the graph (%s)' % ', '.join(self._plaintext_side())
        return Report(max(report.level, Level.WARN),
                      told if report.level == Level.OK else '%s; %s' % (report.message, told), values)

    def _plaintext_side(self):
        """The topics where this gate's messages are in clear: the Proxy's (client side) or the Protocol's."""
        ports = ('requests_in', 'replies_out') if self.side == 'client' else ('requests_out', 'replies_in')
        return [self.ports.topic(p) or rospy.resolve_name(p) for p in ports]

    def _wait_for_status(self, deadline):
        while True:
            with self.lock:
                if self.book.seq is not None:
                    return True
            if time.monotonic() > deadline or rospy.is_shutdown():
                return False
            time.sleep(0.02)

    def _tell_without_tls(self, wait):
        """``tls sec_without_tls``, once: after an alarm subscriber is heard (or ``wait`` s), so that
        it is seen. Not ``sec``: the change model takes every SEC alarm for an attack."""
        end = time.monotonic() + wait
        while self.ports.connections('alarms') < 1 and time.monotonic() < end and not rospy.is_shutdown():
            time.sleep(0.1)
        alarm(self.ports, 'tls', 'sec_without_tls',
              'SEC runs without TLS: the plaintext side of %s (%s) is open to every node of the ROS graph, which '
              'may read there what SEC ciphers and publish there what SEC never checks (%s); mutual TLS '
              '(AFT_TLS_DIR, the launch files\' tls_dir:=) closes it' % (
                  rospy.get_name(), ', '.join(self._plaintext_side()),
                  'requests this gate signs as its own, replies for its Proxy' if self.side == 'client'
                  else 'requests for the Protocol'))

    def _peer(self, party):
        """The certified public keys of party: held while valid, else fetched from the CA and checked."""
        now = time.monotonic()
        with self.lock:
            cert = self.book.get(party, now)
            heard = self.book.seq is not None
        if cert is not None:
            return cert.box_public, cert.verify_public
        if not heard:   # nothing to judge a certificate by: the CA is not asked for one it could not take
            raise security.Rejected('ca_unreachable', 'no status from the CA has come yet: the certificate of %s '
                                    'cannot be judged' % party)
        cert = self._refetch(party)
        return cert.box_public, cert.verify_public

    def _ask_ca(self, party):
        """The CA's answer about party, within ~ca_timeout (waiting for another call to the CA included):
        a frozen or hung CA holds no receive thread (and none of the clients behind it) longer; its
        message is refused (Rejected ``ca_unreachable``, an alarm) and its Proxy sends it again. One CA
        call at a time on the persistent connection (receive threads, key watch); a call past the
        deadline is left to a daemon thread of its own, its connection closed, and the next call
        opens a new one."""
        end = time.monotonic() + self.ca_timeout
        if not self.ca_lock.acquire(timeout=self.ca_timeout):
            raise security.Rejected('ca_unreachable', 'the CA, asked about another party, has not answered for '
                                    '%.1f s: %r is not checked' % (self.ca_timeout, party))
        try:
            proxy = self.certificate
            answer, error = _within(lambda: proxy(party=party), max(0.0, end - time.monotonic()))
            if error is None:
                return answer
            self.certificate = proxy.fresh()
            _close(proxy)   # a call stuck reading it gets an error and ends
            if error is TIMED_OUT:
                raise security.Rejected('ca_unreachable', 'the CA did not answer within %.1f s about %r' % (
                    self.ca_timeout, party))
            raise security.Rejected('ca_unreachable', 'the CA cannot be asked about %r: %s' % (party, error))
        finally:
            self.ca_lock.release()

    def _open(self, party, blob, header):
        """Verify and decipher a blob from party: with each certificate held for it (a rotated key's
        old one too), for each key of this gate's own (its old one too); after a bad signature with
        all of them, its certificate fetched again once (at most once a second: it may have rotated)."""
        for attempt in (0, 1):
            self._peer(party)
            with self.lock:
                certs = self.book.candidates(party, time.monotonic())
            mine = [self.me] + ([self.previous_me] if self.previous_me is not None else [])
            error = None
            for cert in certs:
                for me in mine:
                    try:
                        plaintext = security.open_sealed(me, cert.verify_public, blob, header)
                    except security.Rejected as e:
                        error = e
                        if e.kind != 'undecryptable':
                            break   # this certificate's signature or header: the next certificate
                        continue
                    return plaintext
            now = time.monotonic()
            if attempt or error.kind != 'bad_signature' or now - self.refetched.get(party, -1e9) < 1.0:
                raise error
            self.refetched[party] = now
            try:
                self._refetch(party)
            except security.Rejected as e:
                if e.kind == 'ca_unreachable':
                    raise error   # the certificates held stay: an unsigned message evicts none (below)
                raise
        raise error

    def _refetch(self, party):
        """Ask the CA again for party's certificate (its key may have rotated), keeping the ones held:
        added, a new one holds the old as the previous. Dropping the held one first let a forged message
        (a bad signature, claiming party) evict it, so that while the CA was unreachable every genuine
        message of that party was refused ca_unreachable (review of session 41)."""
        answer = self._ask_ca(party)
        if not answer.found:
            kind = 'revoked' if answer.message.startswith('revoked') else 'unknown_party'
            raise security.Rejected(kind, answer.message)
        cert = security.check_certificate(self.ca_verify, party, answer.box_public, answer.verify_public,
                                          answer.serial, answer.not_after, answer.signature)
        with self.lock:
            return self.book.add(party, cert, time.monotonic())

    def _key_file_id(self):
        try:
            info = os.stat(os.path.join(self.keys_dir, self.me.name + '.key'))
            return (info.st_ino, info.st_mtime_ns, info.st_size)
        except OSError:
            return None

    def _watch_own_key(self, period=0.2):
        """A rotation of this gate's own key (a new <party>.key): signed with it only once the CA
        certifies it (it re-reads the public keys every period), so no message is signed with a key
        that no gate can check yet; the old key still opens what was sealed for it."""
        candidate = None
        while not rospy.is_shutdown():
            time.sleep(period)
            seen = self._key_file_id()
            if seen != self.key_file:
                try:
                    candidate = security.read_party(self.keys_dir, self.me.name)
                    self.key_file = seen
                except config.ConfigError as e:
                    rospy.logwarn_throttle(10.0, '%s: the new key cannot be read yet: %s' % (rospy.get_name(), e))
                    continue
                if candidate.verify_public == self.me.verify_public:
                    candidate = None
            if candidate is None:
                continue
            try:
                answer = self._ask_ca(self.me.name)
            except security.Rejected:   # asked again at the next look
                continue
            if answer.found and bytes(answer.verify_public) == candidate.verify_public:
                self.previous_me, self.me, candidate = self.me, candidate, None
                rospy.logwarn('%s: signing with the rotated key of %s now (certificate %d)', rospy.get_name(),
                              self.me.name, answer.serial)

    def _on_status(self, status):
        try:
            with self.lock:
                dropped = self.book.on_status(status.ca_time, status.seq, status.revoked, status.signature,
                                              time.monotonic())
        except security.Rejected as e:
            self._reject(e)
            return
        self.ca_silent_told = False
        if dropped:
            rospy.logwarn('%s: the certificates of %s are revoked or expired: their messages are refused',
                          rospy.get_name(), ', '.join(dropped))

    def _watch_ca(self):
        """Never silent: a CA whose status stops coming cannot revoke anything meanwhile."""
        while not rospy.is_shutdown():
            time.sleep(1.0)
            with self.lock:
                silent = self.book.silent(time.monotonic())
            if silent and not self.ca_silent_told:
                self.ca_silent_told = True
                alarm(self.ports, 'sec', 'ca_silent', 'no status from the certification authority for %s: '
                      'a revocation cannot reach %s' % ('ever' if silent == float('inf') else '%.1f s' % silent,
                                                         rospy.get_name()))

    def _reject(self, error, msg=None):
        self.rejected += 1
        alarm(self.ports, 'sec', error.kind, error.detail, msg)

    # -- requests -----------------------------------------------------------------------------
    def _on_request(self, request):
        try:
            nonce = None
            if self.side == 'client':
                box, _ = self._peer(self.server_party)
                header = security.header_of(request, security.REQUEST_FIELDS, self.server_party, self.destination)
                with self.lock:
                    header['nonce'] = self.runs.nonce_for(request.origin, request.id, request.oldest_pending)
                    challenge = self.challenges.get(request.origin)
                if challenge is not None:   # the server gates that asked it take it at once
                    header['challenge'] = challenge
                payload = security.seal(self.me, box, header, request.payload)
                if len(payload) + CHALLENGE_ROOM > security.MAX_SEALED_BYTES:   # (sealed again with a challenge,
                    self._too_large(request, len(payload))                    # it must still fit)
                    return
            else:
                party, nonce = security.sender_of(request.payload), security.nonce_of(request.payload)
                challenge = security.challenge_of(request.payload)
                header = security.header_of(request, security.REQUEST_FIELDS, self.me.name, self.destination)
                if nonce is not None:   # signed, when named (a request that names none: no client gate will
                    header['nonce'] = nonce   # take its reply)
                if challenge is not None:
                    header['challenge'] = challenge
                payload = self._open(party, request.payload, header)
                with self.lock:
                    self.origins.bind(party, request.origin, keep=False)
                    self.replays.check(request.origin, request.id)
                    ask = self.freshness.check(request.origin, challenge, time.monotonic())
                    if ask is None:
                        # Past its quota, nothing of it is kept (a flood of one-shot origins grows nothing).
                        self.quota.admit(party, request.origin, request.id, request.oldest_pending)
                        self.origins.bind(party, request.origin)
                        self.replays.advance(request.origin, request.oldest_pending, request.id)
                        self.nonces.note(request.origin, request.id, nonce, request.oldest_pending)
                        floors = self.replays.floors(request.origin)
                        self.freshness.confirm(request.origin)
                if ask is not None:
                    self._ask_fresh(request, nonce, party, ask)
                    return
                self._make_durable(request.origin, floors)
        except security.Rejected as e:
            if e.kind == 'earlier_run':
                self._earlier_run(e, request, nonce, party)
                return
            if e.kind == 'party_quota' and not e.first:
                with self.lock:
                    self.rejected += 1   # told once while the party stays at its quota (diagnostics say it)
                return
            self._reject(e, request)
            if e.kind == 'replay':
                self._renumber(request, nonce, party)
            elif e.kind == 'replay_log':
                self._fail_stop(e.detail)
            return
        # batch is PBR's group commit, numbered by the Protocol behind the server's gate: a client's
        # request carries none. One a client set (signed: it is its own) made PBR's After wait for batch
        # members that never came, or fail-stop the primary (review of group commit, session 33).
        out = Request(id=request.id, origin=request.origin, client=request.client,
                      service_type=request.service_type, oldest_pending=request.oldest_pending,
                      attempt=request.attempt, payload=payload, epoch=request.epoch, transfer=request.transfer,
                      batch=request.batch if self.side == 'client' else (0, 0))
        if self.side == 'client':
            with self.lock:
                self.sent[(request.origin, request.id)] = out
                self.unsealed[(request.origin, request.id)] = request
                for key in [k for k in self.sent if k[0] == request.origin and k[1] < request.oldest_pending]:
                    del self.sent[key]   # answered: the Proxy will not ask again
                    self.unsealed.pop(key, None)
        self.ports.publish('requests_out', out)

    def _make_durable(self, origin, floors):
        """The origin's floors on disk before its request goes on (a run started later refuses it)."""
        if self.replay_log is None:
            return
        try:
            self.replay_log.record(origin, *floors)
        except OSError as e:
            raise security.Rejected('replay_log', 'request not let through: its replay floors could not be made '
                                                  'durable (%s); its Proxy sends it again' % e)

    def _earlier_run(self, error, request, nonce, party):
        """A request an earlier run of this gate let through: never executed now. Alarmed once per id (its
        Proxy sends it again every half second; at most 256 ids remembered). While this site serves it is
        answered, sealed for its signer, ERROR "outcome unknown", so that an honest call in flight at the
        restart ends (it waited for ever under the Proxy's default of no timeout, its oldest_pending held
        every later reply of its Proxy in the caches). A backup says nothing: its primary answers."""
        key = (request.origin, request.id)
        with self.lock:
            first = key not in self.earlier_told
            self.earlier_told[key] = True
            while len(self.earlier_told) > 256:
                self.earlier_told.popitem(last=False)
            if not first:
                self.rejected += 1
        if first:
            self._reject(error, request)
        # Without a witness there are no re-joins: a gate that restarted restarted with its whole
        # deployment, and one that receives requests may answer (a promoted backup too).
        serving = self.site_role.role in (Role.PRIMARY, Role.ALONE) if self.witness else True
        if serving:   # its epoch: a deposed primary's answer is refused as stale by the Proxy
            self._on_reply(Reply(id=request.id, origin=request.origin, client=request.client,
                                 oldest_pending=request.oldest_pending, attempt=request.attempt, batch=request.batch,
                                 status=Reply.ERROR, epoch=self.site_role.epoch or 0,
                                 error='outcome unknown: %s' % error.detail), nonce, party)

    # -- the peer gate's floors, at a join ----------------------------------------------------------
    FLOOR_TRIES = 5          # asks of the peer's gate per configuration, FLOOR_RETRY s apart
    FLOOR_RETRY = 1.0
    FLOOR_TIMEOUT = 2.0      # the longest wait for one answer
    FLOOR_LATER = 5.0        # then one ask this often, doubling up to FLOOR_LATER_MAX, while the pairing lasts
    FLOOR_LATER_MAX = 60.0

    def _serve_floors(self, req):
        """This gate's watermarks for its peer's gate: sealed by and for the gates' party."""
        if len(req.nonce) > 128:
            raise rospy.ServiceException('a nonce of %d characters: at most 128' % len(req.nonce))
        with self.lock:
            marks = dict(self.replays.watermarks)
        return ReplayFloorsResponse(sealed=security.seal_floors(self.me, marks, req.nonce))

    def _on_configuration(self, epoch, primary, backup):
        """A configuration of the witness: one that pairs this site with a peer has the peer's floors
        asked for, once per (epoch, peer), in a thread of its own. Any other ends the last pairing
        (its asking stops)."""
        site = self.site_role.site
        paired = bool(primary and backup) and site in (primary, backup)
        peer = (backup if site == primary else primary) if paired else None
        with self.lock:
            if self.floors_asked == (epoch, peer) or (not paired and self.floors_asked is None):
                return
            self.floors_asked = (epoch, peer)
        if paired:
            threading.Thread(target=self._follow_floors, args=(epoch, peer), name='floors', daemon=True).start()

    def _pairing_is(self, pairing):
        """pairing (epoch, peer) is still the last one seen (None: asked outside a pairing, as the tests do)."""
        with self.lock:
            return pairing is None or self.floors_asked == pairing

    def _follow_floors(self, epoch, peer):
        """The floors of peer's gate asked in a burst; a peer that did not answer (paused, slow, restarting
        through the join) is asked again, once every FLOOR_LATER s (doubling up to FLOOR_LATER_MAX), for
        as long as this pairing is the last one seen (the loop ends with it, or with the node)."""
        pairing = (epoch, peer)
        if self._pull_floors(peer, pairing=pairing):
            return
        wait, since = self.FLOOR_LATER, time.monotonic()
        while not rospy.is_shutdown():
            time.sleep(wait)
            if not self._pairing_is(pairing):
                return
            if self._pull_floors(peer, tries=1, alarmed=True, pairing=pairing):
                if not self.fail_stopped:
                    rospy.loginfo('%s: the replay floors of %s learned %.0f s after its first tries failed',
                                  rospy.get_name(), peer, time.monotonic() - since)
                return
            wait = min(wait * 2, self.FLOOR_LATER_MAX)

    def _pull_floors(self, peer, tries=None, alarmed=False, pairing=None):
        """Ask peer's gate for its floors, up to tries (FLOOR_TRIES) times FLOOR_RETRY s apart, and learn
        them: True once done with (learned, or the site fail-stopped on its log). Otherwise the reason is
        kept (floors_missing, a WARN, while pairing is the last one seen) and, unless alarmed already,
        ``floors_unavailable`` raised. An ask of a peer still unanswered (its gate paused: rospy's call has
        no timeout of its own) is not doubled: its thread is the only one held (another peer is asked)."""
        service = '/%s/%s/replay_floors' % (peer, rospy.get_name().rsplit('/', 1)[-1])
        why = 'never asked'
        tries = self.FLOOR_TRIES if tries is None else tries
        for attempt in range(tries):
            if attempt:
                time.sleep(self.FLOOR_RETRY)
            if rospy.is_shutdown():
                return False
            pending = self.floor_calls.get(peer)
            if pending is not None and not pending.is_set():
                why = 'an earlier ask still unanswered'
                continue
            nonce = os.urandom(12).hex()
            self.floor_calls[peer] = threading.Event()
            answer, error = _within(lambda: rospy.ServiceProxy(service, ReplayFloors)(nonce=nonce), self.FLOOR_TIMEOUT,
                                    done=self.floor_calls[peer])
            if error is not None:
                why = 'no answer within %.1f s' % self.FLOOR_TIMEOUT if error is TIMED_OUT else str(error)[:200]
                continue
            try:
                marks = security.read_floors(self._open(self.me.name, answer.sealed,
                                                        security.floors_header(self.me.name, nonce)))
            except security.Rejected as e:
                if e.kind in SEC_UNAVAILABLE:
                    why = e.detail
                    continue
                self._reject(security.Rejected(e.kind, 'the replay floors %s answered: %s' % (service, e.detail)))
                why = 'its answer was refused (%s)' % e.kind
                continue
            return self._learn_floors(peer, marks, pairing)
        with self.lock:
            if pairing is not None and self.floors_asked != pairing:
                return False   # (a later pairing asks for itself and says so)
            self.floors_missing = (peer, why)
        if not alarmed:
            alarm(self.ports, 'sec', 'floors_unavailable', 'the replay floors of %s could not be had in %d tries '
                  '(%s): requests its Proxies sent while this site was down, replayed now, pass this gate (the '
                  'Protocol still drops those below its own watermarks); asked again every %.0f s or more while '
                  'the pairing lasts' % (service, tries, why, self.FLOOR_LATER))
        return False

    def _learn_floors(self, peer, marks, pairing=None):
        """Take the peer's floors where higher, on the replay log too: True (done), also when the log failed
        and the site fail-stops (nothing more to ask then)."""
        with self.lock:
            raised = self.replays.learn(marks)
            floors = [(origin, self.replays.floors(origin)) for origin in raised]
        try:
            for origin, floor in floors:
                self._make_durable(origin, floor)
        except security.Rejected as e:   # (the next request meets the broken log too)
            self._reject(e)
            self._fail_stop(e.detail)
            return True
        with self.lock:
            self.floors_learned += len(raised)
            if pairing is None or self.floors_asked == pairing:
                self.floors_missing = None
        rospy.loginfo('%s: the replay floors of %s\'s gate: %d origin(s), %d raised here', rospy.get_name(), peer,
                      len(marks), len(raised))
        return True

    def _fail_stop(self, why):
        """The replay log failed: nothing more can be let through safely. A replica with a peer that can
        take over fail-stops its site (the peer fences it and serves), once, rather than refuse every
        request for ever. Alone (the only copy of the state) or outside a replica it stays, refusing
        each request with the alarm, its diagnostics ERROR, for an operator to act."""
        if not self.site_role.site or self.site_role.alone() or self.fail_stopped:
            return
        self.fail_stopped = True
        fail_stop(self.ports, self.site_role.site, '%s: %s' % (rospy.get_name(), why))

    def _too_large(self, request, size):
        """A client's request larger sealed than a server gate takes: answered here, not executed. Sent
        on, it was refused unread there with no reply, and its Proxy sent it again every half second for
        ever, every other call of that Proxy refused meanwhile (review of session 41)."""
        detail = ('request %s/%d is %d bytes sealed, more than a SEC message may be (%d): not sent, nothing '
                  'executed' % (request.origin, request.id, size, security.MAX_SEALED_BYTES))
        alarm(self.ports, 'proxy', 'request_too_large', detail, request)
        self.ports.publish('replies_out', Reply(id=request.id, origin=request.origin, client=request.client,
                                                oldest_pending=request.oldest_pending, attempt=request.attempt,
                                                batch=request.batch, status=Reply.NOT_EXECUTED, error=detail,
                                                epoch=request.epoch))

    def _reply_too_large(self, reply, size, box, party, nonce):
        """A reply larger sealed than a client's gate takes: replaced by a sealed ERROR saying the request
        was executed and its answer cannot be carried. Sent as it was, the client's gate refused it
        unread, its Proxy asked again every half second for ever, and the cache answered the same
        (review of session 41). Returns (the reply as it goes on the wire, its payload)."""
        error = ('the reply to request %s/%d is %d bytes sealed, more than a SEC message may be (%d): the request '
                 'was executed; its answer cannot be carried' % (reply.origin, reply.id, size,
                                                                security.MAX_SEALED_BYTES))
        alarm(self.ports, 'server', 'reply_too_large', error, reply)
        wire = Reply(id=reply.id, origin=reply.origin, client=reply.client, oldest_pending=reply.oldest_pending,
                     attempt=reply.attempt, batch=reply.batch, status=Reply.ERROR, error=SEALED_ERROR,
                     epoch=reply.epoch)
        return wire, self._seal_reply(wire, box, party, nonce, error, b'')

    def _seal_reply(self, reply, box, party, nonce, error, payload):
        """payload and the error text sealed for party, with reply's header (and the nonce its request
        came with, when it named one) signed."""
        header = security.header_of(reply, security.REPLY_FIELDS, party, self.destination)
        if nonce is not None:
            header['nonce'] = nonce
        return security.seal(self.me, box, header, security.frame_error(error, payload))

    def _ask_fresh(self, request, nonce, party, challenge):
        """A request of an origin that has not proved fresh in this run of the gate (security.Freshness):
        not let through; the party that signed it is asked, sealed, to sign it again naming challenge.
        Its client gate does so if the request is pending there; a replay is never answered (and raises
        ``unanswered_challenge`` once its origin stays unconfirmed CHALLENGE_WAIT s)."""
        self._on_reply(Reply(id=request.id, origin=request.origin, client=request.client,
                             oldest_pending=request.oldest_pending, attempt=request.attempt, batch=request.batch,
                             status=Reply.CHALLENGE, epoch=self.site_role.epoch or 0,
                             payload=challenge.encode('ascii')), nonce, party)

    def _answer_challenge(self, reply, payload):
        """Client side: a server gate asks this gate to prove a request fresh (security.Freshness). The
        request, if still pending here, is sealed again naming the challenge and sent; every later
        request of its origin names it too. For a request not pending here (a replay's, or one answered
        meanwhile) nothing is sent."""
        challenge = bytes(payload).decode('ascii', 'replace')
        if not challenge or len(challenge) > 128 or not all(c in '0123456789abcdef' for c in challenge):
            raise security.Rejected('malformed', 'a freshness challenge for %s/%d is not a nonce' % (
                reply.origin, reply.id))
        key = (reply.origin, reply.id)
        with self.lock:
            self.challenges[reply.origin] = challenge
            request = self.unsealed.get(key)
            if request is None:
                self.not_for_me += 1
                return
        box, _ = self._peer(self.server_party)
        header = security.header_of(request, security.REQUEST_FIELDS, self.server_party, self.destination)
        header['challenge'] = challenge
        with self.lock:   # still pending, sealed with its run's nonce as it was (its Proxy may have gone on
            if key not in self.unsealed:   # meanwhile: nonce_for would take the older id for a new run)
                return
            header['nonce'] = security.nonce_of(self.sent[key].payload)
            payload = security.seal(self.me, box, header, request.payload)
            out = _request_with(self.sent[key], payload)
            self.sent[key] = out
        self.ports.publish('requests_out', out)

    def _watch_challenges(self, period=1.0):
        """Server side: an origin asked to prove itself fresh that has not, CHALLENGE_WAIT s on, is said
        once (``unanswered_challenge``): only replays came from it, or its client gate cannot answer."""
        while not rospy.is_shutdown():
            time.sleep(period)
            with self.lock:
                late = self.freshness.unanswered(time.monotonic(), self.CHALLENGE_WAIT)
            for origin, waited in late:
                alarm(self.ports, 'sec', 'unanswered_challenge',
                      'requests of %s were asked to prove they are fresh (signed again for this run of %s) %.1f s '
                      'ago and none has: replays of an earlier run (refused, not executed), or its client gate '
                      'cannot answer (its requests are not let through here)' % (origin, rospy.get_name(), waited))

    CHALLENGE_WAIT = 5.0   # s an origin may stay asked and unconfirmed before it is said

    def _renumber(self, request, nonce, party):
        """A verified request below the ids answered: a replay, or its Proxy started again with its clock
        behind (numbering below its predecessor: refused here for ever, it hung). Its party is told, sealed,
        the ids to use (STALE_ID, as the Protocol would): a Proxy waiting for that id sends it again
        under a new one; one that is not (the replay's) ignores it. Nothing is executed. Sealed for the
        party that signed it (which may send as its origin): a gate started again knows the floors of an
        origin from its replay log, not yet the party bound to it."""
        with self.lock:
            first_id = self.replays.first_free(request.origin)
        self._on_reply(Reply(id=request.id, origin=request.origin, client=request.client, oldest_pending=first_id,
                             attempt=request.attempt, batch=request.batch, status=Reply.STALE_ID,
                             error='id below those answered already: renumber'), nonce, party)

    def resend(self):
        """A new server gate subscribed (a backup took over): send it what is not answered yet, at
        once, as the Proxy does for its own subscribers."""
        with self.lock:
            pending = sorted(self.sent.values(), key=lambda r: r.id)
        for request in pending:
            self.ports.publish('requests_out', request)

    # -- replies ------------------------------------------------------------------------------
    def _on_reply(self, reply, nonce=None, party=None):
        try:
            if self.side == 'server':
                with self.lock:
                    party = party or self.origins.party_of(reply.origin)
                    nonce = nonce if nonce is not None else self.nonces.of(reply.origin, reply.id)
                if party is None:
                    raise security.Rejected('unknown_party', 'no verified request came from %s' % reply.origin)
                box, _ = self._peer(party)
                # The error text is sealed with the payload (a server's error names the client's data: "cannot
                # withdraw 999 from a balance of 4342"); the reply on the wire says only that there is one.
                error, reply = reply.error, _with_error(reply, SEALED_ERROR if reply.error else '')
                payload = self._seal_reply(reply, box, party, nonce, error, reply.payload)
                if len(payload) > security.MAX_SEALED_BYTES:
                    reply, payload = self._reply_too_large(reply, len(payload), box, party, nonce)
            else:
                if security.addressee_of(reply.payload) not in (self.me.name, None):
                    with self.lock:   # for another client's gate, which checks it: not an attack on this one
                        self.not_for_me += 1
                    return
                if security.sender_of(reply.payload) != self.server_party:
                    raise security.Rejected('unknown_party', 'the reply is not signed by %s' % self.server_party)
                nonce = security.nonce_of(reply.payload)
                header = security.header_of(reply, security.REPLY_FIELDS, self.me.name, self.destination)
                if nonce is not None:
                    header['nonce'] = nonce
                payload = self._open(self.server_party, reply.payload, header)
                with self.lock:
                    current = self.runs.current(reply.origin)
                if nonce != current:
                    with self.lock:
                        asked = (reply.origin, reply.id) in self.sent
                    if asked:   # an old reply for an id this run asks again: its Proxy would take it
                        raise security.Rejected('replay', 'reply %s/%d was sealed for %s, not for this run of '
                                                'its Proxy and its gate: captured from an earlier run'
                                                % (reply.origin, reply.id, 'another run' if nonce else 'no run'))
                    with self.lock:   # for no request of this run: its Proxy has nothing waiting for it
                        self.not_for_me += 1
                    return
                error, payload = security.unframe_error(payload)
                reply = _with_error(reply, error if error is not None else reply.error)
                if reply.status == Reply.CHALLENGE:
                    self._answer_challenge(reply, payload)
                    return
        except security.Rejected as e:
            self._reject(e, reply)
            return
        if self.side == 'client':
            with self.lock:
                self.sent.pop((reply.origin, reply.id), None)
                self.unsealed.pop((reply.origin, reply.id), None)
        self.ports.publish('replies_out', Reply(id=reply.id, origin=reply.origin, client=reply.client,
                                                oldest_pending=reply.oldest_pending, attempt=reply.attempt,
                                                batch=reply.batch, status=reply.status, error=reply.error, payload=payload,
                                                epoch=reply.epoch))


SEALED_ERROR = '(sealed)'   # the error text a reply carries on the wire: the real one is sealed with its payload
CHALLENGE_ROOM = 256   # bytes a request sealed again with a freshness challenge may grow by (about 45 used)


def _request_with(request, payload):
    """request (aft_msgs/Request) with another payload."""
    return Request(id=request.id, origin=request.origin, client=request.client, service_type=request.service_type,
                   oldest_pending=request.oldest_pending, attempt=request.attempt, payload=payload,
                   epoch=request.epoch, transfer=request.transfer, batch=request.batch)


def _warn(report, told, values):
    """report at least WARN, told added to its message, with values."""
    return Report(max(report.level, Level.WARN), told if report.level == Level.OK
                  else '%s; %s' % (report.message, told), values)


def _with_error(reply, error):
    return Reply(id=reply.id, origin=reply.origin, client=reply.client, oldest_pending=reply.oldest_pending,
                 attempt=reply.attempt, batch=reply.batch, status=reply.status, error=error, payload=reply.payload,
                 epoch=reply.epoch)


class _ResendOnConnect(rospy.SubscribeListener):
    def __init__(self, gate):
        super(_ResendOnConnect, self).__init__()
        self.gate = gate

    def peer_subscribe(self, topic_name, topic_publish, peer_publish):
        if self.gate.side == 'client':
            self.gate.resend()


def _split(path):
    """keys_dir and party name of a public key file path (.../ca.pub)."""
    directory, name = os.path.split(path)
    if not name.endswith('.pub'):
        raise config.ConfigError('%s is not a public key file (<party>.pub)' % path)
    return directory, name[:-4]


TIMED_OUT = object()


def _within(call, timeout, done=None):
    """(call()'s result, None), (None, its exception), or (None, TIMED_OUT) after timeout seconds.
    call() runs in a daemon thread of its own: a peer that never answers holds that thread only,
    never the caller, nor the process's exit. (Certificate fetches are rare: a thread each is cheap.)
    done (a threading.Event), if given, is set once call() returned or raised, even after the timeout."""
    out = {}
    done = done or threading.Event()

    def run():
        try:
            out['result'] = call()
        except Exception as e:   # given to the caller
            out['error'] = e
        finally:
            done.set()
    threading.Thread(target=run, name='ca-call', daemon=True).start()
    if not done.wait(timeout):
        return None, TIMED_OUT
    return out.get('result'), out.get('error')


def _close(proxy):
    try:
        proxy.close()
    except Exception:   # already closed, or never opened
        pass
