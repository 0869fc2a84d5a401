"""The witness's rules: each epoch granted to at most one primary; refusals change nothing. No ROS."""
import pytest

from aft_ftm.state_store import StateStore
from aft_ftm.witness import Op, Witness


def pair(store=None):
    """master serving, slave admitted: epoch 2."""
    w = Witness(store=store)
    assert w.request(Op.REGISTER, 'master', 'm1', claim=True).granted
    assert not w.request(Op.REGISTER, 'slave', 's1').granted
    assert w.request(Op.ADMIT, 'master', 'm1', peer='slave', peer_incarnation='s1').granted
    assert (w.epoch, w.primary, w.backup) == (2, 'master', 'slave')
    return w


def test_the_first_claimant_serves_from_its_own_state_and_nobody_else_does():
    w = Witness()
    assert not w.request(Op.REGISTER, 'slave', 's1').granted      # no primary yet: it waits
    assert w.epoch == 0
    assert w.request(Op.REGISTER, 'master', 'm1', claim=True).granted
    assert not w.request(Op.REGISTER, 'other', 'o1', claim=True).granted
    assert (w.epoch, w.primary, w.backup) == (1, 'master', '')


def test_only_the_backup_is_promoted_and_the_old_primary_is_deposed():
    w = pair()
    assert not w.request(Op.PROMOTE, 'master', 'm1').granted
    assert not w.request(Op.PROMOTE, 'slave', 's-old').granted     # another incarnation of the backup
    grant = w.request(Op.PROMOTE, 'slave', 's1')
    assert grant.granted and (grant.epoch, grant.primary, grant.backup) == (3, 'slave', '')
    assert not w.request(Op.EXCLUDE, 'master', 'm1').granted        # deposed: it must fail-stop
    assert not w.request(Op.PROMOTE, 'master', 'm1').granted        # no backup left to promote


@pytest.mark.parametrize('first,second', [(Op.EXCLUDE, Op.PROMOTE), (Op.PROMOTE, Op.EXCLUDE)])
def test_a_primary_and_its_backup_suspecting_each_other_one_wins(first, second):
    """Both slow, both suspect the other: whoever asks first gets the next epoch, the other is refused."""
    w = pair()
    asker = {Op.EXCLUDE: ('master', 'm1'), Op.PROMOTE: ('slave', 's1')}
    assert w.request(first, *asker[first]).granted
    refused = w.request(second, *asker[second])
    assert not refused.granted and refused.epoch == 3
    assert w.primary == asker[first][0] and w.backup == ''


def test_an_excluded_backup_can_never_be_promoted_until_it_rejoins():
    w = pair()
    assert w.request(Op.EXCLUDE, 'master', 'm1').granted
    assert not w.request(Op.PROMOTE, 'slave', 's1').granted
    assert w.request(Op.ADMIT, 'master', 'm1', peer='slave', peer_incarnation='s2').granted
    assert w.request(Op.PROMOTE, 'slave', 's2').granted


def test_a_primary_that_restarted_holds_no_state_and_may_not_serve():
    w = pair()
    refused = w.request(Op.REGISTER, 'master', 'm2', claim=True)
    assert not refused.granted and 'restarted' in refused.message
    assert (w.epoch, w.primary) == (2, 'master')                    # its backup is promoted when detected
    assert w.request(Op.REGISTER, 'master', 'm1').granted           # another node of the same start


def test_a_backup_that_restarted_is_excluded_at_once():
    w = pair()
    grant = w.request(Op.REGISTER, 'slave', 's2')
    assert not grant.granted and (w.epoch, w.backup) == (3, '')
    assert not w.request(Op.PROMOTE, 'slave', 's2').granted


def test_admit_names_another_site_and_is_idempotent():
    w = pair()
    assert not w.request(Op.ADMIT, 'master', 'm1', peer='master', peer_incarnation='m1').granted
    assert w.request(Op.ADMIT, 'master', 'm1', peer='slave', peer_incarnation='s1').granted
    assert w.epoch == 2
    assert not w.request(Op.ADMIT, 'slave', 's1', peer='master', peer_incarnation='m1').granted


def test_epochs_only_grow_and_each_names_one_primary():
    w = pair()
    w.request(Op.PROMOTE, 'slave', 's1')
    w.request(Op.ADMIT, 'slave', 's1', peer='master', peer_incarnation='m2')
    w.request(Op.EXCLUDE, 'slave', 's1')
    epochs = [h[0] for h in w.history]
    assert epochs == sorted(set(epochs)) and all(h[1] for h in w.history)


def test_a_restarted_witness_with_its_file_never_grants_an_epoch_twice(tmp_path):
    store = StateStore(str(tmp_path / 'witness.json'))
    pair(store)
    again = Witness(store=store)
    assert (again.epoch, again.primary, again.backup) == (2, 'master', 'slave')
    assert not again.request(Op.REGISTER, 'master', 'm9', claim=True).granted
    assert again.request(Op.PROMOTE, 'slave', 's1').epoch == 3


def test_a_request_without_a_site_is_refused():
    w = pair()
    assert not w.request(Op.PROMOTE, '', '').granted and w.epoch == 2


def test_a_promotion_whose_answer_was_lost_is_granted_again_and_changes_nothing():
    """Found by the simulation (tests/unit/test_replication_sim.py): the witness stalled, the backup's
    Recovery timed out and asked again; the first PROMOTE was granted meanwhile. Refused, the second
    left the new primary unpromoted, and nobody served for ever."""
    w = pair()
    assert w.request(Op.PROMOTE, 'slave', 's1').granted
    again = w.request(Op.PROMOTE, 'slave', 's1')
    assert again.granted and (again.epoch, again.primary, again.backup) == (3, 'slave', '')
    assert len(w.history) == 3
    assert not w.request(Op.PROMOTE, 'slave', 's2').granted         # another start of it holds nothing
    assert w.request(Op.ADMIT, 'slave', 's1', peer='master', peer_incarnation='m2').granted
    assert not w.request(Op.PROMOTE, 'slave', 's1').granted         # it has a backup: no promotion to repeat


class FailingStore(StateStore):
    """A store whose saves fail while ``failing`` (a full disk, an I/O error)."""
    failing = False

    def save(self, state):
        if self.failing:
            raise OSError(28, 'No space left on device')
        return super(FailingStore, self).save(state)


@pytest.mark.parametrize('op,site,kwargs', [(Op.PROMOTE, 'slave', {}), (Op.EXCLUDE, 'master', {}),
                                            (Op.ADMIT, 'master', {'peer': 'witness_site', 'peer_incarnation': 'w1'})])
def test_a_grant_whose_record_cannot_be_saved_changes_nothing_and_is_never_granted_later(tmp_path, op, site, kwargs):
    """Saved after the change, a failed save left the new epoch in memory: the caller's retry was
    granted "already", and the witness restarted from its file at the old epoch granted that epoch
    again to the other site (slave and master both primaries of epoch 3)."""
    store = FailingStore(str(tmp_path / 'witness.json'))
    w = pair(store)
    incarnation = {'slave': 's1', 'master': 'm1'}[site]
    store.failing = True
    with pytest.raises(OSError):
        w.request(op, site, incarnation, **kwargs)
    assert (w.epoch, w.primary, w.backup, len(w.history)) == (2, 'master', 'slave', 2)   # nothing changed
    with pytest.raises(OSError):   # the retry is not "granted already": it fails the same way
        w.request(op, site, incarnation, **kwargs)
    # Restarted from its file, the witness grants epoch 3 once, to whoever asks first, as it would have.
    store.failing = False
    again = Witness(store=store)
    assert again.epoch == 2
    first = again.request(Op.PROMOTE, 'slave', 's1')
    assert first.granted and first.epoch == 3
    assert not again.request(Op.EXCLUDE, 'master', 'm1').granted


def test_the_initial_primary_whose_registration_cannot_be_saved_is_not_told_to_serve(tmp_path):
    store = FailingStore(str(tmp_path / 'witness.json'))
    store.failing = True
    w = Witness(store=store)
    with pytest.raises(OSError):
        w.request(Op.REGISTER, 'master', 'm1', claim=True)
    assert w.epoch == 0 and not w.incarnations


def test_an_admission_delivered_late_is_refused_once_the_configuration_changed():
    """The primary's ADMIT timed out and was left on its old connection; TCP delivered it after a
    partition healed. Meanwhile the backup was excluded (or another start of it admitted): granted
    then, it named as the backup a site whose state is older than the configuration, to be promoted
    later. An ADMIT says the epoch of its state transfer, and is refused once that epoch is past."""
    w = pair()                                                             # epoch 2: master, slave s1
    assert w.request(Op.EXCLUDE, 'master', 'm1').epoch == 3                 # slave failed: excluded
    late = w.request(Op.ADMIT, 'master', 'm1', peer='slave', peer_incarnation='s1', epoch=2)
    assert not late.granted and 'made in epoch 2' in late.message and (w.epoch, w.backup) == (3, '')
    # Its join in this epoch is admitted; a late admission of its earlier start then changes nothing.
    assert w.request(Op.ADMIT, 'master', 'm1', peer='slave', peer_incarnation='s2', epoch=3).granted
    assert not w.request(Op.ADMIT, 'master', 'm1', peer='slave', peer_incarnation='s1', epoch=3).granted
    assert (w.epoch, w.backup, w.incarnations['slave']) == (4, 'slave', 's2')
    # The same ADMIT asked again (its answer lost) is granted, whatever epoch it was made in.
    assert w.request(Op.ADMIT, 'master', 'm1', peer='slave', peer_incarnation='s2', epoch=3).granted
    assert w.epoch == 4


@pytest.mark.parametrize('lost', ['file', 'rolled_back'])
def test_a_witness_whose_record_was_lost_or_rolled_back_grants_nothing_once_a_site_says_a_newer_epoch(tmp_path, lost):
    """Its record lost (restarted without its file) or rolled back (the file replaced by an old copy),
    a witness granted again epochs granted already: the excluded backup of an old record promoted while
    the real primary went on alone, two primaries in one epoch; a restarted site claiming a fresh
    witness served from an empty state. A request saying a newer epoch than the record stops it."""
    path = str(tmp_path / 'witness.json')
    w = pair(StateStore(path))                                    # epoch 2: master, backup slave
    old = open(path).read()
    assert w.request(Op.EXCLUDE, 'master', 'm1').granted          # epoch 3: master alone, slave excluded
    if lost == 'file':
        import os
        os.remove(path)
    else:
        with open(path, 'w') as f:
            f.write(old)
    w = Witness(store=StateStore(path))
    assert w.epoch == (0 if lost == 'file' else 2)
    # Without a word about epochs, the old rules grant what must not be (the flaw the check closes):
    if lost == 'rolled_back':
        assert w.request(Op.STATUS, 'slave', 's1').backup == 'slave'
    from aft_ftm.witness import WitnessBehind
    with pytest.raises(WitnessBehind, match='epoch 3'):
        w.request(Op.STATUS, 'master', 'm1', known_epoch=3)       # the primary says what it has seen
    record = (w.epoch, w.primary, w.backup)
    for op, site, kwargs in [(Op.PROMOTE, 'slave', dict(incarnation='s1', known_epoch=2)),
                             (Op.REGISTER, 'master', dict(incarnation='m2', claim=True)),
                             (Op.STATUS, 'slave', {})]:
        with pytest.raises(WitnessBehind):
            w.request(op, site, **kwargs)
    assert (w.epoch, w.primary, w.backup) == record               # nothing granted, nothing changed
    fresh = pair()
    assert fresh.request(Op.STATUS, 'master', 'm1', known_epoch=2).granted   # a known epoch not above: as before


def test_an_admit_still_in_flight_when_its_primary_went_on_alone_is_refused_when_it_comes():
    """Review of the witness (session 33): master, alone, sent ADMIT(slave) made in epoch e; its answer
    lost, master's ack timed out and it asked EXCLUDE, answered "already alone" with no new epoch, and
    released replies slave never held. The ADMIT, delivered late, was still of epoch e: granted, it
    named slave the backup, promoted at master's next failure with a stale state."""
    w = pair()
    assert w.request(Op.EXCLUDE, 'master', 'm1').granted              # slave excluded: epoch 3, master alone
    transfer_epoch = w.epoch                                           # slave joins again: its transfer
    late = dict(peer='slave', peer_incarnation='s1', epoch=transfer_epoch)
    alone = w.request(Op.EXCLUDE, 'master', 'm1')                      # the ADMIT unanswered: master goes on alone
    assert alone.granted and alone.epoch == transfer_epoch + 1 and (w.primary, w.backup) == ('master', '')
    refused = w.request(Op.ADMIT, 'master', 'm1', **late)              # the ADMIT, delivered now
    assert not refused.granted and w.backup == '' and 'not admitted' in refused.message
    assert not w.request(Op.PROMOTE, 'slave', 's1').granted


def test_a_witness_found_behind_is_still_behind_when_restarted_with_the_same_record(tmp_path):
    """Review of the witness (session 33): the flag lived in memory only. Restarted again with the same
    rolled-back record, the witness was no longer behind, and the site that had told it did not tell
    again (once per epoch number): a site relaunched claiming the first primary's role got it."""
    path = str(tmp_path / 'witness.json')
    w = pair(StateStore(path))                                    # epoch 2
    old = open(path).read()
    assert w.request(Op.EXCLUDE, 'master', 'm1').granted          # epoch 3
    with open(path, 'w') as f:
        f.write(old)                                              # rolled back to epoch 2
    from aft_ftm.witness import WitnessBehind
    w = Witness(store=StateStore(path))
    with pytest.raises(WitnessBehind):
        w.request(Op.STATUS, 'master', 'm1', known_epoch=3)
    again = Witness(store=StateStore(path))                       # restarted once more, the record unchanged
    with pytest.raises(WitnessBehind, match='master has seen epoch 3'):
        again.request(Op.REGISTER, 'slave', 's2', claim=True)


def test_a_record_that_is_there_but_cannot_be_read_stops_the_witness_instead_of_a_fresh_start(tmp_path):
    """Review of session 35: the node checked one read of the record and the witness made a second,
    taking its failure (EIO, EMFILE for a moment) for a fresh start at epoch 0: the first REGISTER was
    granted the primary's role again. Only "no saved state" is a fresh start now."""
    from aft_ftm.errors import ConfigError

    class Flaky(StateStore):
        def load(self):
            return None, 'saved state unreadable: [Errno 5] Input/output error'
    with pytest.raises(ConfigError, match='Input/output error.*could grant an epoch twice'):
        Witness('', Flaky(str(tmp_path / 'w.json')))
    fresh = Witness('', StateStore(str(tmp_path / 'none.json')))   # nothing saved yet: a fresh start
    assert fresh.epoch == 0 and fresh.reason == 'fresh witness (no saved state)'


def test_the_witness_node_answers_an_unknown_operation_with_a_whole_configuration_and_says_when_it_cannot_save(
        tmp_path, monkeypatch):
    """Review of session 35: an unknown operation was answered outside the lock (an epoch half made:
    e+1 with the old primary, taken by a site for a second content of e+1: a false witness_behind); a
    record that cannot be saved was only logged (callers see the witness unreachable, its diagnostics
    said OK). The answer is built under the lock; a failed save raises witness_unsaved once and the
    diagnostics say ERROR until a save succeeds."""
    import threading
    import rospy
    from aft_msgs.srv import WitnessRequest
    from aft_ftm.ros.witness_node import WitnessNode
    from fakes import FakePublisher

    class Lock(object):
        """A lock that checks it is held whenever the configuration is read."""
        def __init__(self):
            self.inner, self.held = threading.Lock(), False

        def __enter__(self):
            self.inner.acquire()
            self.held = True

        def __exit__(self, *exc):
            self.held = False
            self.inner.release()

    class Watched(Witness):
        lock = None

        def __getattribute__(self, name):
            if name in ('epoch', 'primary', 'backup') and Watched.lock is not None:
                assert Watched.lock.held, 'the configuration read outside the lock'
            return Witness.__getattribute__(self, name)
    monkeypatch.setattr(rospy, 'get_name', lambda: '/aft/witness')
    monkeypatch.setattr(rospy.Time, 'now', staticmethod(lambda: rospy.Time(0)))
    node = WitnessNode.__new__(WitnessNode)
    store = FailingStore(str(tmp_path / 'w.json'))
    node.witness = Watched('', store)
    node.lock, node.alarms, node.persistent, node.told_behind, node.unsaved = Lock(), FakePublisher(), True, 0, None
    node._publish = lambda: None
    Watched.lock = node.lock
    answer = node._on_request(WitnessRequest(op=99, site='x'))
    assert not answer.granted and answer.message == 'unknown operation 99'
    Watched.lock = None
    store.failing = True
    for _ in range(2):
        with pytest.raises(rospy.ServiceException, match='could not save its record'):
            node._on_request(WitnessRequest(op=Op.REGISTER.value, site='master', incarnation='1@1', claim=True))
    assert [a.kind for a in node.alarms.published] == ['witness_unsaved']
    report = node._health()
    assert report.level.name == 'ERROR' and 'cannot be saved' in report.message
    store.failing = False                                          # the disk has room again: saved, OK
    assert node._on_request(WitnessRequest(op=Op.REGISTER.value, site='master', incarnation='1@1', claim=True)).granted
    assert node.unsaved is None and node._health().level.name != 'ERROR'



def test_under_tls_only_a_site_s_own_node_speaks_for_it_to_the_witness():
    """Review of session 41: the witness took req.site and req.known_epoch as sent, from any caller the
    policy allowed: a STATUS with known epoch 2^64-1 left it behind for good, a PROMOTE of the backup
    forced a failover. A STATUS telling no later epoch stays anyone's (operators, rejoin)."""
    from aft_ftm.witness import Op, speaks_for
    assert speaks_for(Op.STATUS, 'rejoin', '/operator', 0, 5) is None
    assert speaks_for(Op.STATUS.value, 'checker', '/checker', 5, 5) is None
    assert 'only a node of that site' in speaks_for(Op.STATUS, 'x', '/operator', 2 ** 64 - 1, 5)
    assert speaks_for(Op.STATUS, 'master', '/master/after', 9, 5) is None        # a site telling it is behind
    for op in (Op.PROMOTE, Op.EXCLUDE, Op.ADMIT, Op.REGISTER):
        assert speaks_for(op, 'slave', '/slave/recovery', 0, 5) is None
        assert speaks_for(op, 'slave', '/slave_evil/recovery', 0, 5) is not None   # a prefix is no namespace
        assert speaks_for(op, 'slave', '/master/recovery', 0, 5) is not None
        assert speaks_for(op, 'slave', '/operator', 0, 5) is not None
        assert speaks_for(op, '', '/x/y', 0, 5) is not None and speaks_for(op, 'a/b', '/a/b/c', 0, 5) is not None
