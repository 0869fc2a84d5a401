"""Emulated hosts, carried out: runs the plans of :mod:`aft_ftm.hosts` (root only).

- :class:`Hosts`: a context manager that brings a topology up and always tears it down (normal
  exit, exception, SIGTERM or SIGINT, interpreter exit); :meth:`Hosts.run_in` starts a process in a
  host with ``ROS_IP``/``ROS_HOSTNAME`` set to the host's address; the faults (partition, pair
  partition, rate limit, power off/on, freeze).
- :func:`cleanup_leftovers`: removes the namespaces and links a killed run left (found by the
  project prefix in their names), never those of a run still alive.
- A run's record is a small JSON file in :func:`state_dir` (root only, mode 0700): its topology,
  the hosts' states and who owns it (the process of a :class:`Hosts`, or none: ``scripts/hosts up``,
  whose hosts stay until ``scripts/hosts down``).

The processes of a host are those started with :meth:`Hosts.run_in` and their descendants (psutil),
together with every process whose network namespace is the host's (a daemon that left its parent
and started a session of its own is still found).
"""
import atexit
import ctypes
import json
import os
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
import time

import psutil

from .hosts import (HostState, HostsError, Network, Signal, Topology, TopologyError, check_seconds,
                    plan_down, plan_up, run_prefix_pattern, PROJECT_PREFIX)
from .process_start import started
from .sites import wait_stopped

STATE_DIRS = ('/run/aft_hosts', '/tmp/aft_hosts')
COMMAND_TIMEOUT = 10.0
KILL_WAIT = 5.0
ISOLATE_WAIT = 0.5      # s: the power switch waits at most this for every thread of a host to be seen stopped
NETNS_DIR = '/run/netns'
CLONE_NEWNET = 0x40000000
KILL_ROUNDS = 3         # rescans of a host's namespace for processes that entered it during a kill
# What ip/tc print when the thing a removal step removes is already gone: that step is done (review of
# session 34: a power_on whose rollback had removed the new namespace failed at its first step for ever).
ABSENT = ('No such file or directory', 'Cannot find device', 'Cannot delete qdisc with handle of zero')
# (not "Cannot open network namespace" alone, nor "does not exist": EPERM or EMFILE were taken for done)


class PlatformError(HostsError):
    """This machine cannot make emulated hosts (not root, no ip command, no namespaces)."""


class CommandError(HostsError):
    """An ip or tc command failed; the message gives the command and what it printed."""

    def __init__(self, argv, message):
        HostsError.__init__(self, '%s: %s' % (' '.join(argv), message))
        self.argv = argv
        self.message = message


def run(argv, timeout=COMMAND_TIMEOUT):
    """Run one command line; its stdout. Raises CommandError naming it if it fails or hangs."""
    try:
        done = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                              timeout=timeout)
    except FileNotFoundError:
        raise CommandError(argv, 'no such program')
    except subprocess.TimeoutExpired:
        raise CommandError(argv, 'still running after %g s' % timeout)
    except OSError as e:      # review of session 34: any other (not executable, no memory) skipped the rollback
        raise CommandError(argv, 'cannot run: %s' % e)
    if done.returncode != 0:
        raise CommandError(argv, 'exit %d: %s' % (done.returncode, done.stderr.decode(errors='replace').strip()))
    return done.stdout.decode(errors='replace')


def check_platform():
    """Raises PlatformError naming what is missing; changes nothing (the probe's namespace has no name
    and vanishes with its process)."""
    if os.geteuid() != 0:
        raise PlatformError('emulated hosts need root (network namespaces, links, tc); this is uid %d'
                            % os.geteuid())
    for program in ('ip', 'tc', 'unshare'):
        try:
            run([program, '-V'] if program != 'unshare' else [program, '--version'])
        except CommandError as e:
            raise PlatformError('the %s command is unavailable (%s)' % (program, e))
    try:
        run(['unshare', '--net', 'true'])
    except CommandError as e:
        raise PlatformError('network namespaces cannot be made here: %s' % e)


def state_dir():
    """The record directory: /run/aft_hosts (or /tmp/aft_hosts), made 0700 if missing, refused if
    anybody but root may write in it."""
    errors = []
    for path in STATE_DIRS:
        try:
            os.makedirs(path, mode=0o700, exist_ok=True)
            st = os.stat(path)
        except OSError as e:
            errors.append('%s: %s' % (path, e))
            continue
        if st.st_uid != 0 or st.st_mode & 0o022:
            errors.append('%s: not root-only (owner uid %d, mode %o)' % (path, st.st_uid, st.st_mode & 0o777))
            continue
        return path
    raise PlatformError('no directory for the hosts record: %s' % '; '.join(errors))


def _owner_record():
    return {'pid': os.getpid(), 'create_time': started(os.getpid())}   # on the boot clock (process_start)


def _owner_alive(owner):
    if owner is None:
        return True          # scripts/hosts up: the hosts stay until scripts/hosts down
    try:
        return started(owner['pid']) == owner['create_time']
    except (KeyError, TypeError):
        return False


def write_record(net, owner, claim=False):
    """Write the run's record (whole, or not at all). ``claim``: the run's first record, made only if
    no record of its prefix exists, else HostsError (review of session 34: two runs that drew the same
    prefix overwrote each other's record, and the first to end removed the other's)."""
    directory = state_dir()
    prefix = net.topology.prefix
    path = os.path.join(directory, prefix + '.json')
    fd, tmp = tempfile.mkstemp(prefix=prefix + '.', suffix='.json.tmp', dir=directory)   # swept with the run
    try:
        with os.fdopen(fd, 'w') as f:
            json.dump({'network': net.to_dict(), 'owner': owner}, f, indent=1, sort_keys=True)
        os.chmod(tmp, 0o644)
        if claim:
            try:
                os.link(tmp, path)       # atomic, and refused if the record exists
            except OSError as e:
                raise HostsError('run prefix %s is taken (its record %s: %s): nothing was made' % (prefix, path, e))
        else:
            os.replace(tmp, path)
            tmp = None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass
    return path


def read_records():
    """prefix -> (record or None if unreadable, path) of every run recorded."""
    records = {}
    directory = state_dir()
    for name in sorted(os.listdir(directory)):
        if not name.endswith('.json'):
            continue
        path = os.path.join(directory, name)
        try:
            with open(path) as f:
                records[name[:-5]] = (json.load(f), path)
        except (OSError, ValueError):
            records[name[:-5]] = (None, path)
    return records


def netns_names():
    return [entry['name'] for entry in json.loads(run(['ip', '-j', 'netns', 'list']) or '[]')]


def root_links():
    return [entry['ifname'] for entry in json.loads(run(['ip', '-j', 'link', 'show']) or '[]')]


def used_networks():
    """The IPv4 networks this machine uses: root namespace routes and addresses, and other runs'."""
    nets = []
    for entry in json.loads(run(['ip', '-j', '-4', 'route', 'show', 'table', 'all']) or '[]'):
        dst = entry.get('dst', '')
        if dst and dst[0].isdigit():
            nets.append(dst if '/' in dst else dst + '/32')
    for link in json.loads(run(['ip', '-j', '-4', 'addr', 'show']) or '[]'):
        for addr in link.get('addr_info', []):
            nets.append('%s/%s' % (addr['local'], addr['prefixlen']))
    for record, _ in read_records().values():
        try:
            nets.append(record['network']['topology']['network'])
        except (KeyError, TypeError):
            pass
    return nets


def netns_pids(namespace):
    """The processes whose network namespace is the named one (this one too: see others_in)."""
    try:
        target = os.stat(os.path.join(NETNS_DIR, namespace))
    except OSError:
        return []
    pids = []
    for pid in psutil.pids():
        try:
            st = os.stat('/proc/%d/ns/net' % pid)
        except OSError:
            continue
        if (st.st_dev, st.st_ino) == (target.st_dev, target.st_ino):
            pids.append(pid)
    return pids


def own_ids():
    """This process's pid and the ids of its threads: never signalled (review of session 34: the
    campaign's main thread lives in the rosmaster host, so /proc showed this process in that namespace
    and the tear-down SIGKILLed itself before removing anything)."""
    ids = {os.getpid()}
    try:
        ids.update(int(tid) for tid in os.listdir('/proc/self/task'))
    except (OSError, ValueError):
        pass
    return ids


def others_in(namespace):
    """The processes in the named namespace, other than this one."""
    own = own_ids()
    return [pid for pid in netns_pids(namespace) if pid not in own]


def clear_namespace(namespace, log):
    """Kill whatever is still in a namespace about to be deleted (bounded rounds). Review of session 34:
    a process that got into an 'off' host (an exec there, a site started with ``ip netns exec``) lived on
    in a namespace without a name, which no cleanup finds. Raises HostsError naming those that would not
    die (the namespace is then kept: a later cleanup still finds them)."""
    killed = set()
    for _ in range(KILL_ROUNDS):
        pids = [pid for pid in others_in(namespace) if pid not in killed]
        if not pids:
            break
        killed.update(pids)
        left = kill_and_wait(pids)
        if left:
            raise HostsError('processes %s of %s would not die: the namespace is kept' % (left, namespace))
    if killed:
        log('hosts: %d processes still in %s killed before it is removed: %s'
            % (len(killed), namespace, sorted(killed)))
    return sorted(killed)


def send(signum, pids):
    """Send signum to each pid still alive (never to this process); the pids it reached."""
    reached = []
    own = own_ids()
    for pid in pids:
        if pid in own:
            continue
        try:
            os.kill(pid, signum)
            reached.append(pid)
        except ProcessLookupError:
            pass
    return reached


def _processes(pids):
    """psutil handles of the pids still there."""
    found = []
    for pid in pids:
        try:
            found.append(psutil.Process(pid))
        except psutil.NoSuchProcess:
            pass
    return found


def kill_and_wait(pids, timeout=KILL_WAIT):
    """SIGKILL each pid, then wait (bounded) until they are gone or zombies; those still there."""
    send(signal.SIGKILL, pids)
    deadline = time.monotonic() + timeout
    alive = list(pids)
    while alive and time.monotonic() < deadline:
        alive = [pid for pid in alive if _running(pid)]
        if alive:
            time.sleep(0.005)
    return alive


def _running(pid):
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def cleanup_leftovers(prefix=PROJECT_PREFIX, log=None):
    """Remove the namespaces and root-namespace links named ``<prefix><4 hex>-...`` whose run is not
    alive (no record, or a record whose owner process is gone), killing any process still in them,
    and their records. Never raises; returns the names removed."""
    log = log or _stderr
    pattern = run_prefix_pattern(prefix)
    removed = []
    try:
        # The names are listed BEFORE the records are read (review of session 34: a run starting between
        # the two was swept). A run writes its record before it makes any name, so every name listed
        # here belongs to a run whose record is read below.
        namespaces = [n for n in netns_names() if pattern.match(n)]
        links = [n for n in root_links() if pattern.match(n)]
        records = read_records()
        alive = set(p for p, (record, _) in records.items() if _record_alive(record))
        namespaces = [n for n in namespaces if pattern.match(n).group(1) not in alive]
        # hosts first, the switch last (a host's namespace removes its cable, and the switch's end)
        namespaces.sort(key=lambda n: n.endswith('-sw'))
        for ns in namespaces:
            if _alive_now(pattern.match(ns).group(1)):
                continue      # its record made since it was read: a run starting with that prefix
            pids = others_in(ns)
            if pids:
                kill_and_wait(pids)
            _quiet(['ip', 'netns', 'del', ns], log, removed, ns)
        for link in links:
            run_prefix = pattern.match(link).group(1)
            if run_prefix not in alive and not _alive_now(run_prefix):
                _quiet(['ip', 'link', 'del', link], log, removed, link)
        for run_prefix in records:
            if run_prefix not in alive and pattern.match(run_prefix + '-') and not _alive_now(run_prefix):
                _remove_run_files(run_prefix)
    except (HostsError, OSError, ValueError) as e:
        log('hosts: cleanup of leftovers incomplete: %s' % e)
    return removed


def _stderr(message):
    sys.stderr.write(message + '\n')


def _record_alive(record):
    return record is not None and _owner_alive(record.get('owner', False))


def _alive_now(run_prefix):
    """Whether the run's record, read again now, names a live owner."""
    try:
        with open(os.path.join(state_dir(), run_prefix + '.json')) as f:
            return _record_alive(json.load(f))
    except (OSError, ValueError, HostsError):
        return False


def _remove_run_files(run_prefix):
    """A swept run's files: its record last, and its power switch socket and unfinished record writes
    (review of session 34: only the record went)."""
    directory = state_dir()
    names = sorted(n for n in os.listdir(directory) if n == run_prefix + '.switch' or
                   (n.startswith(run_prefix + '.') and n.endswith('.json.tmp')))
    for name in names + [run_prefix + '.json']:
        try:
            os.unlink(os.path.join(directory, name))
        except FileNotFoundError:
            pass


def _quiet(argv, log, done, name):
    try:
        run(argv)
        done.append(name)
    except CommandError as e:
        log('hosts: %s' % e)


def leftovers(prefix):
    """Names of namespaces and root links that start with ``prefix`` (a run's prefix, for checks)."""
    return [n for n in netns_names() + root_links() if n.startswith(prefix + '-')]


def run_step(argv):
    """Run one step of a plan. A removal whose object is already gone is done, not failed (review of
    session 34: after a rollback, power_on and unrate failed at their first step on every retry)."""
    try:
        run(argv)
    except CommandError as e:
        if 'del' not in argv or not any(text in e.message for text in ABSENT):
            raise


def carry_out(plan, on_signal=send, log=None):
    """Run a plan's steps in order. If a step fails, the undo of the steps done is run in reverse
    and CommandError is raised: the hosts are as before (an undo that fails is logged)."""
    done = []
    try:
        for item in plan:
            if isinstance(item, Signal):
                on_signal(item.signum, item.pids)
            else:
                run_step(item.argv)
                done.append(item)
    except CommandError:
        for step in reversed(done):
            if step.undo is not None:
                try:
                    run_step(step.undo)
                except CommandError as e:
                    (log or _stderr)('hosts: undo of "%s" failed, left as it is: %s' % (step.why, e))
        raise


def bring_up(net, owner):
    """Make a topology's hosts, with its record (claimed first: HostsError, nothing made, if the prefix
    is taken); on failure everything made is removed again."""
    write_record(net, owner, claim=True)
    try:
        carry_out(plan_up(net.topology))
    except CommandError:
        remove_record(net.topology.prefix)
        raise


def tear_down(topology, log):
    """Kill every process in the run's namespaces, remove them. Never raises; the errors, logged."""
    errors = []
    for ns in topology.namespaces():
        pids = others_in(ns)
        if pids:
            left = kill_and_wait(pids)
            if left:
                errors.append('processes %s of %s would not die' % (left, ns))
    existing = set(netns_names())
    for argv in plan_down(topology):
        if argv[:3] == ['ip', 'netns', 'del'] and argv[3] not in existing:
            continue
        if argv[:2] == ['ip', '-n'] and argv[2] not in existing:
            continue          # a link in a namespace already gone: gone with it
        try:
            run(argv)
        except CommandError as e:
            errors.append(str(e))
    remove_record(topology.prefix)
    for message in errors:
        log('hosts: tear-down: %s' % message)
    return errors


def remove_record(prefix):
    try:
        os.unlink(os.path.join(state_dir(), prefix + '.json'))
    except (OSError, HostsError):
        pass


def setns(fd):
    """Move the calling thread into the network namespace of ``fd``. Raises OSError."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.setns(fd, CLONE_NEWNET) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, 'setns: %s' % os.strerror(errno))


def new_topology(hosts, draws=16):
    """A topology whose prefix no run uses: no record and no name of it (review of session 34: a prefix
    drawn twice made one run overwrite, then remove, the other's record). At most ``draws`` draws."""
    pattern = run_prefix_pattern(PROJECT_PREFIX)
    taken = set(read_records())
    taken.update(pattern.match(n).group(1) for n in netns_names() + root_links() if pattern.match(n))
    for _ in range(draws):
        token = secrets.token_hex(2)
        if PROJECT_PREFIX + token not in taken:
            return Topology.make(hosts, token=token, taken=used_networks())
    raise HostsError('no free run prefix in %d draws: %d runs recorded or left over (hosts down removes '
                     'the leftovers)' % (draws, len(taken)))


class Freeze(object):
    """A freeze under way: thawed by its timer, or at once with :meth:`thaw` (idempotent)."""

    def __init__(self, pids, seconds):
        self.pids = pids
        self.seconds = seconds
        self.done = threading.Event()
        self._lock = threading.Lock()
        self._timer = threading.Timer(seconds, self.thaw)
        self._timer.daemon = True

    def start(self):
        send(signal.SIGSTOP, self.pids)
        self._timer.start()
        return self

    def thaw(self):
        with self._lock:
            if self.done.is_set():
                return
            self._timer.cancel()
            send(signal.SIGCONT, self.pids)
            self.done.set()

    def wait(self, timeout=None):
        return self.done.wait(timeout)


class Hosts(object):
    """Emulated hosts for the duration of a ``with`` block; always removed at its end.

    ``Hosts(['a', 'b'])`` or ``Hosts(topology)``. Inside, :meth:`run_in` starts processes in a host,
    and the fault methods act on hosts. Tear-down (:meth:`close`) kills every process of every host
    and removes every namespace and link; it runs on leaving the block, on SIGTERM/SIGINT (then the
    signal goes on: the previous handler, or the default's exit) and at interpreter exit.
    """

    def __init__(self, hosts, log=None):
        self._hosts = hosts
        self.log = log or (lambda message: sys.stderr.write(message + '\n'))
        self.net = None
        self._lock = threading.RLock()
        self._started = {}        # host -> [(Popen, psutil.Process)]
        self._freezes = []
        self._switch = None       # the power switch agent (power_switch()), stopped by close()
        self.powered_off_at = {}  # host -> wall time its link went down in its last power_off()
        self._isolated = set()    # hosts whose power_off has cut the link and stopped every process (read unlocked)
        self._previous = {}       # signum -> handler replaced
        self._open = False
        self._claimed = False     # the record is ours: close() may remove what carries the prefix
        self._home = None         # fd of the network namespace __enter__ ran in (close() goes back there)
        self._deferred = []       # signals that came during close(), delivered once it is done

    @property
    def topology(self):
        return self.net.topology

    def __enter__(self):
        check_platform()
        cleanup_leftovers(log=self.log)
        topology = self._hosts if isinstance(self._hosts, Topology) else new_topology(self._hosts)
        self.net = Network(topology)
        try:
            self._home = os.open('/proc/thread-self/ns/net', os.O_RDONLY)
        except OSError:
            self._home = None
        self._install_handlers()
        atexit.register(self.close)
        self._open = True
        try:
            write_record(self.net, _owner_record(), claim=True)   # a prefix taken: nothing of it is touched
            self._claimed = True
            carry_out(plan_up(topology), log=self.log)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    # -- processes --------------------------------------------------------------------------------
    def ip(self, name):
        return self.topology.host(name).ip

    def run_in(self, name, argv, env=None, **popen_args):
        """Start argv in host ``name`` (``ip netns exec``), with ROS_IP and ROS_HOSTNAME set to the
        host's address. The Popen; the process and its descendants are the host's."""
        with self._lock:
            if not self.net.runs(name):
                raise HostsError('cannot start %s in host %s: it is off' % (argv[0], name))
            host = self.topology.host(name)
            env = dict(os.environ if env is None else env, ROS_IP=host.ip, ROS_HOSTNAME=host.ip)
            popen = subprocess.Popen(['ip', 'netns', 'exec', host.namespace] + list(argv), env=env, **popen_args)
            try:
                self._started.setdefault(name, []).append((popen, psutil.Process(popen.pid)))
            except psutil.NoSuchProcess:
                pass
            return popen

    def processes(self, name):
        """pids of every live process of the host: started with run_in and their descendants, and
        every process in its network namespace."""
        pids = set(others_in(self.topology.host(name).namespace))
        for popen, proc in self._started.get(name, []):
            try:
                if proc.is_running():
                    pids.add(proc.pid)
                    pids.update(child.pid for child in proc.children(recursive=True))
            except psutil.NoSuchProcess:
                pass
        return sorted(pids - own_ids())

    # -- faults -----------------------------------------------------------------------------------
    def _do(self, decision):
        plan, changes = decision
        carry_out(plan, log=self.log)
        self.net.commit(changes)
        write_record(self.net, _owner_record())

    def partition(self, name, other=None):
        """Cut host ``name`` off (link down, processes go on); with ``other``: only those two."""
        with self._lock:
            self._do(self.net.partition(name) if other is None else self.net.partition_pair(name, other))

    def heal(self, name, other=None):
        with self._lock:
            self._do(self.net.heal(name) if other is None else self.net.heal_pair(name, other))

    def rate(self, name, kbit):
        with self._lock:
            self._do(self.net.rate(name, kbit))

    def unrate(self, name):
        with self._lock:
            self._do(self.net.unrate(name))

    def power_off(self, name, on_link_down=None, if_on=False, on_isolated=None):
        """Link down first, then every process of the host stopped and killed; returns their pids.
        Processes forked while they were being stopped are caught by further rounds.
        ``on_link_down()``, if given, is called the moment the link is down (the power loss).
        ``on_isolated(pids, running)``, if given, once the link is down and every thread of every
        process is seen stopped (``running``: those still not, after ISOLATE_WAIT: a thread in the
        kernel's uninterruptible sleep stops only on its way out): from then on the host can neither
        send nor run, which is all a promotion needs; the kill and the kernel's tear-down (tens of ms
        for a few rospy nodes) follow before this returns.
        ``if_on``: a host already off is left as it is ([] returned) instead of refused."""
        with self._lock:
            if if_on and self.net.state[self.topology.host(name).name] is HostState.OFF:
                return []
            plan, changes = self.net.power_off(name, self.processes(name))
            link, stop, kill = plan                    # link down, SIGSTOP, SIGKILL: in this order
            carry_out([link], log=self.log)            # nothing more leaves the host
            self.powered_off_at[name] = time.time()
            if on_link_down is not None:
                on_link_down()
            send(stop.signum, stop.pids)
            stopped = set(stop.pids)
            for _ in range(20):                        # bounded: forked before they were stopped
                new = set(self.processes(name)) - stopped
                if not new:
                    break
                send(stop.signum, sorted(new))
                stopped |= new
            if on_isolated is not None:
                running = wait_stopped(_processes(sorted(stopped)), ISOLATE_WAIT)
                self._isolated.add(name)
                on_isolated(sorted(stopped), sorted(p.pid for p in running))
            self._isolated.add(name)
            killed = stopped | set(kill.pids)
            left = kill_and_wait(sorted(killed))
            for _ in range(KILL_ROUNDS):               # review of session 34: entered meanwhile (ip netns exec)
                late = set(self.processes(name)) - killed
                if not late:
                    break
                killed |= late
                left += kill_and_wait(sorted(late))
            for popen, _ in self._started.get(name, []):
                try:
                    popen.wait(timeout=KILL_WAIT)
                except subprocess.TimeoutExpired:
                    pass
            self._started.pop(name, None)
            self.net.commit(changes)
            write_record(self.net, _owner_record())
            if left:
                raise HostsError('host %s: processes %s still alive after SIGKILL' % (name, left))
            return sorted(killed)

    def power_on(self, name):
        """The host made again from nothing (new namespace, same address), linked. Whatever got into
        the old namespace while the host was off is killed first (clear_namespace)."""
        with self._lock:
            decision = self.net.power_on(name)        # refused unless the host is off
            clear_namespace(self.topology.host(name).namespace, self.log)
            self._do(decision)
            self._isolated.discard(name)

    def freeze(self, target, seconds):
        """SIGSTOP of every process of host ``target`` (a name) or of one process (a pid, of a host
        of this run) for ``seconds``; a :class:`Freeze` (wait() returns once thawed)."""
        seconds = check_seconds(seconds)
        with self._lock:
            if isinstance(target, int) and not isinstance(target, bool):
                if not any(target in self.processes(n) for n in self.topology.hosts):
                    raise TopologyError('process %d is not a process of these hosts' % target)
                pids = [target]
            else:
                pids = self.processes(self.topology.host(target).name)
            freeze = Freeze(pids, seconds).start()
            self._freezes.append(freeze)
            return freeze

    def state(self, name):
        """'up', 'partitioned' or 'off'."""
        with self._lock:
            self.topology.host(name)
            return self.net.state[name].value

    # -- the power switch -------------------------------------------------------------------------
    def power_switch(self):
        """Start (once) the hosts' power switch: an agent in this process, outside every host, on a
        Unix-domain socket in the run's root-only state directory (the filesystem is shared by the
        namespaces, so this is a management network that no partition of the data network cuts).
        A request to power a host off is answered once its link is down and its processes are stopped
        (:meth:`power_off`'s ``on_isolated``): it can no longer answer anyone, so a promotion need
        not wait for the kill and the kernel's tear-down, which go on after the answer; the host
        cannot be powered on before they are done. Returns the :class:`aft_ftm.power_switch_exec.SwitchServer`; its spec
        for Recovery's ``~power_switch`` is ``'unix:' + switch.path``. Stopped by :meth:`close`."""
        from .power_switch_exec import SwitchServer
        with self._lock:
            if self._switch is None:
                path = os.path.join(state_dir(), self.topology.prefix + '.switch')
                self._switch = SwitchServer(path, self._switch_off, self._switch_state, self.log).start()
            return self._switch

    def _switch_off(self, name):
        self.topology.host(name)
        started = time.monotonic()
        isolated, outcome = threading.Event(), {}

        def off():
            try:
                outcome['pids'] = self.power_off(name, on_isolated=lambda pids, running: (
                    outcome.update(stopped=len(pids), running=running, isolated=time.monotonic() - started),
                    isolated.set()))
            except Exception as e:   # after the answer: said in the log; before it: the switch's error
                outcome['error'] = e
                if isolated.is_set():
                    self.log('power switch: host %s: %s' % (name, e))
            finally:
                isolated.set()
        threading.Thread(target=off, name='power-off-%s' % name, daemon=True).start()
        isolated.wait()
        if 'isolated' not in outcome:
            raise outcome.get('error') or HostsError('host %s: power off ended before the host was isolated' % name)
        late = outcome['running']
        return 'link down and %d processes stopped in %.1f ms%s; their kill goes on' % (
            outcome['stopped'] - len(late), outcome['isolated'] * 1e3,
            ' (%d in the kernel, cut off by the link: %s)' % (len(late), late) if late else '')

    def _switch_state(self, name):
        self.topology.host(name)
        if name in self._isolated:   # not behind the lock: a power_off in progress holds it until its kill ends
            return 'off'
        with self._lock:
            return 'off' if self.net.state[name] is HostState.OFF else self.net.state[name].value

    # -- tear-down --------------------------------------------------------------------------------
    def close(self):
        """Kill every process of the hosts, remove every namespace and link and the record.
        Idempotent; never raises, but a SIGINT/SIGTERM that came meanwhile goes on once it is done."""
        with self._lock:
            if not self._open:
                return
            self._open = False
            self._defer_signals()
            try:
                self._go_home()
                if self._switch is not None:
                    self._switch.stop()
                for freeze in self._freezes:
                    freeze.thaw()
                if self._claimed:       # else the prefix may be another run's: nothing of ours to remove
                    for name in self.topology.hosts:
                        pids = self.processes(name)
                        if pids:
                            kill_and_wait(pids)
                for launched in self._started.values():
                    for popen, _ in launched:
                        try:
                            popen.wait(timeout=KILL_WAIT)
                        except subprocess.TimeoutExpired:
                            pass
                if self._claimed:
                    tear_down(self.topology, self.log)
            except Exception as e:      # shutdown never raises
                self.log('hosts: tear-down failed: %s' % e)
            finally:
                previous = dict(self._previous)
                self._restore_handlers()
                try:
                    atexit.unregister(self.close)
                except Exception:
                    pass
                if self._home is not None:
                    os.close(self._home)
                    self._home = None
            deferred, self._deferred = self._deferred, []
        for signum in sorted(set(deferred)):    # the signal goes on now, as _on_signal would have taken it
            self.log('hosts: signal %d came during the tear-down: handled now it is done' % signum)
            # (not raise_signal: with the default handler back, SIGTERM killed the process outright and
            # the caller's finally blocks never ran; review of session 34)
            _chain(previous.get(signum), signum, None)

    def _go_home(self):
        """Back to the network namespace __enter__ ran in (review of session 34: a signal handled while
        the campaign's main thread lived in the rosmaster host ran the tear-down from there)."""
        if self._home is None:
            return
        try:
            here = os.stat('/proc/thread-self/ns/net')
            home = os.fstat(self._home)
            if (here.st_dev, here.st_ino) != (home.st_dev, home.st_ino):
                setns(self._home)
        except OSError as e:
            self.log('hosts: could not return to the namespace the hosts were made from: %s' % e)

    def _defer_signals(self):
        """SIGTERM/SIGINT during close() are held until it is done (review of session 34: a second
        Ctrl-C raised KeyboardInterrupt in the middle of the tear-down, which then left hosts behind)."""
        if threading.current_thread() is not threading.main_thread():
            return
        for signum in self._previous:
            signal.signal(signum, self._defer)

    def _defer(self, signum, frame):
        self._deferred.append(signum)   # only noted: a log write here could re-enter the one interrupted

    def _install_handlers(self):
        if threading.current_thread() is not threading.main_thread():
            return
        for signum in (signal.SIGTERM, signal.SIGINT):
            if signal.getsignal(signum) == signal.SIG_IGN:
                continue   # ignored by this process (a background job's SIGINT): it stays ignored
            self._previous[signum] = signal.signal(signum, self._on_signal)

    def _restore_handlers(self):
        if threading.current_thread() is not threading.main_thread():
            return
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous.clear()

    def _on_signal(self, signum, frame):
        previous = self._previous.get(signum)
        self.close()
        _chain(previous, signum, frame)


def _chain(previous, signum, frame):
    """Take a signal as the handler ``previous`` (the one the hosts replaced) would have."""
    if previous == signal.SIG_IGN:
        return
    if callable(previous):
        previous(signum, frame)
    elif signum == signal.SIGINT:
        raise KeyboardInterrupt()
    else:
        raise SystemExit(128 + signum)
