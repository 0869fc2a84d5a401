"""Subscriptions connected again to the publishers rospy gave up on (see aft_ftm.subscriptions).

:func:`keep_subscriptions` (``run_node`` calls it before ``init_node``) records, for each topic, the
publishers the master last told the node of (the answer to ``registerSubscriber``, through rospy's
``RegManager.publisher_update``, and each ``publisherUpdate``, empty lists included; a registration
answer older than a list taken while it was out is dropped, see record_publisher_lists), and starts a
daemon thread that every ``period`` seconds (env ``AFT_SUBSCRIPTION_CHECK_PERIOD``, 2 s by default; 0
turns the thread off, not the mending of that race) compares them with each subscription's transports and the connections rospy is making:
no call to the master, nothing sent while every publisher is connected. A publisher lacking a live,
connecting or being-made transport for ``aft_ftm.subscriptions.GRACE`` seconds is connected again: a
transport rospy left behind done is removed, and rospy's own connecting thread is started for that
publisher. Each time is logged as a warning that names the topic, the publisher and how long it was
missing; a registered publisher that does not answer its API, or no longer publishes the topic, is not
connected to (a host powered off: the master keeps it until someone cleans), and is looked at again
after a backoff. Each publisher's API is asked at most once per look.
"""
import threading
import time

import rospy
from rospy.impl.registration import get_topic_manager

from ..subscriptions import Keeper
from .fencing import node_api
from .ports import publisher_callers
from .rejoin import period_from_env

DEFAULT_PERIOD = 2.0
PROBE_TIMEOUT = 1.0   # s for a publisher's getPublications before it is connected to again
HURRY_PERIOD = 0.1    # s between two looks while hurried (hurry())
_RUNNING = {}         # 'keeper': the thread's Keeper; 'wake': an Event that ends its wait


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


_TOLD = {}            # topic -> the publisher URIs the master last told this node of
_CONNECTING = set()   # (topic, uri) rospy is connecting now (its requestTopic retries for up to 32 s)
_STATE = {}           # 'reg_manager': rospy's RegManager, seen at its first publisher list
_UPDATES = {}         # topic -> how many publisherUpdate calls (the master's) this node has taken for it
_REGISTERING = {}     # topic -> _UPDATES[topic] when this node's registration of it was sent
_LOCAL = threading.local()   # .from_api: the publisher list at hand came through publisherUpdate
# Reentrant: a publisherUpdate is counted and queued in one hold (rospy's handler calls back into
# RegManager.publisher_update); rospy's own locks are taken inside it, never the other way round.
_LOCK = threading.RLock()
ASK_TRIES = 6         # fresh registrations asked for a list no publisherUpdate overtook
ASK_TIMEOUT = 5.0     # s for each


def master_updates(topic):
    """How many publisher lists the master has sent this node for topic, through its publisherUpdate
    API. A registration answer is in doubt if this number moved while the registration was out."""
    with _LOCK:
        return _UPDATES.get(topic, 0)


def _queue(manager, topic, uris):
    """(under _LOCK) The list recorded and handed to rospy, which connects to its new publishers."""
    _TOLD[topic] = frozenset(uris)
    _STATE['queue'](manager, topic, uris)


def registration_answer(manager, topic, uris, sent_at):
    """The answer to a registerSubscriber sent when ``master_updates(topic)`` was ``sent_at``: queued if
    no publisherUpdate for topic came since; otherwise it is in doubt and a fresh one is asked for
    (:func:`_ask_again`, in a thread). Returns True if it was queued."""
    with _LOCK:
        if _UPDATES.get(topic, 0) == sent_at:
            _queue(manager, topic, uris)
            return True
    threading.Thread(target=_ask_again, args=(manager, topic, sorted(uris)), daemon=True,
                     name='aft-ask-again-%s' % topic).start()
    return False


def _ask_again(manager, topic, doubted):
    """Register the subscription again (rosmaster takes it as the same registration, and tells nobody)
    until an answer comes back with no publisherUpdate for topic taken meanwhile: that one is the
    master's newest list, and is queued. A publisherUpdate taken while a registration is out may be
    newer than its answer (a publisher registered meanwhile) or older (one queued for this node's
    URI before, held up in the master's three workers by nodes that do not answer: a subscription
    made again, a node started on a dead one's port, a master started again); neither may win
    unasked."""
    caller_id = rospy.get_caller_id()
    for attempt in range(ASK_TRIES):
        impl = get_topic_manager().get_subscriber_impl(topic)
        if impl is None or rospy.core.is_shutdown():
            return   # unsubscribed meanwhile: nothing to tell
        sent_at = master_updates(topic)
        master = node_api(manager.master_uri, ASK_TIMEOUT)
        try:
            # Never for a name the master now gives another process (this node frozen or cut off while it
            # asked, and replaced): registering would hand the name back, and the master would tell the
            # replacement to shut down (review of the plumbing, session 36).
            known = master.lookupNode(caller_id, caller_id)
            if known[0] == 1 and known[2] != manager.uri:
                rospy.logwarn('%s: the master gives this name to %s now: %s is not registered again',
                              caller_id, known[2], topic)
                return
            code, message, uris = master.registerSubscriber(caller_id, topic, impl.type, manager.uri)
            if code == 1 and get_topic_manager().get_subscriber_impl(topic) is None:
                master.unregisterSubscriber(caller_id, topic, manager.uri)   # unsubscribed meanwhile: undone
                return
        except Exception as e:   # the master is away: asked again after a while
            code, message, uris = -1, str(e), []
        if code == 1:
            with _LOCK:
                if _UPDATES.get(topic, 0) == sent_at:
                    _queue(manager, topic, uris)
                    rospy.loginfo('%s: the registration answer for %s (publishers %s) was in doubt (a publisher '
                                  'list came while it was out): asked again, publishers %s',
                                  caller_id, topic, doubted, sorted(uris))
                    return
        time.sleep(min(0.05 * 2 ** attempt, 1.0))
    rospy.logwarn('%s: no registration answer for %s came without a publisher list overtaking it in %d tries '
                  '(last: %s): the list the master sent last stands, and the subscription keeper looks on',
                  caller_id, topic, ASK_TRIES, message if code != 1 else 'overtaken')


def record_publisher_lists():
    """Keep each publisher list the master tells this node, and which connections rospy is making (once
    per process). A subscription's first list comes with its registration (RegManager.publisher_update),
    later ones through the node's publisherUpdate API, which rospy passes on only when it names a
    publisher: an empty list (the last publisher gone) is recorded there.

    It also mends a race in rospy (1.15, ``RegManager.reg_added`` and ``start``): a subscription's
    registration answer is queued after the registerSubscriber call returns, and the newest list queued
    wins. A publisher that registers while that call is out is told to this node by the master's
    publisherUpdate, which can be taken before the answer, a list made earlier, is queued: the answer
    then replaces it, and rospy never connects to that publisher; the master does not tell again
    (CI: "the car did not come up within 90 s: /board_a/controller_pid not connected (/board_a/pid_raw
    to /board_a/cycle_after)", with no warning logged anywhere). Here a registration answer is queued
    only if no publisherUpdate for its topic was taken since the registration was sent (counted and
    queued under one lock); otherwise the master is asked again (:func:`registration_answer`)."""
    from rospy.impl.masterslave import ROSHandler
    from rospy.impl.registration import Registration, RegManager
    if getattr(RegManager.publisher_update, 'recorded', False):
        return
    update, told, connect = RegManager.publisher_update, ROSHandler.publisherUpdate, RegManager._connect_topic_thread
    added, start, run = RegManager.reg_added, RegManager.start, RegManager.run
    _STATE['queue'] = update

    def publisher_update(self, resolved_name, uris):
        with _LOCK:
            _STATE['reg_manager'] = self
            if getattr(_LOCAL, 'from_api', False):
                _queue(self, resolved_name, uris)
                return None
            # a subscription made after start() was called is registered by it too: from 0 updates
            sent_at = _REGISTERING.get(resolved_name, 0 if _STATE.get('starting') else None)
            if sent_at is None:   # not a registration answer of the paths watched: as rospy does
                _queue(self, resolved_name, uris)
                return None
        registration_answer(self, resolved_name, uris, sent_at)
        return None

    def publisher_update_api(self, caller_id, topic, publishers):
        with _LOCK:   # counted and queued in one hold: no answer checked in between is queued after it
            _UPDATES[topic] = _UPDATES.get(topic, 0) + 1
            _LOCAL.from_api = True
            try:
                answer = told(self, caller_id, topic, publishers)
            finally:
                _LOCAL.from_api = False
            if answer and answer[0] == 1 and isinstance(publishers, (list, tuple)):   # (validated by rospy)
                _TOLD[topic] = frozenset(publishers)
        return answer

    def mark(topics):
        with _LOCK:
            marked = [t for t in topics if t not in _REGISTERING]
            for topic in marked:
                _REGISTERING[topic] = _UPDATES.get(topic, 0)
        return marked

    def unmark(marked):
        with _LOCK:
            for topic in marked:
                _REGISTERING.pop(topic, None)

    def reg_added(self, resolved_name, data_type_or_uri, reg_type):
        marked = mark([resolved_name] if reg_type == Registration.SUB else [])
        try:
            return added(self, resolved_name, data_type_or_uri, reg_type)
        finally:
            unmark(marked)

    def start_registering(self, *args, **kwargs):
        # rospy's start registers what the node made before init_node's registration, then spins in
        # run() for the life of the node: the marks end where run begins
        _STATE['start_marked'] = mark([name for name, _ in get_topic_manager().get_subscriptions()])
        _STATE['starting'] = True
        try:
            return start(self, *args, **kwargs)
        finally:
            registered()

    def registered():
        _STATE.pop('starting', None)
        unmark(_STATE.pop('start_marked', []))

    def run_registered(self, *args, **kwargs):
        registered()
        return run(self, *args, **kwargs)

    def connect_topic_thread(self, topic, uri):
        with _LOCK:
            _CONNECTING.add((topic, uri))
        try:
            return connect(self, topic, uri)
        finally:
            with _LOCK:
                _CONNECTING.discard((topic, uri))
    publisher_update.recorded = True
    RegManager.publisher_update = publisher_update
    RegManager.reg_added = reg_added
    RegManager.start = start_registering
    RegManager.run = run_registered
    ROSHandler.publisherUpdate = publisher_update_api
    RegManager._connect_topic_thread = connect_topic_thread


def told():
    """({topic: publisher URIs}, {(topic, uri) being connected by rospy})."""
    with _LOCK:
        return dict(_TOLD), set(_CONNECTING)


def connect_again(topic, uri, impl):
    """The ended transports to uri removed from the subscription, then rospy's own connecting thread
    started for that one publisher (as its registration manager does for each publisher it is told of;
    not through its queue of updates, which keeps only the newest per topic: a list the master sent
    meanwhile must not be dropped). Returns how many ended transports were removed."""
    _, ended = transports(impl)
    removed = 0
    for connection in ended:
        if connection.endpoint_id == uri:
            try:
                impl.remove_connection(connection)
                removed += 1
            except (ValueError, OSError):   # rospy removed it meanwhile
                pass
    with _LOCK:
        manager = _STATE.get('reg_manager')
    if manager is None:
        raise RuntimeError('rospy has told this node of no publisher list yet')
    threading.Thread(target=manager._connect_topic_thread, args=(topic, uri), daemon=True,
                     name='aft-connect-%s' % topic).start()
    return removed


def hurry(seconds):
    """For the next ``seconds``, look every HURRY_PERIOD and connect a missing publisher again at
    once (aft_ftm.subscriptions.Keeper.hurry): this node's TLS layer knows its connections were cut on
    purpose and that no rospy retry is coming. Returns whether a keeper runs in this process."""
    keeper = _RUNNING.get('keeper')
    if keeper is None:
        return False
    keeper.hurry(time.monotonic() + seconds)
    _RUNNING['wake'].set()
    return True


def _loop(period, keeper, wake):
    while not rospy.core.is_initialized():   # started before init_node
        if rospy.core.is_shutdown():
            return
        time.sleep(0.1)
    caller_id = rospy.get_caller_id()
    silent = set()   # (topic, uri) already said not to answer
    names = {}       # publisher URI -> its node name, from the header of a transport it had (for the log)
    while not rospy.core.is_shutdown():
        wake.wait(HURRY_PERIOD if keeper.hurrying(time.monotonic()) else period)
        wake.clear()
        if rospy.core.is_shutdown() or rospy.core.is_shutdown_requested():
            break
        try:
            _look(keeper, caller_id, silent, names)
        except Exception as e:   # never let the keeper die silently
            rospy.logerr('%s: the subscription keeper failed a look (it goes on): %s', caller_id, e)


def _look(keeper, caller_id, silent, names):
    subscriptions = subscribed()
    lists, connecting = told()
    wanted = {topic: lists[topic] for topic in subscriptions if topic in lists}
    # a publisher rospy is connecting to now counts as had: a second connection would replace the first
    have = {topic: transports(impl)[0] | {uri for t, uri in connecting if t == topic}
            for topic, impl in subscriptions.items()}
    if len(names) > 1000:   # publishers come and go: bounded
        names.clear()
    if len(silent) > 1000:
        silent.clear()
    for impl in subscriptions.values():
        names.update(publisher_callers(impl))
    publications = {}   # uri -> its publications, or the error: each publisher asked once per look
    for topic, uri, missing_s, attempt in keeper.step(time.monotonic(), wanted, have):
        publisher = '%s (%s)' % (names[uri], uri) if uri in names else uri
        if uri not in publications:
            try:
                code, _, topics = node_api(uri, PROBE_TIMEOUT).getPublications(caller_id)
                publications[uri] = {name for name, _ in topics} if code == 1 else set()
            except Exception as e:   # a dead registration (a host powered off): not this node's to clean
                publications[uri] = e
        found = publications[uri]
        if isinstance(found, Exception):
            if (topic, uri) not in silent:
                silent.add((topic, uri))
                rospy.loginfo('%s: subscription %s lacks publisher %s, which does not answer (%s): '
                              'looked at again later', caller_id, topic, publisher, found)
            continue
        if topic not in found:
            continue   # no longer its publisher (the master's updates can arrive out of order)
        silent.discard((topic, uri))
        try:
            removed = connect_again(topic, uri, subscriptions[topic])
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
    record_publisher_lists()   # (rospy's race mended, with the keeper or without)
    if period <= 0 or getattr(keep_subscriptions, 'thread', None) is not None:
        return getattr(keep_subscriptions, 'thread', None)
    keeper = keeper or Keeper()
    _RUNNING.update(keeper=keeper, wake=threading.Event())
    thread = threading.Thread(target=_loop, args=(period, keeper, _RUNNING['wake']), daemon=True,
                              name='aft-subscription-keeper')
    thread.start()
    keep_subscriptions.thread = thread
    return thread
