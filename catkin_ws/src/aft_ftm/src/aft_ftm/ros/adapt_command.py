"""The ``adapt`` command: run an adaptation script against the live system."""
import argparse
import json
import os
import sys

import rospkg
import rospy

from .. import adaptation
from ..adaptation import ScriptError


def find_script(spec):
    """A path, or the name of a script shipped in aft_ftm/adaptations (with or without .yaml)."""
    if os.path.isfile(spec):
        return spec
    name = spec if spec.endswith('.yaml') else spec + '.yaml'
    shipped = os.path.join(rospkg.RosPack().get_path('aft_ftm'), 'adaptations', name)
    if os.path.isfile(shipped):
        return shipped
    raise ScriptError('no adaptation script %r (neither a file nor one of %s)'
                      % (spec, ', '.join(sorted(f[:-5] for f in os.listdir(os.path.dirname(shipped))))))


def load_script(spec, overrides=()):
    path = find_script(spec)
    with open(path) as f:
        return adaptation.load(f.read(), adaptation.parse_overrides(overrides), source=path)


def main(argv):
    parser = argparse.ArgumentParser(prog='adapt', description=__doc__)
    parser.add_argument('script', help='path or shipped name (compose, switch, update_after)')
    parser.add_argument('--mode', choices=adaptation.MODES, default='prepared',
                        help='prepared (default): launch before the pause; paper: launch during it')
    parser.add_argument('--check', action='store_true', help='validate against the live system, change nothing')
    parser.add_argument('--json', help='write the report to this file')
    options, rest = parser.parse_known_args(argv)
    overrides = [a for a in rest if ':=' in a and not a.startswith('__')]
    unknown = [a for a in rest if ':=' not in a]
    if unknown:
        parser.error('unrecognised arguments: %s' % ' '.join(unknown))
    try:
        script = load_script(options.script, overrides)
    except ScriptError as e:
        print('adapt: script rejected, nothing changed: %s' % e, file=sys.stderr)
        return 2
    rospy.init_node('aft_adapt', anonymous=True, disable_signals=True)
    from .adaptation_engine import Engine
    engine = Engine(log=print)
    try:
        if options.check:
            steps = engine.validate(script, options.mode)
            print('adapt: %s is valid against the live system; %s order:' % (script.name, options.mode))
            for step in steps:
                print('  %-13s %s' % (step.action, step.target))
            return 0
        report = engine.run(script, options.mode)
    except ScriptError as e:
        print('adapt: script rejected, nothing changed: %s' % e, file=sys.stderr)
        return 2
    if options.json:
        with open(options.json, 'w') as f:
            json.dump(report, f, indent=1)
    return 0 if report['ok'] else 1
