"""The service manager as a ROS node: spawns the configured services as child processes, watches
them, and carries out the decisions of aft_service_manager.services.Supervisor."""
import collections
import json
import math
import os
import select
import signal
import subprocess
import threading
import time

import psutil
import rospy
from aft_msgs.msg import SafeState, ServiceHeartbeat
from aft_msgs.srv import ServiceCommand, ServiceCommandResponse
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from std_msgs.msg import String
from std_srvs.srv import Trigger, TriggerResponse

from aft_ftm import config as params
from aft_ftm.process_start import started as process_started
from aft_service_manager import channel, programs, tree, trust
from aft_service_manager.services import Sample, ServiceConfigError, State, Supervisor, parse_config
from aft_ftm.ros.params import param
from aft_service_manager.ros.service_heartbeat import TOPIC

LEVELS = {State.RUNNING: DiagnosticStatus.OK, State.STARTING: DiagnosticStatus.WARN,
          State.RESTARTING: DiagnosticStatus.WARN, State.STOPPED: DiagnosticStatus.STALE,
          State.ERROR: DiagnosticStatus.ERROR, State.FAILED: DiagnosticStatus.ERROR}


def resolve_rosrun(command, where):
    """``rosrun PKG TYPE ARGS`` as the node's own executable and ARGS, found once, at start: rosrun
    looks the package up at every start, which added about 300 ms to each restart. A node that
    does not exist is a configuration error."""
    if len(command) < 3 or os.path.basename(command[0]) != 'rosrun':
        return command
    import roslib.packages
    import rospkg
    try:
        found = roslib.packages.find_node(command[1], command[2])
    except rospkg.ResourceNotFound:
        found = None
    if not found:
        raise params.ConfigError('%s: rosrun %s %s: no such node' % (where, command[1], command[2]))
    return [found[0]] + command[3:]


class AdoptedProcess(object):
    """What the manager needs of a Popen, for a service process an earlier manager started (it is not
    this manager's child: its end is seen through its pidfd, its exit status is not known)."""

    def __init__(self, pid):
        self.pid = pid
        self.returncode = None
        self._fd = os.pidfd_open(pid)
        self._lock = threading.Lock()

    def poll(self):
        return self.wait(0.0, raise_timeout=False)

    def wait(self, timeout=None, raise_timeout=True):
        # the pidfd stays open until the process is seen gone (a close under a waiter is not raced)
        fd = self._fd
        if self.returncode is None and fd is not None and select.select([fd], [], [], timeout)[0]:
            with self._lock:
                if self.returncode is None:
                    self.returncode = 'unknown (adopted)'
                    os.close(self._fd)
                    self._fd = None
        if self.returncode is None and raise_timeout:
            raise subprocess.TimeoutExpired('adopted pid %d' % self.pid, timeout)
        return self.returncode


class Child(object):
    """A service's process (a session of its own, so that everything it starts goes with it) and
    what the manager measures of it: CPU use over a window, memory, whether it is stopped."""

    def __init__(self, popen, cpu_window, slot=None, spare=False, instance=0, tree=None, handle=None, watchdog=None):
        self.popen = popen
        self.watchdog = watchdog   # its kernel watchdog (channel.Watchdog), re-armed by each beat, or None
        self.promote_w = None      # a spare's promotion pipe (write end), or None
        self.closed_lock = threading.Lock()
        self.tree, self.handle = tree, handle   # every process of it, wherever they went (aft_service_manager.tree)
        self.proc = psutil.Process(popen.pid)
        self.pidfd = os.pidfd_open(popen.pid)   # readable once it exits: its end is seen at once
        self.start = process_started(popen.pid, zombie=True)   # as the pid file names it (None: gone already)
        self.cpu_window = cpu_window
        self.cpu_marks = []   # (wall time, cpu seconds)
        self.others = {}      # pid -> psutil.Process: the service's processes beside its leader
        self.cpu_seen = {}    # pid -> the CPU seconds last read of it
        self.cpu_total = 0.0  # CPU seconds of the whole service, summed from each process's increments
        self.slot = slot      # its beat slot (local channel), or None
        self.beats = 0        # beats seen in the slot
        self.spare = spare    # a warm spare, not yet promoted
        self.ready = False    # a spare that said it is set up
        self.instance = instance
        self.born = time.monotonic()   # a spare not ready start_timeout after this is replaced

    def close(self):
        """Release what the manager holds of it (once it is killed or gone). Once, whoever calls."""
        with self.closed_lock:
            self._close()

    def _close(self):
        if self.tree is not None and self.handle is not None:
            self.tree.kill(self.handle, 0.0)   # its cgroup removed if empty
            self.handle = None
        if self.pidfd is not None:
            os.close(self.pidfd)
            self.pidfd = None
        if self.watchdog is not None:
            self.watchdog.close()
            self.watchdog = None
        if self.promote_w is not None:
            os.close(self.promote_w)
            self.promote_w = None
        if self.slot is not None:
            self.slot.close()
            try:
                os.unlink(self.slot.path)
            except OSError:
                pass
            self.slot = None

    def read_beat(self):
        """(monotonic time of the last beat, status) if it beat since the last read, else None."""
        seen = self.slot.read() if self.slot is not None else None
        if seen is None or seen[0] == self.beats:
            return None
        self.beats = seen[0]
        return seen[1], seen[2]

    @property
    def pid(self):
        return self.popen.pid

    def _processes(self):
        """The service's processes beside its leader: the members of its cgroup, else the leader's
        descendants (a process that left its session for a tree of its own is its tree's to kill,
        not measured here)."""
        if self.tree is not None and self.handle is not None and getattr(self.tree, 'kind', '') == 'cgroup':
            pids = set(self.tree.members(self.handle))
        else:
            try:
                pids = {child.pid for child in self.proc.children(recursive=True)}
            except psutil.Error:
                pids = set()
        pids.discard(self.proc.pid)
        for pid in list(self.others):
            if pid not in pids:
                del self.others[pid]
        for pid in pids - set(self.others):
            try:
                self.others[pid] = psutil.Process(pid)
            except psutil.Error:   # gone meanwhile
                pass
        return list(self.others.values())

    def sample(self, resources):
        """Whether it lives; with ``resources``, the CPU (%, over cpu_window), the memory (RSS) and
        whether it is stopped, of the whole service: its leader and every process it started. The
        leader's alone were measured: a wrapper (sh -c, roslaunch) or a forked worker leaking memory or
        spinning never tripped a limit, and a worker stopped never looked hung (review of session 36)."""
        code = self.popen.poll()
        if code is not None:
            return Sample(False, code, False, None, None)
        if not resources:
            return Sample(True, None, False, None, None)
        try:
            with self.proc.oneshot():
                stopped = self.proc.status() in (psutil.STATUS_STOPPED, psutil.STATUS_TRACING_STOP)
                times = self.proc.cpu_times()
                rss = self.proc.memory_info().rss
        except psutil.NoSuchProcess:
            return Sample(False, self.popen.poll(), False, None, None)
        cpu_now = {self.proc.pid: times.user + times.system}
        for other in self._processes():
            try:
                with other.oneshot():
                    stopped = stopped or other.status() in (psutil.STATUS_STOPPED, psutil.STATUS_TRACING_STOP)
                    t = other.cpu_times()
                    rss += other.memory_info().rss
                cpu_now[other.pid] = t.user + t.system
            except psutil.Error:   # ended between the listing and the reading
                continue
        # Each process's increment since it was last read: one that ended takes its last moments with it
        # (never counted twice, as the leader's children_ times would once it reaps it), and the sum
        # never goes back.
        for pid, seconds in cpu_now.items():
            self.cpu_total += max(0.0, seconds - self.cpu_seen.get(pid, 0.0))
        self.cpu_seen = cpu_now
        now = time.monotonic()
        self.cpu_marks.append((now, self.cpu_total))
        while len(self.cpu_marks) > 2 and now - self.cpu_marks[1][0] >= self.cpu_window:
            self.cpu_marks.pop(0)
        cpu = None
        first = self.cpu_marks[0]
        if now - first[0] >= self.cpu_window:
            cpu = 100.0 * (self.cpu_marks[-1][1] - first[1]) / (now - first[0])
        return Sample(True, None, stopped, cpu, rss)

    def signal_session(self, sig):
        """Signal the service's process group, only while its leader is not reaped: a reaped leader's pid,
        and so its group id, may be another process's by then (a service stopped by an operator hours
        before the manager's shutdown). What is left of the group is its tree's to kill. Returns whether
        it was sent."""
        if self.popen.poll() is not None:   # reaped now if it had ended (an adopted one: seen by its pidfd)
            return False
        try:
            os.killpg(self.popen.pid, sig)
        except (ProcessLookupError, PermissionError):
            return False
        return True

    def kill(self, timeout, wait=True):
        """SIGKILL the whole session at once (a faulty service is not asked), and every other process
        of it (its tree: those in sessions of their own too). With ``wait``, it is reaped here if it
        dies within 0.2 s (it almost always does), else by a thread, so the manager's loop never
        waits long; without, the caller ends it (:meth:`end`) off the loop: once SIGKILL is sent,
        nothing of it runs again, and its replacement need not wait for the kernel's clean-up."""
        self.signal_session(signal.SIGKILL)
        if self.tree is not None and self.handle is not None:
            self.tree.signal(self.handle)
        if not wait:
            return
        try:
            self.popen.wait(min(timeout, 0.2))
        except subprocess.TimeoutExpired:
            threading.Thread(target=self.popen.wait, daemon=True).start()
        self._kill_tree(min(timeout, 0.5))

    def end(self, timeout):
        """After kill(wait=False), off the manager's loop: reap it, wait for its whole tree to be gone,
        release what the manager holds of it."""
        try:
            self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            rospy.logerr('service process %d not reaped %.1f s after SIGKILL', self.popen.pid, timeout)
        self._kill_tree(timeout)
        self.close()

    def _kill_tree(self, timeout):
        if self.tree is not None and self.handle is not None and not self.tree.kill(self.handle, timeout):
            rospy.logerr('service process tree %s: processes left after %.1f s: %s', self.handle, timeout,
                         self.tree.members(self.handle))

    def alive(self):
        return self.popen.poll() is None

    def owns(self, pid):
        """Whether pid is this service's process or one of its descendants (or in its tree)."""
        if pid == self.popen.pid:
            return True
        if self.tree is not None and self.handle is not None and self.tree.owns(self.handle, pid):
            return True
        try:
            return any(p.pid == pid for p in self.proc.children(recursive=True))
        except psutil.Error:
            return False

    def terminate(self, timeout):
        """SIGTERM the session, SIGKILL it after timeout (an operator's stop)."""
        try:
            if self.signal_session(signal.SIGTERM):
                self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            self.kill(timeout)
        self._kill_tree(timeout)   # what it left in sessions of its own goes too
        self.close()


SPARE_AFTER_PROMOTION = 0.1   # s
LOCK_WAIT = 3.0               # s: beyond kill_timeout, for a manager of the same name that is stopping


def _instance_of(handle):
    """The instance number in a tree's handle (``.../<name>-<n>`` or ``<owner>.<name>-<n>.<tag>``), 0 if none."""
    import re
    found = re.findall(r'-(\d+)', str(handle))
    return int(found[-1]) if found else 0


def publisher_endpoints(topic, header):
    """(this end, the publisher's end) of the connection of this node's subscription to topic that
    carried a message (its ``_connection_header``: rospy gives every message of a connection that very
    dict), as (host, port) pairs; None if there is none."""
    from rospy.impl.registration import get_topic_manager
    impl = get_topic_manager().get_subscriber_impl(topic)
    for connection in list(getattr(impl, 'connections', None) or ()):
        sock = getattr(connection, 'socket', None)
        if getattr(connection, 'header', None) is header and sock is not None:
            try:
                return sock.getsockname()[:2], sock.getpeername()[:2]
            except OSError:
                return None
    return None


def _lost_identity(entry):
    """A lost instance as the record names it: (service, pid, start on the boot clock)."""
    return (str(entry.get('service')), int(entry['pid']), round(float(entry['create_time']), 6))


def _counted_lost(record):
    """The lost instances a record says were counted ((service, pid, start) tuples); malformed: none."""
    counted = set()
    items = record.get('lost_counted', []) if isinstance(record, dict) else []
    for item in items if isinstance(items, list) else ():
        try:
            service, pid, start = item
            counted.add(_lost_identity({'service': service, 'pid': pid, 'create_time': start}))
        except (TypeError, ValueError, ArithmeticError):   # Infinity, 1e999: int() overflows
            continue
    return counted


class ServiceManagerNode(object):
    """Spawns, watches, restarts, terminates and escalates (see aft_service_manager.services).

    Parameters:
        ~config (str, required): the configuration file (YAML; keys in aft_service_manager.services)
        ~resource_period (float, 0.1 s): how often CPU, memory and stopped processes are measured, for
            the services with limits or without heartbeats (an exit is seen at once, through the
            process's pidfd; a heartbeat timeout at its deadline, on the manager's period)
        ~heartbeat_topic (str, /aft/service_heartbeat): where the services' heartbeats come
    The local channel (aft_service_manager.channel): each service spawned here gets a beat slot and
    the manager's socket (<state_dir>/manager_<name>.sock) in its environment, and beats there
    unless its heartbeat_channel is ros. A warm spare (warm_spare: true) is spawned with AFT_SPARE=1
    and spare_args, and promoted with SIGUSR1.
    Subscribes:
        (~heartbeat_topic) (aft_msgs/ServiceHeartbeat): every service's heartbeats (passed to the services
            as AFT_HEARTBEAT_TOPIC); a beat from a process the manager has replaced is ignored
    Publishes:
        safe_state (aft_msgs/SafeState, latched): the safe-state command
        /diagnostics (diagnostic_msgs/DiagnosticArray): every service's health, each second and when the
            safe state changes
        ~events (std_msgs/String): one JSON record per fault detected and per decision
    Services:
        ~start, ~stop, ~restart, ~status (aft_msgs/ServiceCommand), ~clear_safe_state (std_srvs/Trigger)
    """

    programs = None   # the on_failure programs running (aft_service_manager.programs.Programs), from __init__

    def __init__(self):
        path = param('config', params.non_empty_str, required=True)
        try:
            with open(path) as f:
                self.config = parse_config(f.read(), source=path)
        except OSError as e:
            raise params.ConfigError('cannot read the configuration %s: %s' % (path, e.strerror))
        except ServiceConfigError as e:
            raise params.ConfigError(str(e))
        for name, service in self.config['services'].items():
            for key in ('command', 'program'):
                if service[key]:
                    service[key] = resolve_rosrun(service[key], 'services.%s.%s' % (name, key))
        manager = self.config['manager']
        try:
            manager['state_dir'] = trust.ensure_private_dir(manager['state_dir'] or trust.default_state_dir())
        except ServiceConfigError as e:
            raise params.ConfigError('%s: %s' % (path, e))
        self.prefix = 'manager%s' % rospy.get_name().replace('/', '_')
        # One manager of a name at a time, before anything of the name is touched (its trees, socket,
        # pid file and record): a second one adopted what the first was stopping, and the first's
        # shutdown killed the second's services (review of session 34). Held for the process's life.
        # One asked to stop (the master stops a node whose name another takes) is waited for.
        try:
            self.name_lock = trust.hold_lock(os.path.join(manager['state_dir'], self.prefix + '.lock'),
                                             wait=manager['kill_timeout'] + LOCK_WAIT)
        except (ServiceConfigError, OSError) as e:
            raise params.ConfigError('%s: %s' % (rospy.get_name(), e))
        self.resource_period = param('resource_period', params.positive_float, 0.1)
        self.heartbeat_topic = rospy.resolve_name(param('heartbeat_topic', params.non_empty_str, TOPIC))
        self.period = self.config['manager']['period']
        self.supervisor = Supervisor(self.config)
        self.children = {}
        self.lock = threading.RLock()
        self.total_memory = psutil.virtual_memory().total
        self.heartbeats = 0
        self.unknown_heartbeats = 0
        self.stale_heartbeats = 0     # from a process the manager has replaced: ignored
        self.refused_heartbeats = 0   # from no process of the service's (forged, or pid 0): refused, said
        self.replaced = {}            # name -> pids of the service's processes the manager replaced
        self.origins = trust.HeartbeatOrigins(self._published_by)
        self.stopping = {}            # name -> Child being stopped by an operator (SIGTERM, then SIGKILL)
        self.published_safe = None    # the safe state last published (its reason, None: not in it)
        self.pid_file = os.path.join(self.config['manager']['state_dir'],
                                     'manager%s.pids' % rospy.get_name().replace('/', '_'))
        # The safe state and the services left down, for a manager of this name started again.
        self.record_file = os.path.join(self.config['manager']['state_dir'],
                                        'manager%s.record' % rospy.get_name().replace('/', '_'))
        self.recorded = None          # what record_file holds (written only when it changes)
        self.own = {}                 # path -> identity of the pid file and record this manager wrote or took
        self.own_trees = collections.deque(maxlen=1024)   # the trees it made or adopted (shutdown kills no other)
        self.spares = {}              # name -> Child: its warm spare, idle until promoted
        self.closing = False          # shutting down: nothing more is spawned
        self.instances = 0            # a number per process spawned (a spare's {n})
        self.spare_retry = {}         # name -> when to try again to start its spare (it died)
        self.boot = trust.boot_id()   # this boot: what the pid file recorded under another ended with it
        self.lost = {}                # name -> how its instance, left by an earlier manager, was found ended
        self.unacted = {}             # name -> the pid-file entry of its lost instance, kept there until counted
        self.counted = set()          # (service, pid, start) of lost instances counted in the record this set-up
        self.already_counted = set()  # ... those the record of the previous manager says it counted
        self.programs = programs.Programs()   # the on_failure programs running, watched to their end
        self.local = None             # the manager's end of the local channel
        self.tree = tree.make(self.prefix.replace('/', '_'))   # a cgroup per instance, or a tag
        self.wake_r, self.wake_w = os.pipe()   # a command or a ROS heartbeat wakes the loop
        os.set_blocking(self.wake_w, False)
        self.wakes = 0                # loop iterations (the bench's cost of supervision)
        self.cycle_cpu = self.diagnostics_cpu = 0.0   # CPU seconds the loop spent checking, and on diagnostics

    def setup(self, timeout):
        self.safe_pub = rospy.Publisher('safe_state', SafeState, queue_size=1, latch=True)
        self.diag_pub = rospy.Publisher('/diagnostics', DiagnosticArray, queue_size=10)
        self.events_pub = rospy.Publisher('~events', String, queue_size=100)
        rospy.Subscriber(self.heartbeat_topic, ServiceHeartbeat, self._on_heartbeat, queue_size=1000, tcp_nodelay=True)
        held = self._restore()
        self.published_safe = self.supervisor.safe_state
        self.published_also = 0   # how many of supervisor.also_unsafe were said
        if self.published_safe:
            rospy.logerr('%s: SAFE STATE, held from the previous run: %s', rospy.get_name(), self.published_safe)
        self.safe_pub.publish(SafeState(active=self.published_safe is not None, reason=self.published_safe or '',
                                        stamp=rospy.Time.now()))
        rospy.on_shutdown(self.shutdown)
        # the socket first: what adopted services say from now on reaches it
        self.local = channel.ManagerSocket(channel.socket_path(self.config['manager']['state_dir'], self.prefix))
        with self.lock:
            adopted = self._kill_orphans()
        for handle in self.tree.leftovers():   # whatever escaped the pid file: the trees themselves
            if handle not in adopted:
                rospy.logwarn('%s: killing %s, left by an earlier manager', rospy.get_name(), handle)
                self.tree.kill(handle, self.config['manager']['kill_timeout'])
            self.instances = max(self.instances, _instance_of(handle))
        rospy.loginfo('%s: every process of a service is tracked by %s', rospy.get_name(), self.tree.describe())
        now = time.monotonic()
        with self.lock:
            # The instances found ended first: all taken as started, then each fault decided, counted in
            # the record, and acted on in turn (one stops or restarts what must not run without it, or
            # restarts with it); then the others, in dependency order, each told what those faults mean
            # for it (reviews of session 39).
            lost = self._take_lost(held)
            # Only these are started below: not adopted, not held, not lost, not yet started. One the
            # lost ones' faults stopped, failed or restarted is theirs to run (review of session 39).
            untouched = {n for n, s in self.supervisor.services.items() if n not in lost and n not in held and
                         n not in self.children and s.state == State.STOPPED}
            self._act_on_lost(lost, now)
            for name in self.supervisor.order:
                service = self.supervisor[name]
                if name in lost or (name not in untouched and name not in self.children):
                    if name not in lost and service.spawn_at is not None:   # a hold resumed: due() spawns it
                        rospy.logwarn('%s: %s: %s', rospy.get_name(), name, service.reason)
                    continue
                elif service.config['autostart'] and name not in self.children:
                    verb, why = self.supervisor.starts_after_lost(name, lost, now)
                    if verb == 'spawn':
                        self._spawn(name, now)
                    else:
                        rospy.logwarn('%s: %s not started: %s', rospy.get_name(), name, why)
                        self._event('not_started' if verb == 'skip' else 'held', name, why, now)
                        # Kept in the record at once: the losses that decided it are counted already,
                        # and a manager killed during the spawns below would start it (review of
                        # session 40), or forget a critical one's escalation.
                        self._sync_safe_state()
                elif name in self.children:
                    self._ensure_spare(name)
            self._sync_safe_state()
        if self.closing:   # a shutdown ran during those spawns, on this thread: what it could not see goes too
            self._stop_left_by_shutdown()
            return False
        threading.Thread(target=self._loop, name='service_manager', daemon=True).start()
        # the operators' services last: no command meets a manager still adopting or spawning
        for verb in ('start', 'stop', 'restart', 'status'):
            rospy.Service('~' + verb, ServiceCommand, lambda req, verb=verb: self._on_command(verb, req))
        rospy.Service('~clear_safe_state', Trigger, self._on_clear)
        return True

    def _take_lost(self, held):
        """The set-up's first step with the instances found ended (self.lost): {name: how} of those to
        count (not held down by the record, not adopted); the pid file written again, still naming
        them (self.unacted) until the record counts them."""
        lost = {n: why for n, why in self.lost.items() if n not in self.children and n not in held}
        # Lost, but a newer instance of it runs (adopted): counted, nothing done; named in the pid file
        # until the record holds the count (review of session 41: it was dropped here, counted nowhere).
        replaced = {n: why for n, why in self.lost.items() if n in self.children and n not in held}
        for name, why in sorted(replaced.items()):
            self.supervisor.replaced_unwatched(name, why, time.monotonic())
            rospy.logwarn('%s: %s: an instance ended while no manager watched it, already replaced: counted',
                          rospy.get_name(), name)
            if name in self.unacted:
                self.counted.add(_lost_identity(self.unacted[name]))
        counted_now = bool(replaced) and self._sync_safe_state()
        self.unacted = {n: e for n, e in self.unacted.items() if n in lost or (n in replaced and not counted_now)}
        if self._record_pids():
            # What the previous manager counted is no longer named in the pid file: its record may forget it.
            self.counted -= self.already_counted
        return lost

    def _act_on_lost(self, lost, now):
        """The instances found ended ({name: how}): all taken as started; then each fault decided,
        counted in the record before its entry leaves the pid file, and acted on. A manager killed in
        between leaves the next one each loss once: named in the pid file, or counted in the record
        (whose ``lost_counted`` the next one skips). A failed write of the record keeps the entry in
        the pid file; a failed write of the pid file keeps it in ``lost_counted``."""
        for name in self.supervisor.take_as_started(lost, now):
            decision = self.supervisor.ended_unwatched(name, lost[name], now)
            entry = self.unacted.get(name)
            if entry is not None:
                self.counted.add(_lost_identity(entry))
                if self._sync_safe_state():
                    del self.unacted[name]
            if decision is not None:
                self._fault(decision, now)
        if lost and self._record_pids():   # only those whose count is not on disk yet still named
            self.counted = {_lost_identity(e) for e in self.unacted.values()}
            self._sync_safe_state()

    # -- processes -------------------------------------------------------------------------------
    def _spawn(self, name, now):
        """Start name: promote its warm spare if one is ready, else a cold start; then (re)make its spare."""
        service = self.supervisor[name]
        spare = self.spares.get(name)
        if spare is not None and spare.ready and spare.alive():
            del self.spares[name]
            try:
                if spare.promote_w is not None:
                    os.write(spare.promote_w, b'p')      # its waiting thread wakes at once
                else:
                    os.kill(spare.pid, signal.SIGUSR1)   # adopted: no pipe to it
            except OSError as e:   # gone meanwhile: a cold start instead
                spare.close()
                rospy.logwarn('%s: the spare of %s cannot be promoted: %s', rospy.get_name(), name, e)
            else:
                spare.spare = False
                if spare.promote_w is not None:
                    os.close(spare.promote_w)
                    spare.promote_w = None
                self.children[name] = spare
                self._record_pids()
                service.spawned(now)
                self._event('spawned', name, 'warm spare pid %d promoted' % spare.pid, now, starts=service.starts,
                            pid=spare.pid, promoted=True)
                # the next spare a little later: its fork and start-up would take the CPU the promoted
                # instance needs for its first cycle (2 cores)
                self.spare_retry[name] = time.monotonic() + SPARE_AFTER_PROMOTION
                return
        try:
            child = self._start_process(name, spare=False)
        except (OSError, psutil.Error) as e:
            if self.closing:
                return   # the shutdown stops everything: no fault, no retry
            self._spawn_failed(self.supervisor.spawn_failed(name, now, str(e)), now)
            if service.state in (State.STOPPED, State.FAILED):
                self._kill_from(self.spares, name)
            return
        self.children[name] = child
        self._reused(child.pid)   # its beats are its own, not a replaced instance's (review of session 34)
        self._record_pids()
        service.spawned(now)
        self._event('spawned', name, 'pid %d' % child.pid, now, starts=service.starts, pid=child.pid)
        self._ensure_spare(name)

    def _fault(self, decision, now, act_now=None):
        """A fault decided (a check's, or an instance found ended at the start): said on rosout too,
        whatever the policy does about it (a service restarted for ever more slowly than its limit, or
        left stopped by its policy, showed only on ~events; review of session 36), on ~events, then
        acted on (at act_now, default now)."""
        rospy.logwarn('%s: %s: %s: %s; %s', rospy.get_name(), decision.service, decision.kind, decision.detail,
                      ', '.join('%s %s' % a for a in decision.actions) or 'nothing done')
        self._event('fault', decision.service, decision.detail, now, kind=decision.kind,
                    actions=decision.actions, escalate=decision.escalate)
        self._act(decision, now if act_now is None else act_now)

    def _spawn_failed(self, decision, now):
        """A spawn that failed is a fault: reported and acted on as any other (it is retried, and an
        exhausted limit escalates; review of session 34)."""
        rospy.logerr('%s: %s: %s', rospy.get_name(), decision.service, decision.detail)
        self._event('fault', decision.service, decision.detail, now, kind=decision.kind, actions=decision.actions,
                    escalate=decision.escalate)
        self._act(decision, now)

    def _start_process(self, name, spare):
        """A process of service name (its active instance, or a warm spare), in a session of its own,
        with its local channel; raises OSError or psutil.Error (nothing left running)."""
        if self.closing:
            raise OSError('the manager is shutting down')
        cfg, manager = self.supervisor[name].config, self.config['manager']
        self.instances += 1
        state_file = cfg['state_file'] or os.path.join(manager['state_dir'], name + '.json')
        env = dict(os.environ, AFT_SERVICE=name, AFT_STATE_FILE=state_file, AFT_HEARTBEAT_TOPIC=self.heartbeat_topic,
                   AFT_RESTORE_STATE='1' if cfg['restore_state'] else '0')
        slot = watchdog = None
        promote_r = promote_w = None
        command = list(cfg['command'])
        if spare:
            command += [a.replace('{n}', str(self.instances)) for a in cfg['spare_args']]
            env[channel.ENV_SPARE] = '1'
            promote_r, promote_w = os.pipe()
            env[channel.ENV_PROMOTE] = str(promote_r)
        if cfg['heartbeat_channel'] == 'local' or spare:
            slot = channel.BeatSlot(channel.slot_path(manager['state_dir'], '%s.%s.%d' % (
                self.prefix, name, self.instances)), create=True)
            env.update({channel.ENV_SLOT: slot.path, channel.ENV_SOCKET: self.local.address()})
        popen = None
        try:
            if slot is not None and cfg['heartbeat_timeout'] is not None:
                watchdog = channel.Watchdog()
                env.update({channel.ENV_WATCHDOG: str(watchdog.fd),
                            channel.ENV_WATCHDOG_TIMEOUT: repr(cfg['heartbeat_timeout'])})
            prefix, extra, handle = self.tree.prepare('%s-%d' % (name, self.instances))
            self.own_trees.append(handle)
            env.update(extra)
            popen = subprocess.Popen(prefix + command, env=env, stdin=subprocess.DEVNULL, start_new_session=True,
                                     pass_fds=tuple(fd for fd in (watchdog and watchdog.fd, promote_r) if fd))
            if self.closing:
                # The shutdown ran meanwhile, on this very thread (rospy runs it in the signal handler of
                # the main thread, which spawns at set-up; the lock is re-entrant): it did not see this
                # process, which would outlive the manager unsupervised.
                raise OSError('the manager is shutting down: %s started during its shutdown is stopped' % name)
            child = Child(popen, cfg['cpu_window'], slot, spare, self.instances, self.tree, handle, watchdog)
            child.promote_w, promote_w = promote_w, None
            return child
        except BaseException:
            if promote_w is not None:
                os.close(promote_w)
            if watchdog is not None:
                watchdog.close()
            if popen is not None:   # started but cannot be watched: not left running unwatched
                try:
                    os.killpg(popen.pid, signal.SIGKILL)
                except OSError:
                    pass
                threading.Thread(target=popen.wait, daemon=True).start()
            if slot is not None:
                slot.close()
                os.unlink(slot.path)
            raise
        finally:
            if promote_r is not None:
                os.close(promote_r)   # the spare's end: this process keeps the other

    def _ensure_spare(self, name):
        """Start name's warm spare if it should have one and has none (it sets up while the active one runs)."""
        service = self.supervisor[name]
        if not service.config['warm_spare'] or name in self.spares or \
                service.state not in (State.STARTING, State.RUNNING):
            return
        if time.monotonic() < self.spare_retry.get(name, 0.0):
            return
        try:
            self.spares[name] = self._start_process(name, spare=True)
        except (OSError, psutil.Error) as e:
            self.spare_retry[name] = time.monotonic() + 1.0
            rospy.logwarn('%s: the warm spare of %s cannot be started: %s', rospy.get_name(), name, e)
            return
        self._reused(self.spares[name].pid)   # promoted, its beats are its own (review of session 34)
        self._record_pids()
        self._event('spare_started', name, 'pid %d' % self.spares[name].pid, time.monotonic(),
                    pid=self.spares[name].pid)

    def _replace_unready_spares(self, now):
        """A warm spare that has not said it is ready within its service's start_timeout (hung in its
        set-up) is killed and another started a second later: kept, it was never promoted, and every
        restart silently fell back to a cold start."""
        for name, spare in list(self.spares.items()):
            timeout = self.supervisor[name].config['start_timeout']
            if spare.ready or now - spare.born <= timeout:
                continue
            self._kill_from(self.spares, name)
            self.supervisor[name].errors['spare_start_timeout'] += 1
            self.spare_retry[name] = now + 1.0
            rospy.logwarn('%s: the warm spare of %s (pid %d) was not ready within %.1f s: replaced (restarts '
                          'meanwhile are cold)', rospy.get_name(), name, spare.pid, timeout)
            self._event('spare_start_timeout', name, 'pid %d not ready within %.1f s' % (spare.pid, timeout), now)

    def _record_pids(self, stopping=False):
        """The process groups of the running services (pid, start time, command line), so that a
        manager started after this one was killed can stop what it left behind; written atomically,
        0600, in the private state directory. ``stopping``: this manager stops them (a clean stop):
        their end is not a fault. The lost instances not yet counted stay named, unmarked. Returns
        whether it was written."""
        def record(name, child, ending=False):
            return dict(trust.describe(child.proc), service=name, spare=child.spare, ready=child.ready,
                        tree=child.handle, slot=child.slot.path if child.slot else None, instance=child.instance,
                        boot=self.boot, **({'stopping': True} if stopping or ending else {}))
        try:
            records = {n: record(n, c) for n, c in self.children.items() if c.alive()}
            records.update(('%s (spare)' % n, record(n, c)) for n, c in self.spares.items() if c.alive())
            # An operator's stop under way: marked, so that a manager started meanwhile ends it rather
            # than adopting it, and does not count its end (the stop was undone; review of session 40).
            records.update(('%s (stopping)' % n, record(n, c, ending=True)) for n, c in
                           getattr(self, 'stopping', {}).items() if c.alive())
            # A lost instance stays named until the record counts it: a manager dying in its set-up
            # meanwhile leaves it for the next one to count (it was forgotten; Limits of session 39).
            # Under a key of its own: under the service's, the service restarted meanwhile (a record
            # write failed, the loss still unacted) hid it, and it was counted nowhere (session 41).
            records.update(('%s (lost)' % n, e) for n, e in self.unacted.items())
            self.own[self.pid_file] = trust.write_private_json(self.pid_file, records)
            return True
        except (OSError, psutil.Error) as e:
            rospy.logwarn_throttle(10.0, '%s: cannot record the services\' pids in %s: %s'
                                   % (rospy.get_name(), self.pid_file, e))
            return False

    def _adopt(self, name, entry, proc, now):
        """Take over a service instance an earlier manager of this name left running (it was killed
        or crashed): its process, tree and beat slot, without restarting it. True if adopted."""
        service = self.supervisor.services.get(entry.get('service'))
        handle, slot_file = entry.get('tree'), entry.get('slot')
        if service is None or not handle or not self.tree.owns(handle, proc.pid):
            return False
        spare = bool(entry.get('spare'))
        if entry['service'] in (self.spares if spare else self.children):
            return False
        slot = channel.BeatSlot(slot_file) if slot_file else None
        child = Child(AdoptedProcess(proc.pid), service.config['cpu_window'], slot, spare,
                      int(entry.get('instance') or 0), self.tree, handle)
        self.own_trees.append(handle)
        child.proc = proc
        child.ready = bool(entry.get('ready'))
        child.beats = slot.read()[0] if slot and slot.read() else 0
        self.instances = max(self.instances, child.instance)
        if spare:
            self.spares[entry['service']] = child
        else:
            self.children[entry['service']] = child
            service.spawned(now)
            self._event('adopted', entry['service'], 'pid %d, left running by an earlier manager' % proc.pid, now,
                        pid=proc.pid)
        rospy.logwarn('%s: adopted %s (pid %d), left running by an earlier manager', rospy.get_name(), name, proc.pid)
        return True

    def _kill_orphans(self):
        """Adopt the service instances an earlier manager of the same name left running (it was
        killed), each only if it is still the process recorded (pid and start time) and still in the
        recorded tree; kill any other it left (process group checked by pid, start time and command
        line). Returns the trees adopted. An active instance found ended (its pid gone, or another
        process's now) is put in self.lost, to be counted as an exit (_found_ended)."""
        adopted = []
        # The predecessor's pid file is this manager's own from now on (as its record is, _restore): a
        # clean stop before this manager first wrote it marks the instances it adopted as stopping,
        # and keeps the losses found. Left unmarked, the next manager counted every adopted instance
        # this stop ended as a fault (review of session 40).
        self.own[self.pid_file] = trust.identity(self.pid_file)
        try:
            recorded = trust.read_private_json(self.pid_file)
        except (OSError, ValueError) as e:
            rospy.logwarn('%s: the pid file %s is not trusted, nothing in it is signalled: %s', rospy.get_name(),
                          self.pid_file, e)
            return adopted
        now = time.monotonic()
        for name, entry in (recorded or {}).items() if isinstance(recorded, dict) else ():
            try:
                proc = psutil.Process(int(entry['pid']))
                started = trust.same_process(entry, proc, command_line=False)
                # One a clean stop was ending (its manager killed meanwhile) is not adopted: it goes. So
                # does one whose fault the record counted (lost_counted) and whose kill did not happen.
                counted = trust.well_formed(entry) and _lost_identity(entry) in self.already_counted
                if not started and not entry.get('stopping') and not counted and self._adopt(name, entry, proc, now):
                    adopted.append(entry['tree'])
                    continue
                if started:   # another process under its pid now: the recorded one ended
                    self._found_ended(entry, 'pid %s is another process now (%s)' % (entry.get('pid'), started))
                why = started or trust.same_process(entry, proc) or (
                    None if os.getpgid(proc.pid) == proc.pid else 'pid %d leads no process group' % proc.pid)
            except psutil.NoSuchProcess:
                self._found_ended(entry, 'pid %s is gone' % entry.get('pid'))
                continue   # nothing to stop
            except (psutil.Error, OSError, KeyError, TypeError, ValueError, AttributeError, ArithmeticError):
                continue   # gone, or a malformed number (Infinity: int() overflows): nothing to stop
            if why:
                rospy.logwarn('%s: %s left by an earlier manager is not signalled: %s', rospy.get_name(), name, why)
                continue
            rospy.logwarn('%s: killing %s (pid %d), left running by an earlier manager', rospy.get_name(), name,
                          proc.pid)
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except OSError:
                pass
        return adopted

    def _found_ended(self, entry, how):
        """An active instance an earlier manager recorded ended while no manager watched it (with its
        manager, or in between): a fault of the service, counted as an exit at the start (self.lost).
        Before session 39 it was started again as if nothing had happened, its restart allowance and
        back-off untouched. Not a spare (never the service's work), nor one recorded under another
        boot of the machine, or none (the machine stopped, not the service)."""
        if not trust.well_formed(entry) or entry.get('spare') or entry.get('stopping') or not self.boot or \
                entry.get('boot') != self.boot:
            return   # (a malformed entry: nothing is known of it, not even that it ended)
        service = entry.get('service')
        if isinstance(service, str) and service in self.supervisor.services:
            if _lost_identity(entry) in self.already_counted:
                # The previous manager counted it, and died in its set-up before the pid file forgot it.
                rospy.logwarn('%s: %s (pid %s) ended while no manager watched it: already counted by the previous '
                              'manager', rospy.get_name(), service, entry.get('pid'))
                return
            self.lost[service] = ('%s: it ended while no manager watched it (with the manager, or while none ran; '
                                  'exit status unknown)' % how)
            self.unacted[service] = entry   # named in every pid file written from now on, until counted

    def _kill(self, name):
        """Kill name's active process (and its spare too if the service is not to run)."""
        self._kill_from(self.children, name)
        if self.supervisor[name].state in (State.STOPPED, State.FAILED):
            self._kill_from(self.spares, name)   # no spare is kept for a service that does not run

    def _kill_from(self, processes, name):
        child = processes.pop(name, None)
        if child is not None:
            # Its members read before the kill: read after, a worker (the process that sends its heartbeats,
            # under a launcher) was gone, and its last heartbeats were refused as forged, a lasting WARN
            # (review of session 48). The operator's stop reads them first too.
            self._replaced(name, child)
            child.kill(self.config['manager']['kill_timeout'], wait=False)   # then: its replacement waits on it
            threading.Thread(target=child.end, args=(self.config['manager']['kill_timeout'],), daemon=True,
                             name='end_%s' % name).start()
            self._record_pids()

    def _replaced(self, name, child):
        """Remember the pids of a child the manager stops: their last heartbeats are stale, not forged."""
        try:
            pids = [child.pid] + (child.tree.members(child.handle) if child.tree is not None and child.handle
                                  else [p.pid for p in child.proc.children(recursive=True)])
        except psutil.Error:
            pids = [child.pid]
        self.replaced[name] = (self.replaced.get(name, []) + pids)[-64:]

    def _stale(self, name, pid, child):
        """Whether a beat from pid is the last words of an instance of name the manager replaced. A
        process of the current instance (child) is never stale, whatever replaced says: replaced keeps
        64 pids per service and pid_max may be 32768, and a new instance given a recycled pid had its
        every ROS heartbeat dropped until its start timed out (review of session 34)."""
        if pid is None or pid not in self.replaced.get(name, ()):
            return False
        return child is None or not child.owns(pid)

    def _reused(self, pid):
        """A spawned instance (re)uses pid: it names no replaced process any more, of any service."""
        for pids in self.replaced.values():
            while pid in pids:
                pids.remove(pid)

    def _published_by(self, header, pid):
        """Whether process pid published on the heartbeat subscription's connection whose header this
        is: it holds that very connection's other end (its local address is the publisher's end, its
        remote address this end), on this host (None: no such connection)."""
        ends = publisher_endpoints(self.heartbeat_topic, header)
        if ends is None:
            return None
        mine, theirs = ends
        try:
            return any(c.laddr and c.raddr and tuple(c.laddr[:2]) == tuple(theirs) and tuple(c.raddr[:2]) == tuple(mine)
                       for c in psutil.Process(pid).connections('tcp'))
        except psutil.Error:
            return False

    def _run_program(self, name, kind):
        cfg = self.supervisor[name].config
        if self.closing:   # (the shutdown ended the programs already: one started now would run unwatched)
            rospy.logerr('%s: the failure program of %s is not run: the manager is shutting down', rospy.get_name(),
                         name)
            return
        env = dict(os.environ, AFT_SERVICE=name, AFT_FAULT=kind)
        now = time.monotonic()
        self._programs_said(self.programs.start(name, kind, cfg['program'], env, now, cfg['program_timeout']), now)

    def _programs_said(self, outcomes, now):
        """Report what the failure programs did: a failure (exit non-zero, killed past its timeout, could
        not start) is an error and an event ``program_failed``; a normal end is logged."""
        for outcome in ([outcomes] if isinstance(outcomes, programs.Outcome) else outcomes or []):
            if outcome.failed:
                rospy.logerr('%s: %s', rospy.get_name(), outcome.detail)
                self._event('program_failed', outcome.service, outcome.detail, now, kind=outcome.fault)
            else:
                rospy.loginfo('%s: %s', rospy.get_name(), outcome.detail)

    def _act(self, decision, now):
        """Carry a fault's decision out: counted in the record first, then acted on. The actions write
        the pid file (the ended instance gone, a new one named); a manager killed between those writes
        and the record's left the fault counted nowhere and an escalation's safe state unsaid (review of
        session 40). The ended instance is named in the record's ``lost_counted`` until the pid file
        no longer names it, so that the next manager does not count it again either."""
        ended = self._ended_identity(decision.service, ('kill', decision.service) in decision.actions)
        if ended is not None:
            self.counted.add(ended)
        self._sync_safe_state()
        for verb, name in decision.actions:
            self._act_one(verb, name, decision, now)
        if ended is not None and ended in self.counted and self._record_pids():
            self.counted.discard(ended)
        self._sync_safe_state()

    def _ended_identity(self, name, killed=False):
        """(service, pid, start) of name's active instance if it ended, or is to be killed (``killed``)
        for the fault being acted on; else None. One to be killed (a hang, a limit) and still named when
        the manager dies is ended by the next manager, not adopted and counted again."""
        child = self.children.get(name)
        if child is None or child.start is None or (child.alive() and not killed):
            return None
        return _lost_identity({'service': name, 'pid': child.popen.pid, 'create_time': child.start})

    def _act_one(self, verb, name, decision, now):
        try:
            if verb == 'kill':
                self._kill(name)
            elif verb == 'spawn':
                if not self.supervisor.may_spawn(name, now):   # after what it is restarted with (held)
                    rospy.loginfo('%s: %s held: %s', rospy.get_name(), name, self.supervisor[name].reason)
                    return
                self._spawn(name, now)
            elif verb == 'run':
                self._run_program(name, decision.kind)
            elif verb == 'alert':
                rospy.logerr('%s: ALERT %s: %s: %s', rospy.get_name(), name, decision.kind, decision.detail)
        except Exception as e:   # one failed action must not leave the others undone
            rospy.logerr('%s: %s %s failed: %s: %s', rospy.get_name(), verb, name, type(e).__name__, e)
            if verb == 'spawn' and self.supervisor[name].state in (State.RESTARTING, State.STARTING):
                self._spawn_failed(self.supervisor.spawn_failed(name, now, str(e)), now)

    def _sync_safe_state(self):
        """Publish the safe state whenever the supervisor's has changed (whatever changed it), and keep
        the record a manager started again reads (:meth:`_restore`). Returns whether the record on disk
        is the current one."""
        if self.supervisor.safe_state != self.published_safe:
            self.published_safe = self.supervisor.safe_state
            self.published_also = 0
            self._publish_safe_state()
        also = self.supervisor.also_unsafe
        if len(also) > self.published_also:   # in the safe state already: said, never swallowed
            for reason in also[self.published_also:]:
                rospy.logerr('%s: SAFE STATE, also: %s', rospy.get_name(), reason)
            self.published_also = len(also)
            self._publish_diagnostics()
        record = self._record_now()
        if record != self.recorded:
            try:
                self.own[self.record_file] = trust.write_private_json(self.record_file, record)
                self.recorded = record
            except OSError as e:
                rospy.logerr_throttle(10.0, '%s: cannot keep the safe state and the services down in %s: %s; '
                                      'a manager started again would not know them' % (rospy.get_name(),
                                                                                      self.record_file, e))
                return False
        return True

    def _record_now(self):
        """The record: the supervisor's, and the lost instances counted in it while the pid file may
        still name them (``lost_counted``)."""
        record = self.supervisor.record()
        if self.counted:
            record['lost_counted'] = sorted([list(c) for c in self.counted])
        return record

    def _restore(self):
        """Read what an earlier manager of this name recorded, if it did not stop cleanly (killed,
        crashed, a power loss) or stopped holding something: its safe state holds (an operator clears it), and the services it left
        down stay down (an operator starts them). Returns those names."""
        self.own[self.record_file] = trust.identity(self.record_file)   # its predecessor's: now its own
        try:
            record = trust.read_private_json(self.record_file)
            held = self.supervisor.restore(record, time.monotonic()) if record is not None else []
        except (OSError, ValueError, ServiceConfigError) as e:
            # Not trusted or not readable: the safe state, rather than a start as if nothing had happened.
            rospy.logerr('%s: the record of the previous run %s is not usable: %s', rospy.get_name(),
                         self.record_file, e)
            self.supervisor._escalate('the record of the manager\'s previous run is not usable (%s): an operator '
                                      'checks the services and clears the safe state' % e, time.monotonic())
            return []
        self.recorded = record
        self.already_counted = _counted_lost(record)
        self.counted = set(self.already_counted)   # said again until the pid file no longer names them
        for name in held:
            rospy.logwarn('%s: %s stays down: %s', rospy.get_name(), name, self.supervisor[name].reason)
        return held

    # -- the loop --------------------------------------------------------------------------------
    def _loop(self):
        """Event-driven, as s6 and systemd supervise: the loop sleeps until something happens or a
        deadline falls due, and beats do not wake it. It wakes when a process ends (its pidfd), a
        service says something on the local channel (first beat, an error, a spare ready), a command
        or a ROS heartbeat comes (the wake pipe), or the earliest deadline falls due: a heartbeat
        timeout (the last beat plus the timeout, read from the slot then), a start timeout, a
        resource sample, a held restart, the diagnostics. Deadlines fall on the manager's period."""
        next_resources = next_diagnostics = 0.0
        meant = None   # when the loop meant to wake (a stall of its own shows as a late wake)
        while not rospy.is_shutdown():
            now = time.monotonic()
            resources = now >= next_resources
            if resources:
                next_resources = now + self.resource_period
            cpu = time.thread_time()
            try:
                with self.lock:
                    self._notice_stall(meant)
                    fds, deadline = self._cycle(now, resources, next_resources, next_diagnostics)
                self.cycle_cpu += time.thread_time() - cpu
                if now >= next_diagnostics:
                    next_diagnostics = now + 1.0
                    cpu = time.thread_time()
                    self._publish_diagnostics()
                    self.tree.sweep()
                    self.diagnostics_cpu += time.thread_time() - cpu
            except Exception as e:   # the loop must outlive anything (and shutdown closes what it uses)
                if rospy.is_shutdown():
                    return
                rospy.logerr('%s: supervision cycle: %s: %s', rospy.get_name(), type(e).__name__, e)
                fds, deadline = [self.wake_r], now + self.period
            # on the period's grid, and at most one timed check per period (an alerted fault's
            # deadline stays in the past)
            period = self.period
            wake = meant = max(math.ceil(deadline / period) * period + 1e-4, now + period)
            poller = select.poll()
            for fd in fds:
                poller.register(fd, select.POLLIN)
            try:
                events = poller.poll(max(0.0, (wake - time.monotonic()) * 1e3))
            except InterruptedError:
                events = []
            if any(fd == self.wake_r for fd, _ in events):
                try:
                    os.read(self.wake_r, 4096)
                except BlockingIOError:
                    pass

    def _notice_stall(self, meant):
        """A wake of the loop far later than it meant is a stall of the manager's own (SIGSTOP, swapped
        out, its lock held): the services beating on the ROS channel get one heartbeat timeout before
        they are judged silent (Supervisor.woke), and it is logged once. Their beats of the stall waited
        in the sockets, and the checks ran before rospy handled them: restarted, each restart counted,
        possibly the safe state (review of session 34). Timed after the lock: a command holding it
        held the beats too."""
        late = self.supervisor.woke(time.monotonic(), meant)
        if late is not None:
            rospy.logwarn('%s: the manager stalled: its loop woke %.3f s late (stopped, swapped out or starved; '
                          '%d stalls so far); the services beating on the ROS channel get one heartbeat timeout '
                          'from now before they are judged silent', rospy.get_name(), late, self.supervisor.stalls)

    def _cycle(self, now, resources, next_resources, next_diagnostics):
        """One wake of the loop: beats, what the channel said, held restarts, every check; returns
        the descriptors to wait on and the next deadline."""
        self.wakes += 1
        self._read_beats()
        self._read_channel(now)
        for verb, name in self.supervisor.due(now):
            self._act_one(verb, name, None, now)
        for name in list(self.supervisor.services):
            self._check(name, now, resources and self._sampled(name))
        self._replace_unready_spares(now)
        if self.programs is not None and self.programs.running:
            self._programs_said(self.programs.check(now), now)
        for name in list(self.spare_retry):
            if now >= self.spare_retry[name]:
                del self.spare_retry[name]
                self._ensure_spare(name)
        self._sync_safe_state()
        # (a process whose end is seen already is not polled again: its pidfd stays readable)
        fds = [self.wake_r, self.local.fileno()] + [
            c.pidfd for c in list(self.children.values()) + list(self.spares.values())
            if c.pidfd is not None and c.popen.returncode is None] + [
            c.watchdog.fd for c in self.children.values() if c.watchdog is not None]
        return fds, min(self._deadlines(next_resources, next_diagnostics))

    def _sampled(self, name):
        """Whether name's process is measured (CPU, memory, stopped): with limits, or with no
        heartbeat to show a hang."""
        c = self.supervisor[name].config
        return c['cpu_limit'] is not None or c['memory_limit'] is not None or c['heartbeat_timeout'] is None

    def _deadlines(self, next_resources, next_diagnostics):
        yield next_diagnostics
        if self.programs is not None and self.programs.running:
            # (a failure program's end is seen within a second; its timeout on time)
            yield min(self.programs.next_deadline() or float('inf'), time.monotonic() + 1.0)
        if any(self._sampled(n) for n in self.children):
            yield next_resources
        due = self.supervisor.next_due()
        if due is not None:
            yield due
        for t in self.spare_retry.values():
            yield t
        for name, spare in self.spares.items():
            if not spare.ready:
                yield spare.born + self.supervisor[name].config['start_timeout']
        for name in self.children:
            s = self.supervisor[name]
            c = s.config
            if s.state == State.STARTING:
                yield s.start_deadline() if c['heartbeat_timeout'] is not None else s.started_at + c['start_grace']
                if self.children[name].slot is not None and self.children[name].beats:
                    yield time.monotonic() + 0.01   # adopted, beating already: its next beat shows it running
            elif s.state == State.RUNNING and c['heartbeat_timeout'] is not None and s.last_heard is not None \
                    and not self._watched_by_kernel(self.children[name]) and 'heartbeat_timeout' not in s.alerted:
                # (a silence alerted already, on_failure alert, is not due again: its deadline stayed in the
                # past and woke the loop every period while it lasted; its end is seen at the next tick)
                yield s.last_heard + c['heartbeat_timeout']

    @staticmethod
    def _watched_by_kernel(child):
        """A service beating in its slot re-arms its watchdog, and the kernel wakes the loop when it
        fires; unless it never armed it (it did not inherit the descriptor): then the manager keeps
        the heartbeat deadline itself, or a hang waited for the next diagnostics tick (1 s)."""
        return child.watchdog is not None and child.beats and child.watchdog.armed()

    def _check(self, name, now, resources):
        child = self.children.get(name)
        if child is None:
            return
        try:
            was = self.supervisor[name].state
            decision = self.supervisor.check(name, child.sample(resources), now, self.total_memory)
            if was == State.STARTING and self.supervisor[name].state == State.RUNNING:
                child.cpu_marks = []   # its CPU is judged from now on, not its start-up
            if decision is not None:
                self._fault(decision, now, time.monotonic())
        except Exception as e:   # the manager must outlive any one service's trouble
            rospy.logerr('%s: while checking %s: %s: %s', rospy.get_name(), name, type(e).__name__, e)

    def _read_beats(self):
        """The beats in the slots of the active instances (one memory read each)."""
        for name, child in list(self.children.items()):
            if child.watchdog is not None:
                child.watchdog.fired()   # (cleared: the check below judges the beat's age)
            seen = child.read_beat()
            if seen is None:
                continue
            self._heard(name, child, seen[0], seen[1], 'reported in its beat' if seen[1] == 'error' else '')
        for name, spare in list(self.spares.items()):
            if not spare.alive():
                self._spare_died(name, spare)

    def _read_channel(self, now):
        """What the services said on the local channel, each checked against the sender's pid."""
        for pid, text in self.local.receive():
            said = channel.parse(text)
            name = said[1] if said else None
            if name not in self.supervisor.services:
                self.unknown_heartbeats += 1
                rospy.logwarn_throttle(5.0, '%s: local channel: %r from pid %s names no service' % (
                    rospy.get_name(), text[:80], pid))
                continue
            verb, detail = said[0], said[2]
            child, spare = self.children.get(name), self.spares.get(name)
            if spare is not None and pid is not None and spare.owns(pid):
                if verb == 'ready' and not spare.ready:
                    spare.ready = True
                    self._record_pids()   # a manager that adopts it knows it may promote it
                    self._event('spare_ready', name, 'pid %d' % spare.pid, now, pid=spare.pid)
                continue
            if self._stale(name, pid, child):
                self.stale_heartbeats += 1   # the last words of an instance the manager replaced
                continue
            if child is None or pid is None or not child.owns(pid):
                self.refused_heartbeats += 1
                rospy.logwarn_throttle(5.0, '%s: local channel: %r from pid %s, not a process of %s: refused (%d so far)'
                                       % (rospy.get_name(), text[:80], pid, name, self.refused_heartbeats))
                continue
            if verb == 'error':
                self._heard(name, child, now, 'error', detail)
            elif verb in ('started', 'ok'):
                seen = child.read_beat()
                if seen is not None:
                    self._heard(name, child, seen[0], seen[1], '')

    def _heard(self, name, child, at, status, detail, stamped_here=False):
        self.heartbeats += 1
        service = self.supervisor[name]
        was = service.state
        service.heard(at, status, detail, stamped_here)
        if was == State.STARTING and service.state == State.RUNNING:
            child.cpu_marks = []
            self._event('running', name, 'heard from', time.monotonic(), started_at=service.started_at)

    def _spare_died(self, name, spare):
        self.spares.pop(name, None)
        code = spare.popen.poll()
        spare.close()
        self.supervisor[name].errors['spare_exit'] += 1
        self.spare_retry[name] = time.monotonic() + 1.0
        self._event('spare_exit', name, 'the warm spare (pid %d) exited with status %s; another in 1 s'
                    % (spare.pid, code), time.monotonic())
        rospy.logwarn_throttle(10.0, '%s: the warm spare of %s exited with status %s (%d so far): another in 1 s; '
                               'restarts meanwhile are cold' % (rospy.get_name(), name, code,
                                                                self.supervisor[name].errors['spare_exit']))
        self._record_pids()

    def _wake(self):
        try:
            os.write(self.wake_w, b'x')
        except (BlockingIOError, OSError):
            pass   # a wake is pending already

    def _on_heartbeat(self, beat):
        now = time.monotonic()
        with self.lock:
            if beat.name not in self.supervisor.services:
                self.unknown_heartbeats += 1
                rospy.logwarn_throttle(5.0, '%s: heartbeat from %r, which is not a configured service (%d so far)'
                                       % (rospy.get_name(), beat.name, self.unknown_heartbeats))
                return
            child = self.children.get(beat.name)
            if child is None or self._stale(beat.name, beat.pid, child):
                self.stale_heartbeats += 1     # a replaced (or stopped) process's last words
                return
            header = getattr(beat, '_connection_header', None) or {}
            why = self.origins.judge(header, beat.pid, child.owns)
            if why:
                self.refused_heartbeats += 1
                rospy.logwarn_throttle(5.0, '%s: heartbeat for %s refused (%d so far): %s'
                                       % (rospy.get_name(), beat.name, self.refused_heartbeats, why))
                return
            was = self.supervisor[beat.name].state
            self._heard(beat.name, child, now, beat.status, beat.detail, stamped_here=True)
            if beat.status == 'error' or was != self.supervisor[beat.name].state:
                self._wake()   # decided on now, not at the next deadline

    # -- reporting -------------------------------------------------------------------------------
    def _event(self, event, name, detail, now, **extra):
        record = dict(extra, event=event, service=name, detail=detail, wall=time.time(), monotonic=now)
        self.events_pub.publish(String(data=json.dumps(record, default=str)))

    def _publish_safe_state(self):
        reason = self.supervisor.safe_state
        if reason:
            rospy.logerr('%s: SAFE STATE: %s', rospy.get_name(), reason)
        self.safe_pub.publish(SafeState(active=reason is not None, reason=reason or '', stamp=rospy.Time.now()))
        self._publish_diagnostics()

    def status(self, name=None):
        with self.lock:
            out = {}
            for n, s in self.supervisor.services.items():
                if name and n != name:
                    continue
                child = self.children.get(n)
                spare = self.spares.get(n)
                out[n] = {'state': s.state.name.lower(), 'reason': s.reason, 'pid': child.pid if child else None,
                          'warm_spare': None if spare is None else {'pid': spare.pid, 'ready': spare.ready},
                          'channel': s.config['heartbeat_channel'], 'consecutive_faults': s.consecutive,
                          'restart_held_s': None if s.spawn_at is None else round(s.spawn_at - time.monotonic(), 3),
                          'starts': s.starts, 'restarts_in_window': s.restarts_in_window(time.monotonic()),
                          'errors': dict(s.errors), 'critical': s.config['critical'],
                          'alerted': sorted(s.alerted),
                          'period': s.config['period'], 'spare': s.config['spare']}
            return {'services': out, 'safe_state': self.supervisor.safe_state,
                    'also_unsafe': list(self.supervisor.also_unsafe), 'down_after_fault': self.supervisor.degraded(),
                    'refused_heartbeats': self.refused_heartbeats, 'stale_heartbeats': self.stale_heartbeats,
                    'stalls': self.supervisor.stalls, 'wakes': self.wakes, 'tree': self.tree.describe(),
                    'cycle_cpu_s': round(self.cycle_cpu, 6), 'diagnostics_cpu_s': round(self.diagnostics_cpu, 6)}

    def _publish_diagnostics(self):
        status = self.status()
        array = DiagnosticArray()
        array.header.stamp = rospy.Time.now()
        for name, s in status['services'].items():
            state = State[s['state'].upper()]
            array.status.append(DiagnosticStatus(
                # a fault alerted and still there (on_failure: alert) is no normal run
                level=DiagnosticStatus.WARN if state == State.RUNNING and s['alerted'] else LEVELS[state],
                name='service_manager: %s' % name, message='%s: %s' % (s['state'], s['reason']),
                hardware_id=str(s['pid'] or ''),
                values=[KeyValue(key='starts', value=str(s['starts'])),
                        KeyValue(key='restarts_in_window', value=str(s['restarts_in_window'])),
                        KeyValue(key='critical', value=str(s['critical']).lower())] +
                [KeyValue(key='errors.%s' % k, value=str(v)) for k, v in sorted(s['errors'].items())]))
        safe, down = status['safe_state'], status['down_after_fault']
        level = DiagnosticStatus.ERROR if safe else DiagnosticStatus.WARN if self.refused_heartbeats or down else \
            DiagnosticStatus.OK
        said = []
        if down:
            said.append('down after a fault: %s' % '; '.join('%s (%s)' % item for item in sorted(down.items())))
        if self.refused_heartbeats:
            said.append('%d heartbeat(s) refused: not from the service\'s own processes' % self.refused_heartbeats)
        message = 'SAFE STATE: %s' % '; also: '.join([safe] + status['also_unsafe']) if safe else \
            ('; '.join(said) or 'normal')
        array.status.append(DiagnosticStatus(level=level, name='service_manager', message=message,
                                             values=[KeyValue(key='heartbeats', value=str(self.heartbeats)),
                                                     KeyValue(key='refused_heartbeats',
                                                              value=str(self.refused_heartbeats))]))
        self.diag_pub.publish(array)

    # -- operators -------------------------------------------------------------------------------
    def _on_command(self, verb, req):
        if verb == 'status':
            if req.name and req.name not in self.supervisor.services:
                return ServiceCommandResponse(success=False, message='unknown service %r (services: %s)'
                                              % (req.name, ', '.join(self.supervisor.services)))
            return ServiceCommandResponse(success=True, message='', status=json.dumps(self.status(req.name or None)))
        if req.name not in self.supervisor.services:
            return ServiceCommandResponse(success=False, message='unknown service %r (services: %s)'
                                          % (req.name, ', '.join(self.supervisor.services)))
        now = time.monotonic()
        with self.lock:
            stopping = self.stopping.get(req.name)
            if verb in ('start', 'restart') and stopping is not None and stopping.alive():
                return ServiceCommandResponse(success=False, message='%s is still stopping: try again' % req.name,
                                              status=json.dumps(self.status(req.name)))
            ok, actions, message = getattr(self.supervisor, verb)(req.name, now)
            for action, name in actions:
                if action == 'kill' and verb == 'stop':
                    # An operator's stop asks first (SIGTERM), off the manager's loop.
                    child = self.children.pop(name, None)
                    if child is not None:
                        self._replaced(name, child)
                        self.stopping[name] = child
                        self._record_pids()   # marked stopping before it is signalled
                        threading.Thread(target=child.terminate, args=(self.config['manager']['kill_timeout'],),
                                         daemon=True).start()
                    self._kill_from(self.spares, name)   # a service that does not run keeps no spare
                elif action == 'kill':
                    self._kill(name)
                elif action == 'spawn':
                    # held like a restart of the manager's own: never before a service it is restarted with
                    # that is held (its back-off), else it ran without it and was not restarted after it
                    # (review of session 48); due() spawns it in its turn
                    if self.supervisor.may_spawn(name, now):
                        self._spawn(name, now)
                    else:
                        message = '%s; %s held: %s' % (message, name, self.supervisor[name].reason)
            self._event('command', req.name, message, now, verb=verb, accepted=ok)
            self._sync_safe_state()
        self._wake()   # the loop watches the processes as they are now
        return ServiceCommandResponse(success=ok, message=message, status=json.dumps(self.status(req.name)))

    def _on_clear(self, _req):
        with self.lock:
            ok, message = self.supervisor.clear_safe_state(time.monotonic())
            self._sync_safe_state()
        rospy.logwarn('%s: clear safe state: %s', rospy.get_name(), message)
        return TriggerResponse(success=ok, message=message)

    def _stop_left_by_shutdown(self):
        """Kill the services a spawn added after the shutdown took its list (the shutdown ran in the signal
        handler of the thread that was spawning them). Never raises."""
        with self.lock:
            left = list(self.children.values()) + list(self.spares.values())
            self.children, self.spares = {}, {}
        for child in left:
            try:
                child.kill(self.config['manager']['kill_timeout'])
                child.close()
            except Exception as e:
                rospy.logerr('%s: stopping pid %d: %s: %s', rospy.get_name(), child.pid, type(e).__name__, e)

    def shutdown(self):
        """Stop every service, those being stopped too, and their spares: SIGTERM to all, then SIGKILL
        to those still running after kill_timeout. Never raises."""
        with self.lock:
            self.closing = True   # nothing is spawned from now on
            # Killed in the middle of this stop (roslaunch's SIGKILL after its SIGTERM), the pid file
            # would name instances this stop ended: the next manager must not count them as faults.
            try:
                own = self.own.get(self.pid_file)
                if own is not None and trust.identity(self.pid_file) == own:   # never a successor's (session 34)
                    self._record_pids(stopping=True)
            except Exception as e:   # shutdown paths never raise
                rospy.logerr('%s: the pid file could not be marked stopping: %s', rospy.get_name(), e)
            spares = list(self.spares.values())
            children = list(self.children.values()) + list(self.stopping.values())
            self.children, self.stopping, self.spares = {}, {}, {}
            ended = self.programs.end_all() if self.programs is not None else 0
        if ended:
            rospy.logwarn('%s: %d failure program(s) still running were killed with the manager', rospy.get_name(),
                          ended)
        try:   # every service stops, the critical ones too: never silently (a client hook may still publish)
            self.safe_pub.publish(SafeState(active=True, reason='the service manager %s stops: every service it '
                                            'ran is stopped' % rospy.get_name(), stamp=rospy.Time.now()))
        except Exception as e:
            rospy.logerr('%s: the safe state could not be commanded at shutdown: %s', rospy.get_name(), e)
        self._wake()
        for spare in spares:   # idle, nothing to save: killed at once
            try:
                spare.kill(0.2)
                spare.close()
            except Exception as e:
                rospy.logerr('%s: stopping spare %d: %s: %s', rospy.get_name(), spare.pid, type(e).__name__, e)
        try:
            for child in children:
                child.signal_session(signal.SIGTERM)
            deadline = time.monotonic() + self.config['manager']['kill_timeout']
            for child in children:
                try:   # each on its own: one child's trouble leaves none of the others running
                    try:
                        child.popen.wait(max(0.0, deadline - time.monotonic()))
                    except subprocess.TimeoutExpired:
                        child.kill(0.2)
                    child._kill_tree(0.5)   # what it started in sessions of its own goes too
                    child.close()
                except Exception as e:
                    rospy.logerr('%s: stopping pid %d: %s: %s', rospy.get_name(), child.pid, type(e).__name__, e)
            for handle in self.tree.leftovers():   # anything of this manager's a race let through
                if handle in self.own_trees:       # (and nothing of another's: review of session 34)
                    self.tree.kill(handle, 0.5)
            if self.local is not None:
                self.local.close()
            self.tree.close(0.3)
        except Exception:   # shutdown paths never raise
            pass
        # A clean stop stopped everything, so the pid file goes. The record goes too unless it holds
        # something: a safe state, or services left down. A manager started again then starts afresh.
        # Removing a held record lifted the safe state at the next start (review of session 34).
        # A killed or crashed manager leaves both, and the next one adopts its services. A file is
        # removed or written only if it is still the one this manager wrote (review of session 34).
        own = self.own.get(self.pid_file)
        if self.unacted and own is not None and trust.identity(self.pid_file) == own:
            with self.lock:   # stopped in its set-up: the losses not yet counted stay for the next manager
                self._record_pids()
        else:
            trust.unlink_own(self.pid_file, own)
        self._keep_or_remove_record()

    def _keep_or_remove_record(self):
        """At a clean stop: the record written again with what the supervisor holds (the safe state, the
        services left down), for the next manager of this name, or removed if it holds nothing. Never
        touches a successor's record. Never raises."""
        try:
            with self.lock:
                held = self._record_now()
            own = self.own.get(self.record_file)
            if not held['safe_state'] and not held['down'] and not held['counts'] and not held.get('lost_counted'):
                trust.unlink_own(self.record_file, own)
                return
            if trust.identity(self.record_file) not in (None, own):
                return   # a successor's: left alone
            trust.write_private_json(self.record_file, held)
            rospy.logwarn('%s: stopped cleanly while holding %s: kept in %s for the next start (an operator clears '
                          'it there)', rospy.get_name(), '; '.join(
                              (['the safe state (%s)' % held['safe_state']] if held['safe_state'] else []) +
                              (['%s down' % ', '.join(sorted(held['down']))] if held['down'] else []) +
                              (['the fault counts of %s' % ', '.join(sorted(held['counts']))]
                               if held['counts'] else [])),
                          self.record_file)
        except Exception as e:   # shutdown paths never raise
            rospy.logerr('%s: the record %s could not be kept at the stop: %s', rospy.get_name(), self.record_file, e)
