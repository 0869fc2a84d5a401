"""The PBR After's outbox (its writer thread, aft_ftm.ros.pbr_nodes) with the publisher faked: the
parts of a state transfer given up are never written (review of stop 39). On a slow link each new
attempt queued behind the last one's unwritten parts; the joiner was never admitted and the outbox
grew without bound (50 MB in 30 s at 10 Mbit/s with the default 1 MiB parts)."""
import queue
import threading
import types

from aft_msgs.msg import Checkpoint

from aft_ftm.ros import pbr_nodes


def test_the_parts_of_a_transfer_given_up_are_dropped_and_the_live_ones_written(monkeypatch):
    after = pbr_nodes.PbrAfterNode.__new__(pbr_nodes.PbrAfterNode)
    after.name, after.outbox, after.parts_dropped = '/master/after', queue.Queue(), 0
    written = []
    after.ports = types.SimpleNamespace(publish=lambda port, cp: written.append((cp.seq, cp.part)))
    after.sender = types.SimpleNamespace(join_seq=7)         # the join under way: transfer 7
    after.outgoing = types.SimpleNamespace(seq=7)
    for seq in (5, 6):                                        # two attempts given up, 4 parts each unwritten
        for part in range(4):
            after.outbox.put(Checkpoint(seq=seq, full=True, part=part, parts=8))
    for part in range(4):
        after.outbox.put(Checkpoint(seq=7, full=True, part=part, parts=8))
    after.outbox.put(Checkpoint(seq=8))                       # a checkpoint queued behind the parts
    done = threading.Event()
    monkeypatch.setattr(pbr_nodes.rospy, 'is_shutdown', lambda: done.is_set())
    writer = threading.Thread(target=after._write_outbox, daemon=True)
    writer.start()
    after.outbox.join()
    done.set()
    writer.join(2.0)
    assert written == [(7, 0), (7, 1), (7, 2), (7, 3), (8, 0)]
    assert after.parts_dropped == 8


def test_a_join_whose_capture_outlived_the_protocols_suspension_is_given_up():
    """Review of group commit (session 33): the capture of a join's state may take two state timeouts,
    as long as the Protocol's suspension lease. Once the lease ran out, the Protocol forwarded a batch
    that straddled the join: its first reply released alone, the rest found the batch broken, and the
    only serving site fail-stopped. The join is now given up unless the Protocol is still held."""
    from aft_ftm.checkpoint import CheckpointSender, Role
    import threading as _threading
    told, joined = [], []
    for held in (False, True):
        after = pbr_nodes.PbrAfterNode.__new__(pbr_nodes.PbrAfterNode)
        after.lock = _threading.RLock()
        after.sender = CheckpointSender(Role.ALONE, first_seq=1)
        after.sender.join = lambda *a, **k: joined.append(a) or 3
        after.state_timeout, after.catch_up = 5.0, True
        after._capture_whole = lambda: (b'state', 0, None)
        after.side = types.SimpleNamespace(
            hold_protocol=lambda lease, held=held: None if held else 'its lease ran out: it resumed by itself',
            tell=lambda kind, detail, key=None: told.append((kind, detail)))
        after.encoder = types.SimpleNamespace(reset=lambda *a: None)
        after.recent = types.SimpleNamespace(replies=lambda: [])
        after.chunk_bytes, after.transfer_window = 1 << 20, 4
        after.first_seq, after.name, after.replaces = 1, '/master/after', ''
        after.ports = types.SimpleNamespace(publish=lambda port, cp: None)
        after._transfer(types.SimpleNamespace(site='slave', after='/slave/after', incarnation='i2'))
        if not held:
            assert joined == [] and told and told[0][0] == 'join_failed' and 'not held' in told[0][1], told
    assert len(joined) == 1   # held: the join goes on


def test_a_backup_the_witness_names_but_this_primary_does_not_checkpoint_to_is_excluded_loudly():
    """Review of the witness (session 33): an ADMIT given up on and carried out late named slave the
    backup of a primary that went on alone; nothing noticed, and slave, holding none of the replies
    released since, was promoted at the next failure. The primary's After now excludes it
    (backup_unfollowed), once: the exclusion's epoch makes that configuration past."""
    import threading as _threading
    from aft_ftm.checkpoint import CheckpointSender, Role
    after = pbr_nodes.PbrAfterNode.__new__(pbr_nodes.PbrAfterNode)
    after.lock, after.site, after.ack_timeout = _threading.RLock(), 'master', 1.0
    after.sender = CheckpointSender(Role.ALONE, first_seq=1)
    after.sender.epoch = 4
    after.joiner = None
    after.group = types.SimpleNamespace(stalled=lambda now, gap: None)
    after.batch_gap = 10.0
    after.configuration_seen = types.SimpleNamespace(epoch=5, primary='master', backup='slave', reason='admitted')
    told, asked = [], []
    after.side = types.SimpleNamespace(tell=lambda kind, detail, key=None: told.append(kind),
                                       alone=lambda act, why: asked.append(why),
                                       exclusion=lambda deposed: types.SimpleNamespace(epoch=6, message='excluded'))
    after._check_acks(None)
    assert told == ['backup_unfollowed'] and len(asked) == 1, (told, asked)
    after._exclude(asked[0])                      # granted: epoch 6, the unfollowed configuration is past
    told.clear(), asked.clear()
    after._check_acks(None)                       # the configuration of epoch 6 not heard yet: no new ask
    assert asked == [] and told == []
    # a primary checkpointing to its backup, or a join under way, is not hit
    after.configuration_seen = types.SimpleNamespace(epoch=7, primary='master', backup='slave', reason='admitted')
    after.joiner = ('slave', 'i2')
    after._check_acks(None)
    assert asked == []
