"""Carrying any application service's messages inside aft_msgs envelopes."""
import io

import roslib.message

from ..errors import ConfigError

_classes = {}


def service_class(type_name):
    """The Python class of a service type name (cached); ConfigError if it cannot be loaded."""
    cls = _classes.get(type_name)
    if cls is None:
        try:
            cls = roslib.message.get_service_class(type_name)
        except (ValueError, ImportError) as e:
            cls = None
            reason = str(e)
        else:
            reason = 'no such service type'
        if cls is None:
            raise ConfigError('cannot load service type %r: %s (is its package built and sourced?)'
                              % (type_name, reason))
        _classes[type_name] = cls
    return cls


def serialize(msg):
    buff = io.BytesIO()
    msg.serialize(buff)
    return buff.getvalue()


def deserialize(cls, data):
    msg = cls()
    msg.deserialize(bytes(data))
    return msg
