"""Reading a node's private parameters once, at the edge, into typed values."""
import rospy

from ..errors import ConfigError


def param(name, convert, default=None, required=False):
    """Read ~name, convert it with convert(full_name, value); ConfigError names the parameter."""
    full = rospy.resolve_name('~' + name)
    if not rospy.has_param('~' + name):
        if required:
            raise ConfigError('missing required parameter %s' % full)
        return default
    return convert(full, rospy.get_param('~' + name))


def run_node(name, factory, setup_timeout=30.0):
    """init_node, build the node object, setup(), spin. Exits non-zero with a clear message on failure."""
    import sys
    rospy.init_node(name)
    try:
        node = factory()
    except ConfigError as e:
        rospy.logfatal('%s: %s', rospy.get_name(), e)
        sys.exit(2)
    if not node.setup(setup_timeout):
        rospy.logfatal('%s: set-up failed, exiting', rospy.get_name())
        sys.exit(1)
    rospy.spin()
