"""A rospy node that registers again with a restarted ROS master (see aft_ftm.rejoin).

:func:`keep_registered` (``run_node`` calls it after ``init_node``) starts a daemon thread that asks
the master every ``period`` seconds (env ``AFT_MASTER_REJOIN_PERIOD``, 1 s by default; 0 turns it
off) its pid and whether it knows this node; when the master is a new one or does not know the node,
the node registers again, as rospy does at start-up
and under the same locks: every publication, subscription and service of the node. Each
subscription is then told its current publishers, as rospy takes a registration answer (queued
unless a publisher list came from the master meanwhile: then it is asked again, see
aft_ftm.ros.subscription_keeper.registration_answer). The private parameters the node read at start-up (through
aft_ftm.ros.params.param) are set again first, where the new master lacks them: tools that look at
a node's parameters (the campaign reads an After's ``mechanism``) find them; other parameters are
not restored.
"""
import os
import threading
import time

import rosgraph
import rospy
from rospy.impl.registration import get_service_manager, get_topic_manager

from ..errors import ConfigError
from ..rejoin import Lookup, Rejoin, judge, master_pid, misdirected_shutdown
from . import tls_transport
from .fencing import node_api
from .params import READ

DEFAULT_PERIOD = 1.0
CALL_TIMEOUT = 5.0   # s: a frozen master must not hold the thread for ever


def restore_parameters(master, caller_id, read):
    """The parameters this node read at start-up ({name: value}), set again where the master lacks
    them (a value changed on the live master since is left alone). Returns how many were set."""
    restored = 0
    for name, value in sorted(read.items()):
        code, _, present = master.hasParam(caller_id, name)
        if code == 1 and not present:
            master.setParam(caller_id, name, value)
            restored += 1
    return restored


def register_again(master, caller_id, node_uri):
    """Every registration of this node, again; returns (publications, subscriptions, services)."""
    from .subscription_keeper import _STATE, master_updates, registration_answer
    topics, services = get_topic_manager(), get_service_manager()
    updates = []
    with topics.lock, services.lock:   # rospy's own order (RegManager.start)
        publications, subscriptions = topics.get_publications(), topics.get_subscriptions()
        offered = services.get_services()
        for name, data_type in publications:
            master.registerPublisher(caller_id, name, data_type, node_uri)
        for name, data_type in subscriptions:
            sent_at = master_updates(name)
            code, _, publishers = master.registerSubscriber(caller_id, name, data_type, node_uri)
            if code == 1:
                updates.append((name, publishers, sent_at))
        for name, service_uri in offered:
            master.registerService(caller_id, name, service_uri, node_uri)
    manager = _STATE.get('reg_manager')
    node = node_api(node_uri, CALL_TIMEOUT)
    for name, publishers, sent_at in updates:
        if manager is not None:   # queued unless a publisher list came meanwhile (then asked again)
            registration_answer(manager, name, publishers, sent_at)
        else:   # (the keeper's recording is not in this process: as the master would tell it)
            node.publisherUpdate('/master', name, publishers)
    return len(publications), len(subscriptions), len(offered)


def _loop(period):
    caller_id, node_uri = rospy.get_caller_id(), rospy.core.get_node_uri()
    master = node_api(rosgraph.get_master_uri(), CALL_TIMEOUT)
    state = Rejoin()
    while not rospy.core.is_shutdown():
        time.sleep(period)
        if rospy.core.is_shutdown() or rospy.core.is_shutdown_requested():
            break
        own_service = dict(get_service_manager().get_services()).get(caller_id + '/get_loggers')
        try:
            pid = master_pid(master.getPid(caller_id))
            answer = master.lookupNode(caller_id, caller_id) if pid is not None else None
            service = (master.lookupService(caller_id, caller_id + '/get_loggers')
                       if own_service and answer is not None and answer[0] == 1 else None)
        except Exception:   # refused, reset, timed out: the master is not there
            pid = answer = service = None
        lookup = judge(answer, node_uri, service, own_service)
        again, message = state.step(pid, lookup)
        if lookup is Lookup.REPLACED and pid is not None and tls_transport.active():
            # under TLS, taken by a node that does not prove the name (an impostor: the master's API is
            # open): contested, and this node registers again (tls_transport.contest_name)
            try:
                if tls_transport.contest_name(answer[2]) is not None:
                    continue
            except Exception as e:   # never let this thread die: the name is contested at the next probe
                rospy.logwarn('%s: checking the node that took this name failed: %s', caller_id, e)
        if message:
            rospy.logwarn('%s: %s', caller_id, message)
        if again and not rospy.core.is_shutdown_requested():
            try:
                restored = restore_parameters(master, caller_id, dict(READ))
                counts = register_again(master, caller_id, node_uri)
                state.registered(pid)
                rospy.logwarn('%s: registered again with the ROS master: %d publications, %d subscriptions, '
                              '%d services; %d parameters set again', caller_id, *(counts + (restored,)))
            except Exception as e:   # the master went away again: the next probe tells
                rospy.logwarn('%s: registering again failed (%s); will retry', caller_id, e)


def period_from_env(environ=os.environ, name='AFT_MASTER_REJOIN_PERIOD', default=DEFAULT_PERIOD):
    text = environ.get(name, '')
    if not text:
        return default
    try:
        period = float(text)
    except ValueError:
        period = -1.0
    if not period >= 0:
        raise ConfigError('%s=%r: expected a number of seconds, 0 or more (0: off)' % (name, text))
    return period


def ignore_misdirected_shutdowns():
    """A master's shutdown request that names another node (aft_ftm.rejoin.misdirected_shutdown: it was
    meant for a dead process whose port this one now has) is refused with a warning; any other is
    obeyed, as rospy does. Once per process, any time before the request (``run_node`` calls it).
    ``AFT_OBEY_EVERY_SHUTDOWN=1`` keeps plain rospy's behaviour (a test's control)."""
    from rospy.impl import masterslave
    original = masterslave.ROSHandler.shutdown
    if os.environ.get('AFT_OBEY_EVERY_SHUTDOWN') == '1' or getattr(original, 'guarded', False):
        return

    def shutdown(handler, caller_id, msg=''):
        if misdirected_shutdown(msg, rospy.get_name()):
            rospy.logwarn('%s: a shutdown request from %s ignored: it names another node (%s), that had this '
                          'address before (a host or site back with its old address)', rospy.get_name(), caller_id, msg)
            return 1, 'ignored: %s is not the node named' % rospy.get_name(), 0
        return original(handler, caller_id, msg)
    shutdown.guarded = True
    masterslave.ROSHandler.shutdown = shutdown


def keep_registered(period=None):
    """Start the thread (once per process; after init_node). Returns it, or None when turned off.
    Raises ConfigError on a bad AFT_MASTER_REJOIN_PERIOD."""
    if period is None:
        period = period_from_env()
    if period <= 0 or getattr(keep_registered, 'thread', None) is not None:
        return getattr(keep_registered, 'thread', None)
    thread = threading.Thread(target=_loop, args=(period,), daemon=True, name='aft-master-rejoin')
    thread.start()
    keep_registered.thread = thread
    return thread
