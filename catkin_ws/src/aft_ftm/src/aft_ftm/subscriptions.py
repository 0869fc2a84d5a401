"""Which subscriptions have lost a publisher for good, and when to connect them again. No ROS here.

rospy connects a subscription to a publisher when the master tells it of the publisher, and then
never looks again. Several of its paths end a subscription's link to a live publisher for good
(rospy 1.15, ``rospy.impl.tcpros_pubsub`` and ``tcpros_base``):
- the publisher's header cannot be read (the connection reset or closed during the handshake, a TLS
  record refused after the client's side of the handshake ended): ``connect`` closes the transport
  as an "unknown error" and the subscriber never tries again;
- after a failed attempt, the publisher's XML-RPC API does not answer ``getPublications`` once:
  the transport is marked done but left in the subscription, which then counts it as connected, so
  later ``publisherUpdate`` calls skip that publisher too;
- the publisher closes a live connection (it kept a duplicate instead): the subscriber takes the
  end of stream as the publisher going away;
- ``requestTopic`` refused once: that publisher is given up.
The master tells the subscriber again only when the topic's set of publishers changes, so each of
these leaves a node that is up, registered and deaf to one publisher, with nothing said (CI: "the
car did not come up within 90 s: /board_b/controller_pid not connected").

:class:`Keeper` compares, at each look, the publishers the master knows for each subscribed topic
with the subscription's live connections. A publisher missing for ``grace`` seconds is connected
again, then again after a backoff that doubles up to ``backoff_max`` while it stays missing (a
powered-off host's publishers stay registered until someone cleans the master); one found connected
is forgotten. The ROS side (aft_ftm.ros.subscription_keeper) does the looking and the connecting.

The grace is for what nobody explains: rospy may still be connecting. A connection this node's TLS
layer knows was cut on purpose (a peer's certificate revoked, this node's own replaced certificate
revoked: a key rotation) has no such doubt, and waiting the grace was each subscription's pause in a
rotation (5.5 s measured). :meth:`Keeper.hurry` opens a window in which a publisher found missing is
connected again at the first look.
"""
GRACE = 5.0          # s: rospy connects a new publisher in milliseconds; its own retries start at 1 s
BACKOFF_FIRST = 4.0  # s between two attempts for one publisher, doubled up to BACKOFF_MAX
BACKOFF_MAX = 60.0


class Missing(object):
    """One (topic, publisher URI) a subscription lacks."""
    __slots__ = ('since', 'next_try', 'backoff', 'attempts')

    def __init__(self, since, grace, backoff):
        self.since, self.next_try, self.backoff, self.attempts = since, since + grace, backoff, 0


class Keeper(object):
    def __init__(self, grace=GRACE, backoff_first=BACKOFF_FIRST, backoff_max=BACKOFF_MAX):
        if not (grace >= 0 and backoff_first > 0 and backoff_max >= backoff_first):
            raise ValueError('grace %r, backoff %r..%r: expected grace >= 0 and 0 < first <= max'
                             % (grace, backoff_first, backoff_max))
        self.grace, self.backoff_first, self.backoff_max = grace, backoff_first, backoff_max
        self.missing = {}   # (topic, uri) -> Missing
        self.hurry_until = float('-inf')   # monotonic s: until then, no grace (connections cut on purpose)

    def hurry(self, until):
        """Until ``until`` (monotonic s), a publisher missing is connected again at once, without the
        grace; a publisher already tried waits its backoff still."""
        self.hurry_until = max(self.hurry_until, until)

    def hurrying(self, now):
        return now < self.hurry_until

    def step(self, now, wanted, have):
        """``wanted``: {topic: publisher URIs the master knows}; ``have``: {topic: URIs the
        subscription has a live or connecting transport to}. Returns [(topic, uri, missing for s,
        attempt number)] to connect again now."""
        lacking = {(topic, uri) for topic, uris in wanted.items() for uri in uris
                   if uri not in have.get(topic, ())}
        for key in list(self.missing):
            if key not in lacking:
                del self.missing[key]   # connected again, or no longer a publisher: forgotten
        due = []
        hurried = self.hurrying(now)
        for key in sorted(lacking):
            entry = self.missing.get(key)
            if entry is None:
                entry = self.missing[key] = Missing(now, 0.0 if hurried else self.grace, self.backoff_first)
            elif hurried and entry.attempts == 0:
                entry.next_try = min(entry.next_try, now)
            if now >= entry.next_try:
                entry.attempts += 1
                entry.next_try = now + entry.backoff
                entry.backoff = min(entry.backoff * 2, self.backoff_max)
                due.append((key[0], key[1], now - entry.since, entry.attempts))
        return due
