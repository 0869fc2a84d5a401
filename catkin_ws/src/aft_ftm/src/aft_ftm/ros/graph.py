"""What the ROS master knows of the graph, for the nodes and tools that launch and wire others: what
is registered, what is connected, dead registrations, a roscore of one's own. Uses the master API
only (no rospy node)."""
import os
import xmlrpc.client

import rosgraph

from ..sites import Site, wait_until


def missing_from_graph(services=(), subscriptions=(), caller='/aft_deployment'):
    """The services and (topic, node) subscriptions not yet registered with the master."""
    try:
        _, subs, srvs = rosgraph.Master(caller).getSystemState()
    except Exception as e:   # master not up yet
        return ['master: %s' % e]
    have_srvs = {name for name, _ in srvs}
    have_subs = {(topic, node) for topic, nodes in subs for node in nodes}
    return ([s for s in services if s not in have_srvs] +
            ['%s subscribed by %s' % s for s in subscriptions if s not in have_subs])


def master_answers(timeout, caller='/aft_probe'):
    """(True, '') if the ROS master answers getPid within ``timeout`` s, else (False, why). A master
    whose host is cut off is noticed within the timeout (rosgraph.Master has none)."""
    from .fencing import node_api
    uri = rosgraph.get_master_uri()
    try:
        code, message, _ = node_api(uri, timeout).getPid(caller)
    except (OSError, xmlrpc.client.Error) as e:
        return False, '%s: %s' % (uri, e)
    return (code == 1), ('' if code == 1 else '%s: %s' % (uri, message))


def publisher_links(node, caller='/aft_deployment'):
    """For each topic node publishes: (the subscribers the master knows, the ones node is connected
    to), or None when node cannot be asked (not up yet, or going away)."""
    from .fencing import node_api
    try:
        master = rosgraph.Master(caller)
        pubs, subs, _ = master.getSystemState()
        code, _, bus = node_api(master.lookupNode(node), 1.0).getBusInfo(caller)
    except Exception:   # not up yet, or going away
        return None
    if code != 1:
        return None
    connected = {}
    for info in bus:   # [id, destination, direction, transport, topic, connected, ...]
        if info[2] == 'o':
            connected.setdefault(info[4], set()).add(info[1])
    subscribers = {t: set(n) - {node} for t, n in subs}
    return {topic: (subscribers.get(topic, set()), connected.get(topic, set()))
            for topic, publishers in pubs if node in publishers}


def unwired(node, caller='/aft_deployment'):
    """{topic: the subscribers the master knows that node's publisher is not connected to} for the
    topics where some are missing ({} when it is wired), or None when node cannot be asked."""
    links = publisher_links(node, caller)
    if links is None:
        return None
    return {topic: subscribers - connected for topic, (subscribers, connected) in links.items()
            if len(connected) < len(subscribers)}


def wired(node, caller='/aft_deployment'):
    """True when every publisher of node is connected to every subscriber the master knows for its
    topic (a subscription registered is not yet a connection: the subscriber connects afterwards)."""
    return unwired(node, caller) == {}


def wait_for_graph(services=(), subscriptions=(), timeout=60.0, abort=None):
    """Wait until everything is registered; returns what is still missing (empty on success).
    ``abort()``, if given, returns why waiting is pointless (a launch that exited): that reason is
    returned at once."""
    why = []

    def done():
        reason = abort() if abort is not None else None
        if reason:
            why.append(reason)
            return True
        return not missing_from_graph(services, subscriptions)
    wait_until(done, timeout, 0.05)
    return why or missing_from_graph(services, subscriptions)


def clean_dead_nodes(caller='/aft_deployment', timeout=0.5):
    """Unregister from the master every node that no longer answers (as ``rosnode cleanup``).

    A node killed by a signal leaves its registrations behind. If a new process later binds the
    dead node's XML-RPC port, the master's "new node registered with the same name" shutdown call
    for the dead node reaches that new process and stops it: so clean up after every stop.
    """
    from .fencing import node_api
    try:
        master = rosgraph.Master(caller)
        pubs, subs, srvs = master.getSystemState()
    except Exception:   # no master: nothing to clean
        return []
    names = sorted({n for _, nodes in list(pubs) + list(subs) + list(srvs) for n in nodes} - {'/rosout', caller})

    uris = {}
    for name in names:   # the master's proxy is not shared between threads: looked up here, in turn
        try:
            uris[name] = master.lookupNode(name)
        except Exception:
            uris[name] = None

    def silent(name, patience):
        if uris[name] is None:
            return True
        try:
            node_api(uris[name], patience).getPid(caller)
            return False
        except Exception:
            return True
    # A node that does not answer in time gets a second, longer chance: a live node slow under load,
    # cleaned up, loses every registration (it registers again within a second, aft_ftm.ros.rejoin,
    # but its peers miss it meanwhile). Each node has a proxy of its own: they are asked at once.
    import concurrent.futures
    with concurrent.futures.ThreadPoolExecutor(16, thread_name_prefix='clean') as pool:
        dead = [n for n, gone in zip(names, pool.map(lambda n: silent(n, timeout), names)) if gone]
        dead = [n for n, gone in zip(dead, pool.map(lambda n: silent(n, 4 * timeout), dead)) if gone]
    if dead:
        unregister(master, dead, uris)
    return dead


def unregister(master, dead, uris, master_as=rosgraph.Master):
    """Every registration of the dead nodes removed from the master (what rosnode's
    cleanup_master_blacklist does), each one on its own: a registration gone meanwhile (the node's
    site stopping, another cleanup) is skipped. rosnode's raised out of the whole cleanup at the
    first service gone between its listing and its lookup ("no provider": a clean-clone CI, the
    campaign's heal, session 47). uris: each node's XML-RPC URI (None if unknown). Returns the
    number of removals the master answered."""
    try:
        pubs, subs, srvs = master.getSystemState()
    except Exception:   # the master gone: nothing to clean
        return 0
    removed = 0
    for name in dead:
        as_node = master_as(name)
        # (remove, the name, the service whose URI is looked up, or None: the node's own URI)
        steps = [(as_node.unregisterPublisher, topic, None) for topic, nodes in pubs if name in nodes]
        steps += [(as_node.unregisterSubscriber, topic, None) for topic, nodes in subs if name in nodes]
        steps += [(as_node.unregisterService, service, service) for service, nodes in srvs if name in nodes]
        for remove, what, service in steps:
            try:   # the master removes it only if that node holds it with that URI
                remove(what, master.lookupService(service) if service else uris.get(name))
                removed += 1
            except Exception:   # gone meanwhile, or the master's answer: nothing left to remove there
                pass
    return removed


def roslaunch(pkg, launch_file, **args):
    return ['roslaunch', '--wait', '--skip-log-check', pkg, launch_file] + \
           ['%s:=%s' % (k, v) for k, v in sorted(args.items())]


def free_port():
    import socket
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def start_master(log_dir, port=None, timeout=30.0):
    """Start a roscore on a free port and point this process (and its children) at it.

    Returns the roscore Site; raises RuntimeError if the master does not answer in time.
    """
    port = port or free_port()
    os.environ['ROS_MASTER_URI'] = 'http://127.0.0.1:%d' % port
    os.makedirs(log_dir, exist_ok=True)
    # roslaunch makes ROS_HOME unguarded: two roscores starting at once in a fresh clone raced on it
    os.makedirs(os.environ.get('ROS_HOME') or os.path.expanduser('~/.ros'), exist_ok=True)
    core = Site('roscore', ['roscore', '-p', str(port)], log_path=os.path.join(log_dir, 'roscore.log')).start()
    if not wait_until(lambda: master_answers(2.0, '/aft_deployment')[0], timeout, 0.05):
        core.stop()
        raise RuntimeError('roscore on port %d did not answer within %.0f s (log: %s)'
                           % (port, timeout, core.log_path))
    return core
