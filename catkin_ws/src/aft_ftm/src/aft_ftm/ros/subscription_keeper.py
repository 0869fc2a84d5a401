"""Subscriptions connected again to the publishers rospy gave up on (see aft_ftm.subscriptions).

:func:`keep_subscriptions` (``run_node`` calls it before ``init_node``) records, for each topic, the
publishers the master last told the node of (every such list goes through rospy's
``RegManager.publisher_update``: the answer to ``registerSubscriber`` and each ``publisherUpdate``),
and starts a daemon thread that every ``period`` seconds (env ``AFT_SUBSCRIPTION_CHECK_PERIOD``, 2 s
by default; 0 turns it off) compares them with each subscription's transports: no call to the master,
nothing sent while every publisher is connected. A publisher lacking a live or connecting transport
for ``aft_ftm.subscriptions.GRACE`` seconds is connected again: a transport rospy left behind done is
removed, and the node's own ``publisherUpdate`` API is told the topic's publishers again (rospy then
connects the ones it lacks). Each time is logged as a warning that names the topic, the publisher and
how long it was missing; a registered publisher that does not answer its API is not connected to (a
host powered off: the master keeps it until someone cleans), and is looked at again after a backoff.
"""
import threading
import time

import rospy
from rospy.impl.registration import get_topic_manager

from ..subscriptions import Keeper
from .fencing import node_api
from .rejoin import period_from_env

DEFAULT_PERIOD = 2.0
CALL_TIMEOUT = 5.0    # s for the node's own publisherUpdate
PROBE_TIMEOUT = 1.0   # s for a publisher's getPublications before it is connected to again


def subscribed():
    """{topic: the subscription's rospy implementation} for this node."""
    manager = get_topic_manager()
    found = {}
    for name, _ in manager.get_subscriptions():
        impl = manager.get_subscriber_impl(name)
        if impl is not None:
            found[name] = impl
    return found


def transports(impl):
    """(URIs of the publishers the subscription has a live or connecting transport to, the transports
    rospy has ended but left in it)."""
    live, ended = set(), []
    for connection in list(impl.connections):
        if connection.done:
            ended.append(connection)
        else:
            live.add(connection.endpoint_id)
    return live, ended


_TOLD = {}   # topic -> the publisher URIs the master last told this node of
_TOLD_LOCK = threading.Lock()


def record_publisher_lists():
    """Wrap rospy's RegManager.publisher_update so that each list the master tells is kept (once per process)."""
    from rospy.impl.registration import RegManager
    original = RegManager.publisher_update
    if getattr(original, 'recorded', False):
        return

    def publisher_update(self, resolved_name, uris):
        with _TOLD_LOCK:
            _TOLD[resolved_name] = frozenset(uris)
        return original(self, resolved_name, uris)
    publisher_update.recorded = True
    RegManager.publisher_update = publisher_update


def told():
    with _TOLD_LOCK:
        return dict(_TOLD)


def connect_again(own_uri, topic, uri, impl, publishers):
    """The ended transports to uri removed from the subscription, then the node's own publisherUpdate
    told the topic's publishers. Returns how many ended transports were removed."""
    _, ended = transports(impl)
    removed = 0
    for connection in ended:
        if connection.endpoint_id == uri:
            try:
                impl.remove_connection(connection)
                removed += 1
            except (ValueError, OSError):   # rospy removed it meanwhile
                pass
    node_api(own_uri, CALL_TIMEOUT).publisherUpdate('/master', topic, sorted(publishers))
    return removed


def _loop(period, keeper):
    while not rospy.core.is_initialized():   # started before init_node
        if rospy.core.is_shutdown():
            return
        time.sleep(0.1)
    caller_id, own_uri = rospy.get_caller_id(), rospy.core.get_node_uri()
    silent = set()   # (topic, uri) already said not to answer
    names = {}       # publisher URI -> its node name, from the header of a transport it had (for the log)
    while not rospy.core.is_shutdown():
        time.sleep(period)
        if rospy.core.is_shutdown() or rospy.core.is_shutdown_requested():
            break
        subscriptions = subscribed()
        lists = told()
        wanted = {topic: lists[topic] for topic in subscriptions if topic in lists}
        have = {topic: transports(impl)[0] for topic, impl in subscriptions.items()}
        if len(names) > 1000:   # publishers come and go: bounded
            names.clear()
        for impl in subscriptions.values():
            for connection in list(impl.connections):
                caller = (getattr(connection, 'header', None) or {}).get('callerid')
                if caller:
                    names[connection.endpoint_id] = caller
        for topic, uri, missing_s, attempt in keeper.step(time.monotonic(), wanted, have):
            publisher = '%s (%s)' % (names[uri], uri) if uri in names else uri
            try:
                code, _, publications = node_api(uri, PROBE_TIMEOUT).getPublications(caller_id)
            except Exception as e:   # a dead registration (a host powered off): not this node's to clean
                if (topic, uri) not in silent:
                    silent.add((topic, uri))
                    rospy.loginfo('%s: subscription %s lacks publisher %s, which does not answer (%s): '
                                  'looked at again later', caller_id, topic, publisher, e)
                continue
            if code != 1 or topic not in {name for name, _ in publications}:
                continue   # no longer its publisher (the master's updates can arrive out of order)
            silent.discard((topic, uri))
            try:
                removed = connect_again(own_uri, topic, uri, subscriptions[topic], wanted[topic])
            except Exception as e:
                rospy.logwarn('%s: subscription %s lacks publisher %s; connecting again failed: %s',
                              caller_id, topic, publisher, e)
                continue
            rospy.logwarn('%s: subscription %s had no connection to publisher %s for %.1f s (rospy gave it up%s): '
                          'connecting again (attempt %d)', caller_id, topic, publisher, missing_s,
                          '; %d ended transport(s) removed' % removed if removed else '', attempt)


def keep_subscriptions(period=None, keeper=None):
    """Start the thread (once per process; before init_node, or before the subscriptions it keeps are
    made). Returns it, or None when turned off. Raises ConfigError on a bad AFT_SUBSCRIPTION_CHECK_PERIOD."""
    if period is None:
        period = period_from_env(name='AFT_SUBSCRIPTION_CHECK_PERIOD', default=DEFAULT_PERIOD)
    if period <= 0 or getattr(keep_subscriptions, 'thread', None) is not None:
        return getattr(keep_subscriptions, 'thread', None)
    record_publisher_lists()
    thread = threading.Thread(target=_loop, args=(period, keeper or Keeper()), daemon=True,
                              name='aft-subscription-keeper')
    thread.start()
    keep_subscriptions.thread = thread
    return thread
