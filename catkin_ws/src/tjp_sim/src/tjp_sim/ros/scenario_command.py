"""The ``scenario`` command: run one scenario of the car case study and print its summary."""
import argparse
import contextlib
import json
import os
import signal
import sys
import time

from .. import scenario as scenarios
from .. import summary as summaries
from ..errors import TjpError


def tls_policy():
    import rospkg
    return os.path.join(rospkg.RosPack().get_path('tjp_sim'), 'config', 'tls_policy.yaml')


class Terminated(BaseException):
    """The scenario command was asked to stop (SIGTERM): the run is stopped, every process of it.

    Not an Exception: raised wherever the main thread is, a RunError was swallowed by the first
    `except Exception` around a master call (the set-up's wait), and the run went on to its end."""


class Deferred(object):
    """SIGTERM (a test's time limit, a supervisor) raises Terminated, once: the run stops every process
    of it on the way out. While the run is stopping (``deferred()``), a SIGTERM is held and raised once
    the stop is done: raised inside it, it left the master, the recorder or a board running."""

    def __init__(self):
        self.stopping = False
        self.held = None
        self.raised = False

    def terminated(self, signum, _frame):
        if self.raised:
            return   # once: the stop it started goes on
        if self.stopping:
            self.held = signum
            return
        self.raised = True
        raise Terminated('terminated by signal %d' % signum)

    @contextlib.contextmanager
    def deferred(self):
        self.stopping = True
        try:
            yield
        finally:
            self.stopping = False
            if self.held is not None and not self.raised:
                self.raised = True
                raise Terminated('terminated by signal %d' % self.held)


def main(argv):
    parser = argparse.ArgumentParser(prog='scenario', description=__doc__)
    parser.add_argument('scenario', help='a scenario file, or the name of one shipped in tjp_sim/scenarios')
    parser.add_argument('--without', metavar='MECHANISM', choices=scenarios.MECHANISMS,
                        help='the control experiment: run it with this mechanism removed')
    parser.add_argument('--until-hazard', action='store_true',
                        help='with --without: end the run a second of road time after the hazard the mechanism '
                             'answers has shown, instead of at the scenario\'s end')
    parser.add_argument('--out', help='directory for run.bag, plot.png, summary.json and the logs '
                                      '(default /tmp/tjp_runs/<scenario>-<time>)')
    parser.add_argument('--gui', action='store_true', help="open pybullet's window")
    parser.add_argument('--no-plot', action='store_true', help='do not draw plot.png')
    parser.add_argument('--json', action='store_true', help='print the summary as JSON instead of text')
    parser.add_argument('--tls', action='store_true',
                        help='mutual TLS on every connection between the car\'s nodes (tjp_sim/config/tls_policy.yaml)')
    options = parser.parse_args(argv)
    try:
        scenario = scenarios.load(options.scenario)
        if options.without:
            scenarios.without(scenario, options.without)
        if options.until_hazard and not (options.without and scenario['control']):
            raise scenarios.ScenarioError('--until-hazard is for a control experiment: give --without MECHANISM '
                                          'for a scenario with a control hazard')
    except TjpError as e:
        print('scenario: rejected: %s' % e, file=sys.stderr)
        return 2
    out = options.out or os.path.join('/tmp/tjp_runs', '%s%s-%s' % (
        scenario['name'], '-without-' + options.without if options.without else '', time.strftime('%Y%m%d-%H%M%S')))
    from .runner import RunError, run_scenario

    signals = Deferred()
    signal.signal(signal.SIGTERM, signals.terminated)
    log = (lambda line: print(line, file=sys.stderr)) if options.json else print
    try:
        summary = run_scenario(options.scenario, out, disable=options.without, gui=options.gui,
                               plot=not options.no_plot, log=log, until_hazard=options.until_hazard,
                               tls_policy=tls_policy() if options.tls else None, stopping=signals.deferred)
    except (RunError, TjpError, Terminated) as e:
        print('scenario: the run failed: %s' % e, file=sys.stderr)
        return 2
    if options.json:
        print(json.dumps(summary, indent=1, default=str))
    else:
        print(summaries.text(summary))
        print('hazards: %s' % (', '.join(summary['hazards']) or 'none'))
        print('record: %s%s' % (summary['bag'], ('\nplot:   %s' % summary['plot']) if summary.get('plot') else ''))
    return 0 if summary['verdict']['ok'] else 1
