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
