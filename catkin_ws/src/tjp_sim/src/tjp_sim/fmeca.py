"""The FMECA of the Traffic Jam Pilot as data (config/fmeca.yaml): loading and checking it."""
import collections
import os

import yaml
from aft_ftm.config import load_yaml

from . import resources
from .errors import TjpConfigError

MECHANISMS = ('pbr', 'tr_sliding_average', 'triplication_vote', 'alarm_and_stop')
FIELDS = ('entity', 'failure_mode', 'effect', 'frequency', 'gravity', 'mechanism', 'scenario')

Row = collections.namedtuple('Row', FIELDS + ('risk',))


def parse(text, source='fmeca'):
    """The rows of an FMECA YAML text; TjpConfigError names the row and the field when one is wrong (a
    field given twice in a row, a name that is not a string, a scenario not shipped included: the
    last of two gravities won silently; review of session 48)."""
    try:
        data = load_yaml(text)
    except yaml.YAMLError as e:
        raise TjpConfigError('%s: not valid YAML: %s' % (source, e))
    if not isinstance(data, dict) or set(data) != {'rows'} or not isinstance(data['rows'], list) or not data['rows']:
        raise TjpConfigError('%s: must be a mapping with one key, rows, a non-empty list' % source)
    rows, seen = [], set()
    for i, item in enumerate(data['rows']):
        where = '%s: row %d' % (source, i + 1)
        if not isinstance(item, dict):
            raise TjpConfigError('%s: must be a mapping' % where)
        unknown, missing = sorted(set(item) - set(FIELDS)), [f for f in FIELDS if f not in item]
        if unknown or missing:
            raise TjpConfigError('%s: %s' % (where, '; '.join(
                (['unknown field %s' % ', '.join(unknown)] if unknown else []) +
                (['missing field %s' % ', '.join(missing)] if missing else []))))
        for field in ('entity', 'failure_mode', 'effect', 'scenario'):
            value = item[field]
            if not isinstance(value, str) or not value.strip():
                raise TjpConfigError('%s: %s must be a non-empty string, got %r' % (where, field, value))
        for field in ('frequency', 'gravity'):
            value = item[field]
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 4:
                raise TjpConfigError('%s: %s must be an integer from 1 to 4, got %r' % (where, field, value))
        if item['mechanism'] not in MECHANISMS:
            raise TjpConfigError('%s: mechanism must be one of %s, got %r' % (where, ', '.join(MECHANISMS),
                                                                            item['mechanism']))
        if not os.path.isfile(resources.path('scenarios', item['scenario'] + '.yaml')):
            raise TjpConfigError('%s: scenario %r is not one of the shipped scenarios (%s)' % (
                where, item['scenario'], resources.path('scenarios')))
        key = (item['entity'], item['failure_mode'])
        if key in seen:
            raise TjpConfigError('%s: %s / %s appears twice' % (where, key[0], key[1]))
        seen.add(key)
        rows.append(Row(*[item[f] for f in FIELDS], risk=item['frequency'] * item['gravity']))
    return rows


def load(path=None):
    """The FMECA table at path (default: the package's config/fmeca.yaml)."""
    path = path or resources.path('config', 'fmeca.yaml')
    with open(path) as f:
        return parse(f.read(), source=os.path.basename(path))


def markdown(rows):
    """The table as it appears in the README."""
    lines = ['| entity | failure mode | effect | F | G | risk | mechanism | scenario |', '|---|---|---|---|---|---|---|---|']
    lines += ['| %s | %s | %s | %d | %d | %d | %s | %s |' % (r.entity, r.failure_mode, r.effect, r.frequency,
                                                           r.gravity, r.risk, r.mechanism, r.scenario)
              for r in sorted(rows, key=lambda r: -r.risk)]
    return '\n'.join(lines)
