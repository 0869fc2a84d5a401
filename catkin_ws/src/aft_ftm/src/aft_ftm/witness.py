"""The witness: grants each configuration epoch to at most one primary.

Two replicas cannot tell a dead peer from a slow one. Each may then believe it is the only one
left: the backup promotes itself while the primary, which only paused, goes on alone. A third
party breaks the tie, as a quorum device does for a two-node cluster. This witness holds one
record, the configuration: its epoch, the site that may serve (primary) and the site that may be
promoted (backup). Every change makes a new epoch, and each request is granted only against the
current record, so at most one site holds the right to serve in any epoch:

- PROMOTE (the backup takes over): granted only to the backup of the current configuration. The
  old primary is deposed: it is neither primary nor backup any more. Asked again by the incarnation
  it promoted (its answer was lost) while it is alone, it is granted again and changes nothing.
- EXCLUDE (the primary goes on alone): granted only to the primary. The backup is excluded and
  can never be promoted until it re-joins (a join transfers the state again). Granted to a primary
  already alone, it makes a new epoch too, so that an ADMIT of an older epoch still on its way is
  refused.
- ADMIT (a joined site becomes the backup): granted only to the primary, naming the joined site
  and its incarnation, and only in the epoch its state transfer was made in (when the request says
  it): a late ADMIT never names a site whose state is older than the configuration.
- REGISTER (a site starts): tells whether it may serve. Only the initial primary (configured, or
  the first site that registers claiming it), in the first epoch and first incarnation, serves
  from its own state; every other start must join. A backup
  of the current configuration that starts again (a new incarnation) holds no state any more: it
  is excluded at once.

Invariants (checked by tests/unit/test_replication_sim.py after every step):
- the epoch only grows; each epoch names at most one primary;
- a site that is refused changes nothing;
- a promotion is granted only to a site that was admitted (or is the initial primary's backup
  never: the first backup is always admitted after a join).

Incarnations identify one start of a site (its launcher's pid and start time): a site that
restarted is a new incarnation, whose server holds none of the old one's state.

``store`` (optional) persists the record before a grant is answered, so that a witness that
restarts never grants an epoch twice; without it a restarted witness starts from epoch 0 and
must not be restarted while replicas run (the README says so).

A record lost or rolled back (a witness without a state file restarted, its file deleted or restored
from an old copy) would grant epochs again that were granted already: two primaries in one epoch.
Each request says the newest epoch its caller has seen (``known_epoch``); one above the record shows
it is behind, and from then on the witness grants nothing, not even a STATUS (WitnessBehind), until
it is restored. The sites see its older configuration too and tell it so (witness_client).
"""
import enum

from .errors import ConfigError
from .state_store import NO_STATE


class WitnessBehind(Exception):
    """The record is older than an epoch a caller has seen: it was lost or rolled back."""


class Op(enum.Enum):
    STATUS = 0
    PROMOTE = 1
    EXCLUDE = 2
    ADMIT = 3
    REGISTER = 4


def speaks_for(op, site, caller, known_epoch, epoch):
    """None if the node ``caller`` may ask ``op`` on behalf of ``site``, else why not. A STATUS that
    tells the witness no later epoch than its own is anyone's to ask; every other request (a
    registration, a promotion, an exclusion, an admission, or a STATUS saying the witness is behind)
    only a node of the site itself (/SITE/...) may make. Otherwise any party allowed to call the
    witness spoke for any site: a STATUS with an epoch of 2^64-1 left the witness behind for good,
    a PROMOTE of the backup forced a failover (review of session 41). Meaningful where a node's name
    is bound to its sender (mutual TLS binds each party to its nodes' names)."""
    op = Op(op)
    if op == Op.STATUS and known_epoch <= epoch:
        return None
    if not site or '/' in site.strip('/') or not caller.startswith('/%s/' % site.strip('/')):
        return '%s may not ask %s for site %r (known epoch %d, the witness\'s %d): only a node of that site may' % (
            caller, op.name, site, known_epoch, epoch)
    return None


class Grant(object):
    """A witness's answer: granted or not, why, and the configuration after it."""
    __slots__ = ('granted', 'message', 'epoch', 'primary', 'backup')

    def __init__(self, granted, message, epoch, primary, backup):
        self.granted = granted
        self.message = message
        self.epoch = epoch
        self.primary = primary
        self.backup = backup

    def __repr__(self):
        return 'Grant(%s, %r, epoch %d, primary %r, backup %r)' % (
            self.granted, self.message, self.epoch, self.primary, self.backup)


class Witness(object):
    """The configuration record and the rules that change it. Not thread-safe: the node serialises calls."""

    def __init__(self, initial_primary='', store=None):
        self.initial_primary = initial_primary   # '' : the first site that registers claiming it
        self.store = store
        self.epoch = 0
        self.primary = ''
        self.backup = ''
        self.incarnations = {}      # site -> the incarnation that holds its role in this epoch
        self.reason = ''
        self.history = []           # (epoch, primary, backup, reason): every configuration made
        self.behind = 0             # the newest epoch a caller has seen, once above the record (lost or rolled back)
        self.behind_told_by = ''
        self.saves = 0              # records saved (a save that raised is not counted)
        if store is not None:
            self._load(store.load())

    # -- queries ----------------------------------------------------------------------------
    def status(self):
        return self._grant(True, 'epoch %d' % self.epoch)

    def role_of(self, site):
        """'primary', 'backup' or '' for site in the current configuration."""
        return 'primary' if site == self.primary else 'backup' if site == self.backup and site else ''

    # -- requests ---------------------------------------------------------------------------
    def request(self, op, site, incarnation='', peer='', peer_incarnation='', claim=False, epoch=0, known_epoch=0):
        """Carry out one request; returns a Grant. Refusals change nothing. ``epoch`` (ADMIT): the epoch
        the joined site's state transfer was made in; 0: not said. ``known_epoch``: the newest epoch the
        caller has seen; above the record, it raises WitnessBehind (and so does every request after)."""
        if not site:
            return self._grant(False, 'a request must name its site')
        if known_epoch > max(self.epoch, self.behind):
            self.behind = known_epoch
            self.behind_told_by = site
            try:   # kept in the record: restarted with it unchanged, the witness is still behind
                self._save(self._record())
            except Exception:   # (refusing is what matters: it does so from memory, and is told again)
                pass
        if self.behind:
            raise WitnessBehind('the witness\'s record is at epoch %d but %s has seen epoch %d: the record was '
                                'lost or rolled back (restarted without its state file, or the file replaced); '
                                'it grants nothing, or it could grant an epoch twice, until its record is '
                                'restored' % (self.epoch, self.behind_told_by, self.behind))
        if op == Op.STATUS:
            return self.status()
        if op == Op.REGISTER:
            return self._register(site, incarnation, claim)
        if op == Op.PROMOTE:
            return self._promote(site, incarnation)
        if op == Op.EXCLUDE:
            return self._exclude(site, incarnation)
        if op == Op.ADMIT:
            return self._admit(site, incarnation, peer, peer_incarnation, epoch)
        return self._grant(False, 'unknown operation %r' % (op,))

    def _register(self, site, incarnation, claim):
        if self.epoch == 0:
            first = self.initial_primary or (site if claim else '')
            if not first:
                return self._grant(False, 'no primary yet: %s waits for the initial primary to register' % site)
            self._change(first, '', 'initial configuration', {})
        if site == self.primary:
            known = self.incarnations.get(site)
            if known is None and self.epoch == 1 and not self.backup:
                incarnations = dict(self.incarnations, **{site: incarnation})
                self._save(self._record(incarnations=incarnations))   # raises: nothing changed
                self.incarnations = incarnations
                return self._grant(True, '%s is the initial primary of epoch 1: serve' % site)
            if known == incarnation:
                return self._grant(True, '%s is the primary of epoch %d: serve' % (site, self.epoch))
            return self._grant(False, '%s restarted (incarnation %s, primary was %s): it holds no state; '
                                      'join the backup once it is promoted' % (site, incarnation, known))
        if site == self.backup and self.incarnations.get(site) != incarnation:
            self._change(self.primary, '', 'backup %s restarted: excluded' % site,
                         {self.primary: self.incarnations.get(self.primary)})
            return self._grant(False, '%s restarted: excluded from epoch %d; join %s'
                               % (site, self.epoch, self.primary))
        if site == self.backup:
            return self._grant(True, '%s is the backup of epoch %d' % (site, self.epoch))
        return self._grant(False, '%s is not in epoch %d: join %s' % (site, self.epoch, self.primary))

    def _promote(self, site, incarnation):
        if site and site == self.primary and not self.backup and self.incarnations.get(site) == incarnation:
            # Granted already, the answer lost (the caller timed out and asks again): saying so changes
            # nothing, where a refusal would leave the new primary waiting for its promotion for ever.
            return self._grant(True, '%s is the primary of epoch %d already' % (site, self.epoch))
        if site != self.backup or not site:
            return self._grant(False, '%s is not the backup of epoch %d (primary %r, backup %r): not promoted'
                               % (site, self.epoch, self.primary, self.backup))
        if self.incarnations.get(site) != incarnation:
            return self._grant(False, '%s incarnation %s is not the admitted one (%s): not promoted'
                               % (site, incarnation, self.incarnations.get(site)))
        deposed = self.primary
        self._change(site, '', '%s promoted, %s deposed' % (site, deposed), {site: incarnation})
        return self._grant(True, '%s is the primary of epoch %d; %s is deposed' % (site, self.epoch, deposed))

    def _exclude(self, site, incarnation):
        refused = self._not_primary(site, incarnation)
        if refused:
            return refused
        if not self.backup:
            # Already alone, still a new epoch: an ADMIT of this primary still in flight (its answer
            # lost, TCP delivering it after a partition healed) was made in an older epoch and is
            # refused when it comes. Answered "already alone" with no new epoch, it was granted after
            # the primary had released replies the joiner never held: it named a stale backup, promoted
            # at the next failure (review of the witness, session 33).
            self._change(site, '', '%s alone again (an ADMIT still in flight is void)' % site, {site: incarnation})
            return self._grant(True, '%s is already alone, in epoch %d now' % (site, self.epoch))
        excluded = self.backup
        self._change(site, '', '%s excluded by %s' % (excluded, site), {site: incarnation})
        return self._grant(True, '%s is alone in epoch %d; %s is excluded until it re-joins'
                           % (site, self.epoch, excluded))

    def _admit(self, site, incarnation, peer, peer_incarnation, epoch=0):
        refused = self._not_primary(site, incarnation)
        if refused:
            return refused
        if not peer or peer == site:
            return self._grant(False, 'ADMIT must name another site, got %r' % (peer,))
        if self.backup == peer and self.incarnations.get(peer) == peer_incarnation:
            return self._grant(True, '%s is already the backup of epoch %d' % (peer, self.epoch))
        if epoch and epoch != self.epoch:
            # Delivered late (its caller timed out, and TCP delivered it after a partition healed): the
            # configuration changed since the transfer, which may lack what changed (an exclusion of
            # that very joiner, another incarnation admitted). Granted, it named a site without the
            # state as the backup, to be promoted later.
            return self._grant(False, '%s\'s state transfer was made in epoch %d, and the configuration is '
                                      'epoch %d now: not admitted; it joins again' % (peer, epoch, self.epoch))
        self._change(site, peer, '%s admitted %s' % (site, peer), {site: incarnation, peer: peer_incarnation})
        return self._grant(True, '%s is the backup of epoch %d' % (peer, self.epoch))

    # -- internals --------------------------------------------------------------------------
    def _not_primary(self, site, incarnation):
        if site != self.primary:
            return self._grant(False, '%s is not the primary of epoch %d (primary %r): deposed'
                               % (site, self.epoch, self.primary))
        if self.incarnations.get(site) != incarnation:
            return self._grant(False, '%s incarnation %s is not the one serving (%s): deposed'
                               % (site, incarnation, self.incarnations.get(site)))
        return None

    def _change(self, primary, backup, reason, incarnations):
        """The one place where the configuration changes: a new epoch, saved before it is made, so a
        save that fails (disk full, an I/O error) raises with nothing changed. Changed first, a failed
        save left the new epoch in memory: the caller's retry was granted "already", and a restarted
        witness, back at the old epoch, granted that epoch again to the other site."""
        incarnations = {k: v for k, v in incarnations.items() if k and v is not None}
        self._save(self._record(epoch=self.epoch + 1, primary=primary, backup=backup, reason=reason,
                                incarnations=incarnations))
        self.epoch += 1
        self.primary, self.backup, self.reason = primary, backup, reason
        self.incarnations = incarnations
        self.history.append((self.epoch, primary, backup, reason))

    def _record(self, **changes):
        """The record as saved: the current one, with ``changes`` made."""
        return dict({'epoch': self.epoch, 'primary': self.primary, 'backup': self.backup, 'reason': self.reason,
                     'incarnations': self.incarnations, 'initial_primary': self.initial_primary,
                     'behind': self.behind, 'behind_told_by': self.behind_told_by}, **changes)

    def _save(self, record):
        if self.store is not None:
            self.store.save(record)
            self.saves += 1

    def _load(self, loaded):
        """Take the record read from the store; only "no saved state" is a fresh start. A record that is
        there but cannot be read (corrupt, or a read failing for a moment: EIO, EMFILE) raises
        ConfigError: a witness started afresh over it grants epochs granted already (review of session
        35: the node checked one read and the witness made a second, taking its failure for a start)."""
        state, why = loaded
        if state is None and why != NO_STATE:
            raise ConfigError('%s (refusing to start: it could grant an epoch twice)' % why)
        if state is None:
            self.reason = 'fresh witness (%s)' % why
            return
        self.epoch = int(state['epoch'])
        self.primary, self.backup = state['primary'], state['backup']
        self.incarnations = dict(state['incarnations'])
        self.reason = 'restored: %s' % state['reason']
        # A record a site had found behind stays so (review of the witness, session 33: the flag lived
        # in memory, and a second restart with the same record handed the first primary's role out again).
        self.behind = int(state.get('behind', 0) or 0)
        self.behind_told_by = str(state.get('behind_told_by', '') or '')

    def _grant(self, granted, message):
        return Grant(granted, message, self.epoch, self.primary, self.backup)
