"""What a replica's Recovery node does when its crash detector declares the peer failed."""
import enum

from .protocol import Role


class Step(enum.Enum):
    WITNESS_PROMOTE = "the witness's vote: this backup may take over (the old primary is deposed)"
    WITNESS_EXCLUDE = "the witness's vote: this primary may go on alone (the backup is excluded)"
    FAIL_SILENCE = 'kill whatever is left of the failed site'
    PROMOTE_AFTER = "fence the After against the old primary's checkpoints and make it ALONE"
    PROMOTE_PROTOCOL = "make the Protocol ALONE once it stored every checkpointed reply"
    AFTER_ALONE = 'stop checkpointing: release the replies held for the lost backup'


# What each step must wait for. No step binds the clients' topics: a replica's entry (its Protocol,
# or a SEC gate in front of it) is bound to them from set-up, so that a failover opens no new
# connection and needs no ROS master. That is safe: a Protocol that is still a backup queues the
# requests it receives (answering only those whose checkpointed reply it holds, refusing none). The
# Protocol executes them only once promoted, and it is promoted only once the
# failed site is silent (no two primaries) and its After is fenced against the old primary.
# With a witness, nothing happens before its vote: a backup that was excluded must not kill the
# primary (the only replica holding the state), and a deposed primary must not kill the new one.
WITNESS = (Step.WITNESS_PROMOTE, Step.WITNESS_EXCLUDE)
PREREQUISITES = {
    Step.WITNESS_PROMOTE: (),
    Step.WITNESS_EXCLUDE: (),
    Step.FAIL_SILENCE: WITNESS,
    Step.PROMOTE_AFTER: WITNESS,
    Step.PROMOTE_PROTOCOL: (Step.FAIL_SILENCE, Step.PROMOTE_AFTER),
    Step.AFTER_ALONE: WITNESS,
}

# Steps whose failure ends the plan: the rest must not run without them.
GATES = frozenset(WITNESS)


def plan(role, witness=False):
    """The steps when the peer of a replica in ``role`` has failed, as waves: the steps of a
    wave run in parallel, each wave once the previous one is complete. ``role`` None: this site is
    in no configuration of the witness (excluded or deposed): nothing to do."""
    if role == Role.BACKUP:
        steps = [Step.FAIL_SILENCE, Step.PROMOTE_AFTER, Step.PROMOTE_PROTOCOL]
        steps = ([Step.WITNESS_PROMOTE] if witness else []) + steps
    elif role == Role.PRIMARY:
        steps = ([Step.WITNESS_EXCLUDE] if witness else []) + [Step.FAIL_SILENCE, Step.AFTER_ALONE]
    else:
        steps = []   # ALONE: nobody left to lose
    return waves(steps)


def failed_steps(record):
    """The steps of a finished recovery record that failed, other than the witness's vote (a refused or
    unreachable witness raises its own alarm): '' if none, else 'STEP: why; ...'. A failover whose
    promotion failed leaves the service with nobody to serve it: never silent (alarm promotion_failed)."""
    gates = {g.name for g in GATES}
    return '; '.join('%s: %s' % (st['step'], st['detail']) for st in record.get('steps', ())
                     if not st['ok'] and st['step'] not in gates)


def incomplete(role, record):
    """(alarm kind, consequence) of a recovery whose steps failed (failed_steps), by the role this site had
    when its peer failed and the steps that failed. A backup's failed promotion leaves nobody to serve. A
    primary whose only failed step is FAIL_SILENCE (its failed backup could not be made silent: a power
    switch that never confirms) still serves, alone: AFTER_ALONE does not wait for FAIL_SILENCE. Saying
    "nobody may serve" there sent operators after the wrong site."""
    gates = {g.name for g in GATES}
    failed = {st['step'] for st in record.get('steps', ()) if not st['ok'] and st['step'] not in gates}
    if role == Role.PRIMARY and failed == {Step.FAIL_SILENCE.name}:
        return ('recovery_incomplete', 'this site goes on serving alone; the failed site was not made silent '
                'and may still run until an operator powers it off or it re-joins')
    return 'promotion_failed', 'nobody may serve until an operator or a re-join repairs it'


def start_plan():
    """The steps when the witness names this site the first primary at start: it serves from its own
    server's state (nothing to fence, nobody to wait for)."""
    return waves([Step.PROMOTE_AFTER, Step.PROMOTE_PROTOCOL])


def role_in(configuration_primary, configuration_backup, site):
    """This site's role in a witness configuration: ALONE, PRIMARY, BACKUP, or None (not in it)."""
    if site == configuration_primary:
        return Role.PRIMARY if configuration_backup else Role.ALONE
    if site and site == configuration_backup:
        return Role.BACKUP
    return None


def waves(steps):
    """Group steps into waves that respect PREREQUISITES (each step in the earliest wave possible)."""
    done, result, left = set(), [], list(steps)
    while left:
        wave = [s for s in left if all(p in done or p not in steps for p in PREREQUISITES[s])]
        if not wave:
            raise ValueError('circular prerequisites among %s' % left)
        result.append(wave)
        done.update(wave)
        left = [s for s in left if s not in wave]
    return result


def promoted_unasked(before, after, site, primary, granted, epoch):
    """Whether a configuration made this site the lone primary without this Recovery's grant: a PROMOTE
    of an earlier failover, answered too late for its Recovery (which gave it up, the site re-joining
    meanwhile) and delivered by TCP after a partition healed, deposes a working primary. The witness
    then names this site the primary while nothing here was promoted: the old primary fail-stops
    (deposed) and nobody serves. Such a site takes over as if its peer had failed (the witness grants
    its PROMOTE again: "already the primary")."""
    return before == Role.BACKUP and after == Role.ALONE and primary == site and granted != epoch


def role_after(role):
    """The replica's role once the plan for its peer's failure is carried out."""
    return Role.ALONE if role in (Role.BACKUP, Role.PRIMARY) else role


def same_process(age, since_heard, tolerance=0.05):
    """True if a process started ``age`` seconds ago could have sent a heartbeat last heard
    ``since_heard`` seconds ago.

    Guards fail-silence against a pid reused by an unrelated process after the site died. Both are
    durations, not dates: a process's start read as a date (psutil's create time) moves with a step of
    the wall clock after boot, and a launcher started before a step back was taken for a newer process
    (its fail-silence skipped) or, after a step forward, a new one for the launcher.
    """
    return age + tolerance >= since_heard


def unfenceable(remote, switch, tls):
    """Why this Recovery cannot make the failed peer silent, or None. ``remote``: {node name: URI} of the
    peer's nodes on another machine (no pid here to signal); ``switch``: whether a power switch of the
    peer's host is configured; ``tls``: whether this graph runs under TLS. Without a switch such a node
    is only asked to shut down over XML-RPC, which a frozen, hung or cut-off node never answers, and
    which a node under TLS refuses (tls shutdown_refused): the failover still goes on (the witness's
    epochs refuse the old primary's checkpoints and replies), but fail-silence is not enforced."""
    if switch or not remote:
        return None
    names = sorted(remote)
    shown = ', '.join('%s at %s' % (n, remote[n]) for n in names[:3]) + (' and %d more' % (len(names) - 3)
                                                                         if len(names) > 3 else '')
    return ('%d node(s) of the peer run on another machine (%s) and no power switch is configured '
            '(~power_switch): a failover can only ask them to shut down, which %s' % (
                len(names), shown, 'under TLS they refuse' if tls else 'a frozen, hung or cut-off node never answers'))


class OnHang(enum.Enum):
    """What a node does when its server (or state manager) hangs past its timeout."""
    FAIL_STOP = 'fail-stop the replica: its peer fences it and executes the request, once'
    WAIT = 'wait for the late answer, with an alarm: nobody else can execute the request'


class SiteRole(object):
    """A replica node's view of its site's role, from the witness's configurations (latched, in order).

    A hang of the server is a reason to fail-stop a replica only while a peer can take over: a
    site that serves alone (the witness excluded its backup, or none joined yet) holds the only
    copy of the state, and fail-stopping it turns a slow server into a stopped service that no
    re-join can restart (the joiner needs the state from it). Alone, the node waits for the late
    answer instead, with an alarm. A site in no replica (``site`` empty) always waits (there is
    nobody to fail over to); a site with no configuration heard (no witness) keeps fail-stop, as
    before the witness: its peer is assumed to be there.

    A configuration that still names a backup is not enough: the backup may have failed a moment
    before, the witness not told yet (campaign seed 15, segment 20: the backup's server killed, the
    machine stalled 10 s, then the primary's server call timed out; the primary fail-stopped, and
    both copies of the state were gone). So the site's crash detector is asked too (``peer_alive``:
    True, False, or None when it does not answer): only a peer heard alive now may take over. When
    unsure the node waits, and asks again while it waits (:meth:`on_hang` again).
    """

    def __init__(self, site):
        self.site = site
        self.role = None    # Role per the last configuration heard; None: none heard, or not in it
        self.epoch = None

    def on_configuration(self, epoch, primary, backup):
        self.epoch = epoch
        self.role = role_in(primary, backup, self.site)

    def alone(self):
        return self.role == Role.ALONE

    def on_hang(self, peer_alive=None):
        """What a hang of the server does now. peer_alive: a function answering whether the peer may
        take over (True, False, None: unknown), called only when the configuration leaves it to the peer;
        None: no detector to ask (the peer is assumed there)."""
        if not self.site or self.alone():
            return OnHang.WAIT
        if peer_alive is not None and peer_alive() is not True:
            return OnHang.WAIT
        return OnHang.FAIL_STOP

    def why_wait(self, peer_why):
        """Why a hang does not fail-stop this site (on_hang gave WAIT), in words; peer_why: the
        detector's last answer."""
        if not self.site:
            return 'not in a replica: nobody else can execute it'
        if self.alone():
            return 'site %s serves alone: a fail-stop would stop the service' % self.site
        return 'the peer of site %s cannot take over now (%s): a fail-stop could lose the only state' % (
            self.site, peer_why)
