"""SEC's access-control policy file and its revocations file (issue 16): which certified party may do what, in the spirit of
SROS2's permissions file. Today it says which Proxies (request origins) each party speaks for; a
party's request from another origin is refused (``spoofed_origin``). YAML::

    parties:
      client:
        origins: [/proxy, /proxy_*]    # fnmatch patterns of Proxy node names
      server: {}                       # sends no request

Every error names the file and what is wrong in it; nothing is half-loaded. No ROS.
"""
import yaml

from .config import load_yaml
from .errors import ConfigError

PARTY_KEYS = ('origins',)


def read_yaml(path, what, missing=False):
    """The YAML in path (``missing`` if there is no file, when given); ConfigError naming ``what``,
    the file and the problem."""
    try:
        with open(path) as f:
            return load_yaml(f.read())
    except FileNotFoundError as e:
        if missing is not False:
            return missing
        raise ConfigError('%s %s cannot be read: %s' % (what, path, e.strerror or e))
    except OSError as e:
        raise ConfigError('%s %s cannot be read: %s' % (what, path, e.strerror or e))
    except yaml.YAMLError as e:
        raise ConfigError('%s %s is not YAML: %s' % (what, path, str(e).splitlines()[0]))


def load(path):
    """{party: [origin patterns]} from the policy file at path."""
    return parse(read_yaml(path, 'SEC policy'), path)


def parse(data, where='the SEC policy'):
    if not isinstance(data, dict) or set(data) != {'parties'} or not isinstance(data['parties'], dict):
        raise ConfigError('%s: expected exactly one key, parties (a mapping of party names)' % where)
    allowed = {}
    for party, rules in data['parties'].items():
        if not isinstance(party, str) or not party or not all(c.isalnum() or c in '_-' for c in party):
            raise ConfigError('%s: %r is not a party name (letters, digits, - or _)' % (where, party))
        rules = {} if rules is None else rules
        if not isinstance(rules, dict):
            raise ConfigError('%s: party %s: expected a mapping (origins: [...]), got %r' % (where, party, rules))
        unknown = sorted(set(rules) - set(PARTY_KEYS))
        if unknown:
            raise ConfigError('%s: party %s: unknown key(s) %s (known: %s)' % (where, party, ', '.join(map(str, unknown)),
                                                                             ', '.join(PARTY_KEYS)))
        origins = rules.get('origins', [])
        if not isinstance(origins, list) or not all(isinstance(o, str) and o.startswith('/') for o in origins):
            raise ConfigError('%s: party %s: origins must be a list of Proxy names starting with /, got %r'
                              % (where, party, origins))
        allowed[party] = list(origins)
    return allowed


def load_revocations(path):
    """The parties the revocations file names (``revoked: [party, ...]``); none if the file is missing.
    ConfigError names the file and the problem."""
    data = read_yaml(path, 'revocations', missing=None)
    if data is None:
        return []
    if not isinstance(data, dict) or set(data) != {'revoked'} or not isinstance(data['revoked'], list) \
            or not all(isinstance(p, str) and p for p in data['revoked']):
        raise ConfigError('revocations %s: expected exactly one key, revoked (a list of party names)' % path)
    return list(data['revoked'])
