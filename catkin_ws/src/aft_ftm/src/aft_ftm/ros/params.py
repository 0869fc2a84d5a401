"""Reading a node's private parameters once, at the edge, into typed values."""
import rospy

from ..errors import ConfigError


READ = {}   # {full name: value as read}: what a restarted ROS master is given back (aft_ftm.ros.rejoin)


def param(name, convert, default=None, required=False):
    """Read ~name, convert it with convert(full_name, value); ConfigError names the parameter."""
    full = rospy.resolve_name('~' + name)
    if not rospy.has_param('~' + name):
        if required:
            raise ConfigError('missing required parameter %s' % full)
        return default
    value = rospy.get_param('~' + name)
    converted = convert(full, value)
    READ[full] = value
    return converted


def node_help(name, factory, variants=None):
    """The text of ``rosrun <package> <name> --help``: the executable's docstring, then the node
    class's (its parameters, topics and services); with variants ({value: class} chosen by a
    parameter), each variant's."""
    import inspect
    import sys
    main = sys.modules.get('__main__')
    parts = ['usage: rosrun <package> %s [_param:=value ...] [__name:=NAME] [__ns:=NS] [topic:=remapped ...]' % name]
    if main is not None and main.__doc__:
        parts.append(inspect.cleandoc(main.__doc__))
    classes = sorted(variants.items()) if variants else [('', factory)]
    for key, cls in classes:
        doc = inspect.getdoc(cls)
        if doc:
            parts.append(('%s: %s' % (key, doc)) if key else doc)
    return '\n\n'.join(parts)


def wants_help(argv):
    """True if the command line asks for help (-h or --help): answer it without starting work."""
    return any(a in ('-h', '--help') for a in argv[1:])


def secure_from_environment(environ=None):
    """Install mutual TLS (aft_ftm.ros.tls_transport) if AFT_TLS_DIR is set: the party is AFT_TLS_PARTY,
    the policy AFT_TLS_POLICY (both required then). Returns the party, or None (no TLS)."""
    import os
    environ = os.environ if environ is None else environ
    directory = environ.get('AFT_TLS_DIR')
    if not directory:
        return None
    party, policy = environ.get('AFT_TLS_PARTY'), environ.get('AFT_TLS_POLICY')
    if not party or not policy:
        raise ConfigError('AFT_TLS_DIR is set (%s): AFT_TLS_PARTY and AFT_TLS_POLICY must be set too' % directory)
    from .. import tls
    from .tls_transport import install
    return install(directory, party, tls.Permissions.load(policy))


def run_node(name, factory, setup_timeout=30.0, variants=None):
    """init_node, build the node object, setup(), spin. Exits non-zero with a clear message on failure.
    ``--help`` prints node_help() and exits 0 without contacting the master."""
    import sys
    if wants_help(sys.argv):
        print(node_help(name, factory, variants))
        sys.exit(0)
    from .handshake import USER_TIMEOUT, bound_handshakes, unacknowledged_limit
    from .rejoin import ignore_misdirected_shutdowns, keep_registered, period_from_env
    from .subscription_keeper import keep_subscriptions
    from .xmlrpc_shutdown import end_serving_on_shutdown
    end_serving_on_shutdown()   # no XML-RPC thread spinning on its closed socket while the node stops
    bound_handshakes()   # no half-made connection wedges this node's TCPROS server
    ignore_misdirected_shutdowns()   # a master's shutdown meant for the dead process this port was
    try:
        # no write to a subscriber on a dead host blocks this node for longer
        unacknowledged_limit(period_from_env(name='AFT_TCP_USER_TIMEOUT', default=USER_TIMEOUT))
        secure_from_environment()   # mutual TLS on every TCPROS connection, where the environment asks for it
        keep_subscriptions()   # connects again the publishers rospy gave up on
    except ConfigError as e:
        sys.stderr.write('%s: %s\n' % (name, e))
        sys.exit(2)
    rospy.init_node(name)
    try:
        keep_registered()   # registers again with a restarted ROS master
        node = factory()
    except ConfigError as e:
        rospy.logfatal('%s: %s', rospy.get_name(), e)
        sys.exit(2)
    if not node.setup(setup_timeout):
        rospy.logfatal('%s: set-up failed, exiting', rospy.get_name())
        sys.exit(1)
    rospy.spin()
