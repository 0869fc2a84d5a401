"""Dynamic binding rules (paper, section 6.2 and Fig. 7).

Every FTM node declares its ports: a name, a direction and a message type. A rebind
request binds a port to a topic, or unbinds it. It is refused, changing nothing, when
the port is unknown, the direction is wrong, or the topic already exists on the master
with another type (the error names both types).
"""
from .errors import RebindError

PUBLISH = 0
SUBSCRIBE = 1
DIRECTIONS = {PUBLISH: 'publish', SUBSCRIBE: 'subscribe'}


class PortSpec(object):
    """A port of a node: ``name`` (relative, documented), ``direction`` and ROS ``msg_type``."""
    __slots__ = ('name', 'direction', 'msg_type')

    def __init__(self, name, direction, msg_type):
        self.name = name
        self.direction = direction
        self.msg_type = msg_type

    def __repr__(self):
        return 'PortSpec(%s, %s, %s)' % (self.name, DIRECTIONS[self.direction], self.msg_type)


def check_rebind(specs, port, direction, topic, topic_types, activate):
    """Validate a rebind request against the node's ports and the master's topic types.

    ``specs`` maps port names to PortSpec; ``topic_types`` maps resolved topic names to
    their type as known by the master. Returns the PortSpec; raises RebindError.
    """
    spec = specs.get(port)
    if spec is None:
        raise RebindError('unknown port %r (this node has: %s)' % (port, ', '.join(sorted(specs))))
    if direction not in DIRECTIONS:
        raise RebindError('direction must be 0 (publish) or 1 (subscribe), got %r' % (direction,))
    if direction != spec.direction:
        raise RebindError('port %r is a %s port, the request asks to %s' % (
            port, DIRECTIONS[spec.direction], DIRECTIONS[direction]))
    if activate:
        if not topic:
            raise RebindError('no topic given to bind port %r to' % port)
        existing = topic_types.get(topic)
        if existing is not None and existing != spec.msg_type:
            raise RebindError('topic %s has type %s but port %r has type %s' % (
                topic, existing, port, spec.msg_type))
    return spec
