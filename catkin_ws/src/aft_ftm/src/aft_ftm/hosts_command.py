"""The ``hosts`` command: emulated hosts (one network namespace each, on a private bridge) that stay
up between commands, and the faults on them.

  hosts up [--hosts client,master,slave,witness,rosmaster]
  hosts status
  hosts exec HOST -- COMMAND ...        run COMMAND in HOST, ROS_IP/ROS_HOSTNAME set to its address
  hosts fault partition HOST [HOST2]    HOST's link down (with HOST2: only HOST and HOST2 cut apart)
  hosts fault heal HOST [HOST2]
  hosts fault rate KBIT HOST            token bucket (tc htb) on both directions of HOST's link
  hosts fault unrate HOST
  hosts fault power_off HOST            link down first, then every process of HOST killed
  hosts fault power_on HOST             HOST made again from nothing, linked
  hosts fault freeze SECONDS HOST       SIGSTOP of every process of HOST, SIGCONT after SECONDS
  hosts down                            everything removed (and any leftovers of killed runs)

Exit status 2, with a message naming the problem and nothing changed, on bad input (unknown host,
bad rate), when not root, or when this machine cannot make network namespaces.
"""
import argparse
import os
import sys

from . import hosts_exec as ex
from .hosts import DEFAULT_HOSTS, HostsError, Network, parse_hosts


def _parser():
    parser = argparse.ArgumentParser(prog='hosts', description=__doc__.split('\n')[0],
                                     epilog=__doc__.split('\n', 2)[2], formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', metavar='{up,down,status,exec,fault}')
    sub.required = True
    up = sub.add_parser('up', help='make the hosts')
    up.add_argument('--hosts', default=','.join(DEFAULT_HOSTS), help='comma-separated host names (default %(default)s)')
    sub.add_parser('down', help='remove the hosts, and leftovers of killed runs')
    sub.add_parser('status', help='the hosts, their addresses and states')
    run = sub.add_parser('exec', help='run a command in a host')
    run.add_argument('host')
    run.add_argument('argv', nargs=argparse.REMAINDER, help='the command (after --)')
    fault = sub.add_parser('fault', help='inject or undo a fault')
    kinds = fault.add_subparsers(dest='kind', metavar='{partition,heal,rate,unrate,power_off,power_on,freeze}')
    kinds.required = True
    for kind, text in (('partition', 'link down (or, with a second host, only the two cut apart)'),
                       ('heal', 'undo a partition')):
        k = kinds.add_parser(kind, help=text)
        k.add_argument('host')
        k.add_argument('other', nargs='?')
    k = kinds.add_parser('rate', help='rate limit (tc htb, low-delay packets first) on both directions '
                                      'of the host link')
    k.add_argument('kbit')
    k.add_argument('host')
    kinds.add_parser('unrate', help='remove the rate limit').add_argument('host')
    kinds.add_parser('power_off', help='link down first, then every process killed').add_argument('host')
    kinds.add_parser('power_on', help='the host made again from nothing').add_argument('host')
    k = kinds.add_parser('freeze', help='SIGSTOP of every process of the host for SECONDS')
    k.add_argument('seconds')
    k.add_argument('host')
    return parser


def _persistent():
    """The run made by 'hosts up' (prefix, Network), or (None, None)."""
    for prefix, (record, _) in ex.read_records().items():
        if record is not None and record.get('owner', False) is None:
            return prefix, Network.from_dict(record['network'])
    return None, None


def _need_up():
    prefix, net = _persistent()
    if net is None:
        raise HostsError('no hosts are up: run "hosts up" first')
    return net


def up(options):
    names = parse_hosts(options.hosts)
    ex.check_platform()
    prefix, _ = _persistent()
    if prefix is not None:
        raise HostsError('hosts are already up (run %s): run "hosts down" first' % prefix)
    ex.cleanup_leftovers()
    net = Network(ex.new_topology(names))
    ex.bring_up(net, ex._owner_record())       # a run killed during up is a leftover: its owner is dead
    ex.write_record(net, None)
    print('\n'.join(net.describe()))
    return 0


def down(options):
    ex.check_platform()
    prefix, net = _persistent()
    errors = []
    if net is not None:
        errors = ex.tear_down(net.topology, lambda m: print(m, file=sys.stderr))
        print('hosts: run %s removed' % prefix)
    removed = ex.cleanup_leftovers()
    if removed:
        print('hosts: leftovers of killed runs removed: %s' % ', '.join(removed))
    if net is None and not removed:
        print('hosts: no hosts were up')
    return 1 if errors else 0


def status(options):
    ex.check_platform()
    prefix, net = _persistent()
    existing = set(ex.netns_names())
    if net is None:
        print('no hosts are up')
    else:
        print('\n'.join(net.describe()))
        missing = [ns for ns in net.topology.namespaces() if ns not in existing]
        if missing:
            print('missing namespaces (removed by hand?): %s' % ', '.join(missing))
    others = [p for p, (record, _) in ex.read_records().items() if p != prefix]
    if others:
        print('other runs (of a test or program, removed when it ends): %s' % ', '.join(others))
    return 0


def exec_in(options):
    argv = options.argv[1:] if options.argv[:1] == ['--'] else options.argv
    if not argv:
        raise HostsError('no command given: hosts exec HOST -- COMMAND ...')
    ex.check_platform()
    net = _need_up()
    host = net.topology.host(options.host)
    if not net.runs(host.name):   # review of session 34: what ran there lived on past its power_on
        raise HostsError('host %s is off: nothing runs in it until "hosts fault power_on %s"' % (host.name, host.name))
    env = dict(os.environ, ROS_IP=host.ip, ROS_HOSTNAME=host.ip)
    os.execvpe('ip', ['ip', 'netns', 'exec', host.namespace] + argv, env)


def fault(options):
    ex.check_platform()
    net = _need_up()
    kind, name = options.kind, options.host
    if kind == 'freeze':
        seconds = ex.check_seconds(options.seconds)
        pids = ex.netns_pids(net.topology.host(name).namespace)
        if not pids:
            raise HostsError('host %s has no process to freeze' % name)
        freeze = ex.Freeze(pids, seconds).start()
        try:
            freeze.wait(seconds + 1.0)
        finally:
            freeze.thaw()
        print('hosts: %d processes of %s frozen for %g s' % (len(pids), name, seconds))
        return 0
    if kind == 'partition':
        decision = net.partition(name) if options.other is None else net.partition_pair(name, options.other)
    elif kind == 'heal':
        decision = net.heal(name) if options.other is None else net.heal_pair(name, options.other)
    elif kind == 'rate':
        decision = net.rate(name, options.kbit)
    elif kind == 'unrate':
        decision = net.unrate(name)
    elif kind == 'power_on':
        decision = net.power_on(name)
    else:
        namespace = net.topology.host(name).namespace
        decision = net.power_off(name, ex.netns_pids(namespace))
    plan, changes = decision
    if kind == 'power_on':   # what got into the old namespace while off: killed, not left in a nameless one
        ex.clear_namespace(net.topology.host(name).namespace, _log)
    ex.carry_out(plan, log=_log)
    if kind == 'power_off':      # and any process forked meanwhile (they were stopped, the link is down)
        left = ex.kill_and_wait(ex.netns_pids(net.topology.host(name).namespace))
        if left:
            print('hosts: processes %s of %s still alive after SIGKILL' % (left, name), file=sys.stderr)
    net.commit(changes)
    ex.write_record(net, None)
    print('hosts: %s %s%s done' % (kind, name, ' ' + options.other if getattr(options, 'other', None) else ''))
    return 0


def _log(message):
    print(message, file=sys.stderr)


COMMANDS = {'up': up, 'down': down, 'status': status, 'exec': exec_in, 'fault': fault}


def main(argv):
    options = _parser().parse_args(argv)
    try:
        return COMMANDS[options.command](options)
    except HostsError as e:
        print('hosts: %s' % e, file=sys.stderr)
        return 2
