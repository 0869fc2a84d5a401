"""Typed parameter converters that fail fast, naming the parameter and the bad value.

The ROS adapters read parameters once, at the edge, and pass them through these
converters; library code never reads parameters itself.
"""
from .errors import ConfigError


def positive_float(name, value):
    """Return value as a float > 0, or raise ConfigError naming the parameter."""
    try:
        result = float(value)
    except (TypeError, ValueError):
        raise ConfigError('parameter %s must be a number, got %r' % (name, value))
    if not result > 0.0:
        raise ConfigError('parameter %s must be > 0, got %r' % (name, value))
    return result


def non_negative_int(name, value):
    """Return value if it is an int >= 0, or raise ConfigError naming the parameter."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError('parameter %s must be an integer, got %r' % (name, value))
    if value < 0:
        raise ConfigError('parameter %s must be >= 0, got %r' % (name, value))
    return value


def one_of(name, value, choices):
    """Return value if it is one of choices, or raise ConfigError listing them."""
    if value not in choices:
        raise ConfigError('parameter %s must be one of %s, got %r'
                          % (name, ', '.join(sorted(str(c) for c in choices)), value))
    return value


def non_empty_str(name, value):
    """Return value if it is a non-empty string, or raise ConfigError."""
    if not isinstance(value, str) or not value.strip():
        raise ConfigError('parameter %s must be a non-empty string, got %r' % (name, value))
    return value.strip()


def service_type(name, value):
    """Return value if it looks like a ROS type name 'package/Type'."""
    value = non_empty_str(name, value)
    parts = value.split('/')
    if len(parts) != 2 or not all(parts):
        raise ConfigError('parameter %s must be a type name like package/Type, got %r' % (name, value))
    return value


def niceness(name, value):
    """Return value if it is a process niceness, an integer from -20 to 19."""
    if isinstance(value, bool) or not isinstance(value, int) or not -20 <= value <= 19:
        raise ConfigError('parameter %s must be an integer from -20 to 19, got %r' % (name, value))
    return value


def boolean(name, value):
    """Return value as a bool: True/False, or the strings true/false/1/0 (``bool('false')`` is True,
    so never convert a parameter with bool())."""
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in ('true', 'false', '1', '0'):
        return value.strip().lower() in ('true', '1')
    raise ConfigError('parameter %s must be true or false, got %r' % (name, value))


def positive_int(name, value):
    """Return value if it is an int > 0, or raise ConfigError naming the parameter."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError('parameter %s must be an integer, got %r' % (name, value))
    if value <= 0:
        raise ConfigError('parameter %s must be > 0, got %r' % (name, value))
    return value
