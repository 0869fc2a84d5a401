"""The Proxy's pending table: ids, watermark, re-sends; and what it logs of a failed call. No ROS master."""
from aft_ftm.proxy import PendingTable


def test_ids_are_unique_and_increasing_from_the_first_id():
    table = PendingTable(first_id=1000)
    ids = [table.open('/c', b'', 0).id for _ in range(5)]
    assert ids == [1000, 1001, 1002, 1003, 1004]


def test_watermark_is_the_oldest_unanswered_id():
    table = PendingTable(first_id=1)
    a, b, c = (table.open('/c', b'', 0) for _ in range(3))
    assert table.oldest_pending() == 1
    table.close(b.id, 'rb')
    assert table.oldest_pending() == 1
    table.close(a.id, 'ra')
    assert table.oldest_pending() == 3
    table.close(c.id, 'rc')
    assert table.oldest_pending() == 4     # nothing pending: the next id


def test_reply_wakes_the_waiting_call_and_a_late_duplicate_is_counted():
    table = PendingTable(first_id=1)
    entry = table.open('/c', b'x', 0)
    assert table.close(entry.id, 'reply') is entry
    assert entry.done.is_set() and entry.reply == 'reply'
    assert table.close(entry.id, 'again') is None and table.late_replies == 1


def test_due_returns_unanswered_requests_not_sent_for_a_period():
    table = PendingTable(first_id=1)
    a = table.open('/c', b'', now=0.0)
    b = table.open('/c', b'', now=0.4)
    assert [e.id for e in table.due(now=0.5, period=0.5)] == [a.id]
    assert a.sends == 2 and a.sent_at == 0.5
    assert [e.id for e in table.due(now=0.5, period=0)] == [a.id, b.id]    # all, on a new subscriber


def test_abandoned_request_is_not_resent():
    table = PendingTable(first_id=1)
    entry = table.open('/c', b'', 0)
    table.abandon(entry)
    assert table.due(now=10, period=0) == [] and len(table) == 0


def test_oldest_age_counts_from_the_first_send_not_the_last_resend():
    table = PendingTable(first_id=1)
    assert table.oldest_age(10.0) is None
    first = table.open('c', b'a', now=10.0)
    table.open('c', b'b', now=11.0)
    table.due(now=12.0, period=0.5)           # both re-sent at 12: their age does not restart
    assert table.oldest_age(13.0) == 3.0
    table.close(first.id, 'reply')
    assert table.oldest_age(13.0) == 2.0


def test_a_renumbered_request_takes_an_id_from_the_one_given_and_later_ones_follow_it():
    table = PendingTable(first_id=40)
    a, b = table.open('/c', b'a', 0), table.open('/c', b'b', 0)
    assert table.renumber(a.id, 5004) is a and a.id == 5004 and table.renumbered == 1
    assert table.renumber(b.id, 5004) is b and b.id == 5005    # above the ids taken since
    assert table.open('/c', b'c', 0).id == 5006
    assert table.renumber(40, 6000) is None                    # no longer waits under 40: a late message
    assert table.renumber(a.id, a.id) is None and table.renumber(b.id, 1 << 63) is None   # not above / absurd
    assert table.abandon(a) is a and table.abandon(a) is None and table.close(b.id, 'r') is b


def test_a_refusal_that_cannot_be_renumbered_says_why_while_the_call_waits():
    """A forged oldest_pending (no SEC) raised the replicas' watermark to 2**64 - 1: the refusals of this
    Proxy's calls name a first free id it cannot take. The call waits for its timeout: that is said, in
    words that name the request and the id, and nothing is said of a request that no longer waits."""
    table = PendingTable(first_id=100)
    a = table.open('/c', b'a', 0.0)
    assert table.renumber(a.id, (1 << 64) - 1) is None
    why = table.unrenumbered(a.id, (1 << 64) - 1)
    assert 'request %d waits' % a.id in why and 'past 2**63' in why and 'forged' in why
    assert 'not above it' in table.unrenumbered(a.id, a.id)
    assert table.unrenumbered(a.id + 7, 1 << 64) is None   # no such call: a late message, nothing to say


def test_a_servers_error_text_goes_to_the_caller_and_not_to_rosout(monkeypatch):
    """rospy logs an exception a service handler raises, text and traceback, on /rosout (in clear); the
    Proxy's own log of a server's failure names no text (the caller gets it; SEC seals it on the wire),
    and a fault of the Proxy itself is logged whole (review of session 42)."""
    import sys
    import rospy
    from aft_ftm.ros import proxy_node
    logged = []
    monkeypatch.setattr(rospy, 'logerr', logged.append)
    node = proxy_node.ProxyNode.__new__(proxy_node.ProxyNode)
    node.name = '/proxy'
    for error in (proxy_node.ServerError('cannot withdraw 5000 from a balance of 1234'), KeyError('its own bug')):
        try:
            raise error
        except Exception as e:
            node._on_error(e, *sys.exc_info())
    assert logged[0] == '/proxy: a call failed in the server (its error went to the caller only)'
    assert '1234' not in ' '.join(logged) and "'its own bug'" in logged[1] and 'Traceback' in logged[1]
