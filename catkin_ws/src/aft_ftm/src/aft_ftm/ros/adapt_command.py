"""The ``adapt`` command: run an adaptation script against the live system.

SIGINT (Ctrl-C), SIGTERM or SIGHUP (its terminal gone) while it runs rolls the adaptation back (the step in progress ends
first): suspended nodes resumed, launched nodes stopped, killed nodes started again, bindings
restored; then it exits with status 1, saying it was interrupted and what was undone. A second
signal does not cut the rollback short. If the command is killed (SIGKILL) or stopped
(SIGSTOP) instead, the nodes it suspended resume by themselves once their lease runs out.
"""
import argparse
import functools
import json
import os
import signal
import sys

import rospkg
import rospy

from .. import adaptation
from ..adaptation import ScriptError
from ..suspension import MAX_LEASE


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


def declared_args(spec):
    """The names of the arguments a script declares (ScriptError if it cannot be loaded)."""
    return set(load_script(spec).args)


def _on_signal(engine, signum, _frame):
    """First signal: interrupt the engine (it rolls back). Later ones: say the rollback goes on.
    Writes with os.write: print is not safe in a signal handler (the main thread may be printing)."""
    name = signal.Signals(signum).name
    if engine.interrupt(name):
        text = 'adapt: %s: interrupting the adaptation, rolling back what was done\n' % name
    else:
        text = 'adapt: %s: the rollback goes on until every suspended node is resumed (SIGKILL would ' \
               'leave them to their lease)\n' % name
    try:
        os.write(sys.stderr.fileno(), text.encode())
    except OSError:   # a terminal gone (SIGHUP: EIO), a closed pipe: raised here, it would skip the rollback
        pass


def _say_interrupted(report):
    undone = ['%s %s%s' % (s['action'], s['target'], '' if s['ok'] else ' (FAILED: %s)' % s['detail'])
              for s in report.get('rollback', [])]
    if report['rolled_back']:
        what = 'rolled back: %s' % ('; '.join(undone) if undone else 'nothing had been changed')
    else:   # interrupted in the cleanup: the new configuration already served
        what = 'the adaptation was in place, nothing undone; left: %s' % '; '.join(report['cleanup_errors'])
    print('adapt: interrupted (%s): %s' % (report['interrupted'], what), file=sys.stderr, flush=True)


def main(argv):
    parser = argparse.ArgumentParser(prog='adapt', description=__doc__)
    parser.add_argument('script', help='path or shipped name (compose, switch, update_after)')
    parser.add_argument('--mode', choices=adaptation.MODES, default='prepared',
                        help='prepared (default): launch before the pause; paper: launch during it')
    parser.add_argument('--check', action='store_true', help='validate against the live system, change nothing')
    parser.add_argument('--json', help='write the report to this file')
    parser.add_argument('--lease', type=float, default=5.0,
                        help='lease of each suspension (s, default 5): renewed while the command runs; a node '
                             'resumes by itself if the command dies or stops for longer')
    parser.add_argument('--quiesce-timeout', type=float, default=5.0,
                        help='how long a suspension waits for the node to be quiescent (s, default 5; the '
                             'node holds its inputs meanwhile): past it, the adaptation is rolled back')
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
    if not 0 < options.lease <= MAX_LEASE:
        parser.error('--lease must be > 0 s and at most %g s, got %r' % (MAX_LEASE, options.lease))
    if not 0 < options.quiesce_timeout <= MAX_LEASE:
        parser.error('--quiesce-timeout must be > 0 s and at most %g s, got %r' % (MAX_LEASE, options.quiesce_timeout))
    from aft_ftm.ros.params import secure_from_environment
    secure_from_environment()   # mutual TLS where AFT_TLS_DIR says so (issue 16)
    rospy.init_node('aft_adapt', anonymous=True, disable_signals=True)
    from .adaptation_engine import Engine
    engine = Engine(log=functools.partial(print, flush=True), lease=options.lease,
                    quiesce_timeout=options.quiesce_timeout)
    try:
        if options.check:
            steps = engine.validate(script, options.mode)
            print('adapt: %s is valid against the live system; %s order:' % (script.name, options.mode))
            for step in steps:
                print('  %-13s %s' % (step.action, step.target))
            return 0
        # SIGHUP too: an ssh session that ends killed the command in the middle of its pause, with
        # nothing undone (review of stop 39). All three roll back.
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, functools.partial(_on_signal, engine))
        report = engine.run(script, options.mode)
    except ScriptError as e:
        print('adapt: script rejected, nothing changed: %s' % e, file=sys.stderr)
        return 2
    if options.json:
        with open(options.json, 'w') as f:
            json.dump(report, f, indent=1)
    if report['interrupted']:
        _say_interrupted(report)
        return 1
    return 0 if report['ok'] else 1
