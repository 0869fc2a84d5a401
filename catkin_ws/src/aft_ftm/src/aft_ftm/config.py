"""Typed parameter converters that fail fast, naming the parameter and the bad value.

The ROS adapters read parameters once, at the edge, and pass them through these
converters; library code never reads parameters itself.
"""
import re
import threading

import yaml

from .errors import ConfigError


# The largest a positive_float may be: the longest wait Python's threads take (about 292 years). A
# timeout of .inf or 1e10 meant as "no bound" passed before, and a wait on it raised OverflowError out
# of the node's handler, the request it held lost with no answer (review of session 48).
LARGEST = threading.TIMEOUT_MAX


def positive_float(name, value):
    """Return value as a finite float > 0 (at most LARGEST), or raise ConfigError naming the parameter."""
    try:
        result = float(value)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError('parameter %s must be a number, got %r' % (name, value))
    if not result > 0.0:
        raise ConfigError('parameter %s must be > 0, got %r' % (name, value))
    if not result <= LARGEST:
        raise ConfigError('parameter %s must be a finite number of at most %.0f, got %r' % (name, LARGEST, value))
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


def flag(name, value):
    """Return value as a bool: only true or false (a bool, or those words in any case) are accepted.
    Never convert a parameter with bool(): ``bool('false')`` is True."""
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.strip().lower() in ('true', 'false'):
        return value.strip().lower() == 'true'
    raise ConfigError('parameter %s must be true or false, got %r' % (name, value))


def optional_name(name, value):
    """Return '' (not set) or a non-empty string, stripped."""
    return '' if value == '' else non_empty_str(name, value)


def witness_service(name, value):
    """Return '' (no witness: '' or none, as the launch files spell it) or the service of a witness,
    which aft_ftm/witness offers as its node's ~request (its configurations are published beside it,
    as ~configuration): an absolute graph name ending in /request. A relative name resolved
    differently in each node's namespace, and "None" meant no witness to some nodes and a witness to
    the launch files (review of session 40): both are refused."""
    if value in ('', 'none'):
        return ''
    if not isinstance(value, str) or not _WITNESS_NAME.match(value.strip()):
        raise ConfigError('parameter %s must name a witness\'s service by its absolute name (/NS/witness/request, '
                          'as witness.launch offers it) or be none, got %r' % (name, value))
    return value.strip()


_WITNESS_NAME = re.compile(r'^(/[A-Za-z]\w*(/\w+)*)?/request$')   # rosgraph's legal names, absolute


def non_negative_float(name, value):
    """Return value as a float >= 0 (0 usually meaning 'off')."""
    return 0.0 if value == 0 else positive_float(name, value)


def number_in(low, high):
    """A converter accepting a number from low to high inclusive."""
    def convert(name, value):
        try:
            result = float(value)
        except (TypeError, ValueError):
            raise ConfigError('parameter %s must be a number, got %r' % (name, value))
        if isinstance(value, bool) or not low <= result <= high:
            raise ConfigError('parameter %s must be a number from %g to %g, got %r' % (name, low, high, value))
        return result
    return convert


def choice(*choices):
    """A converter accepting one of choices."""
    return lambda name, value: one_of(name, value, choices)


def name_list(name, value):
    """Return value as a list of non-empty strings (a YAML list; a single string is refused, so that a
    forgotten pair of brackets is an error rather than a list of characters)."""
    if not isinstance(value, (list, tuple)):
        raise ConfigError('parameter %s must be a list of names, got %r' % (name, value))
    return [non_empty_str('%s[%d]' % (name, i), v) for i, v in enumerate(value)]


def some_names(name, value):
    """name_list() with at least one name."""
    result = name_list(name, value)
    if not result:
        raise ConfigError('parameter %s must name at least one, got an empty list' % name)
    return result


def number(name, value):
    """Return value as a finite float."""
    result = number_in(-float('inf'), float('inf'))(name, value)
    if result in (float('inf'), float('-inf')):
        raise ConfigError('parameter %s must be a finite number, got %r' % (name, value))
    return result


def number_map(name, value):
    """Return value as a dict of names to numbers > 0."""
    if not isinstance(value, dict):
        raise ConfigError('parameter %s must be a dict of names to numbers, got %r' % (name, value))
    return {non_empty_str(name, k): positive_float('%s/%s' % (name, k), v) for k, v in value.items()}


def positive_int(name, value):
    """Return value if it is an int > 0, or raise ConfigError naming the parameter."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError('parameter %s must be an integer, got %r' % (name, value))
    if value <= 0:
        raise ConfigError('parameter %s must be > 0, got %r' % (name, value))
    return value


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (by default the last one wins,
    silently: two services of one name, critical: true then critical: false, an FMECA row's gravity
    written twice, a policy's party listed twice)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == 'tag:yaml.org,2002:merge':   # a merge key (<<: *anchor): what it brings in
                continue                                     # may be overridden here, as YAML allows
            key = self.construct_object(key_node, deep=deep)
            try:
                repeated = key in seen
                seen.add(key)
            except TypeError:   # an unhashable key: the base class says so
                continue
            if repeated:
                raise yaml.constructor.ConstructorError(
                    'while reading a mapping', node.start_mark, 'key %r given twice' % (key,), key_node.start_mark)
        return super(_UniqueKeyLoader, self).construct_mapping(node, deep=deep)


def load_yaml(text):
    """yaml.safe_load, but a key given twice in one mapping raises yaml.YAMLError (a ConstructorError)."""
    return yaml.load(text, Loader=_UniqueKeyLoader)

