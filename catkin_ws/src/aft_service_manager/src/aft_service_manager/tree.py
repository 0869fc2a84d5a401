"""Every process of a service, wherever it went (issue 17). A service's process may start others
in sessions of their own (roslaunch starts each node so; a daemon double-forks and calls setsid):
killing the service's process group leaves them running. No rospy.

- :class:`CgroupTree`: where the machine offers a writable cgroup v2 hierarchy (pure, or the
  ``unified`` one of a hybrid set-up), each service instance is started in a cgroup of its own
  (a shell writes its pid into ``cgroup.procs`` and then execs the command, so even its first
  fork is inside). No process can leave a cgroup by itself; a kill writes ``cgroup.kill`` (Linux
  5.14; before, every pid of ``cgroup.procs`` is killed until none is left).
- :class:`TaggedTree`: otherwise, the instance's environment carries a tag (``AFT_SERVICE_TAG``)
  that its descendants inherit whatever session they start; a kill finds them by it (and by
  parenthood), as the tests' leftover check does. A process that clears its environment escapes it:
  that is the limit of this fallback, and why the cgroup is preferred.

:func:`make` picks one; ``describe()`` says which, for ~status and the logs.
"""
import os
import signal
import time
import uuid

import psutil

TAG = 'AFT_SERVICE_TAG'
EXEC_WAIT = 0.2   # s: the longest a process whose environment reads empty is read again (an exec under way)


def _members(procs, tag, bare, wait=EXEC_WAIT, poll=0.002):
    """The pids of procs (psutil.Process) that carry ``tag``. A process in the middle of its exec reads
    with an empty environment (the kernel is replacing its memory): one whose parent carries the tag
    is read again, for at most ``wait`` seconds in all, not taken for untagged (CI, session 44: a
    launcher's child read just after its fork was not the service's; a kill could have left it). Only
    those are waited for: kernel threads, zombies and other processes without an environment are not
    (they would slow every call). One still empty after a whole wait is put in ``bare`` (a set of
    (pid, start time)) and not waited for again: it cleared its environment (this fallback's limit)."""
    found, unsure = [], []
    for proc in procs:
        try:
            env = proc.environ()
            if env:
                if env.get(TAG) == tag:
                    found.append(proc.pid)
                continue
            if (proc.pid, proc.create_time()) in bare or proc.status() == psutil.STATUS_ZOMBIE:
                continue
            if psutil.Process(proc.ppid()).environ().get(TAG) == tag:
                unsure.append(proc)
        except (psutil.Error, OSError):
            continue
    deadline = time.monotonic() + wait
    while unsure and time.monotonic() < deadline:
        time.sleep(poll)
        still = []
        for proc in unsure:
            try:
                env = proc.environ()
            except (psutil.Error, OSError):
                continue
            if not env:
                still.append(proc)
            elif env.get(TAG) == tag:
                found.append(proc.pid)
        unsure = still
    if len(bare) + len(unsure) > 4096:
        bare.clear()
    for proc in unsure:
        try:
            bare.add((proc.pid, proc.create_time()))
        except (psutil.Error, OSError):
            pass
    return sorted(found)


def cgroup2_root(mountinfo='/proc/self/mountinfo'):
    """The mount point of a cgroup v2 hierarchy this process may make cgroups in, or None."""
    try:
        with open(mountinfo) as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    for line in lines:
        fields = line.split(' - ', 1)
        if len(fields) == 2 and fields[1].split()[0] == 'cgroup2':
            mount = fields[0].split()[4]
            if os.access(mount, os.W_OK) and os.path.exists(os.path.join(mount, 'cgroup.procs')):
                return mount
    return None


class CgroupTree(object):
    """One cgroup per instance under ``<root>/aft_service_manager/<owner>``."""
    kind = 'cgroup'

    STALE = 60.0   # s: an empty cgroup this old is litter of a manager that was killed

    def __init__(self, root, owner):
        self.base = os.path.join(root, 'aft_service_manager', owner)
        self._remove_litter(os.path.dirname(self.base))
        os.makedirs(self.base, exist_ok=True)
        self.emptied = set()   # cgroups whose processes are dead but not yet reaped (rmdir: busy)

    def _remove_litter(self, top):
        """Empty cgroups left by managers that were killed (any owner's), once old enough that no
        manager is about to start a process in them."""
        now = time.time()
        try:
            owners = [os.path.join(top, d) for d in os.listdir(top)]
        except OSError:
            return
        for owner in owners:
            try:
                instances = [os.path.join(owner, d) for d in os.listdir(owner)
                             if os.path.isdir(os.path.join(owner, d))]
                for path in instances:
                    if not self.members(path) and now - os.stat(path).st_mtime > self.STALE:
                        os.rmdir(path)
                if now - os.stat(owner).st_mtime > self.STALE:
                    os.rmdir(owner)
            except OSError:
                continue   # busy, or in use: left

    def describe(self):
        return 'cgroup v2 (%s)' % self.base

    def prepare(self, instance):
        """(command prefix, environment additions, handle) for a new instance."""
        path = os.path.join(self.base, instance)
        os.makedirs(path, exist_ok=True)
        return ['/bin/sh', '-c', 'echo $$ > "$0/cgroup.procs" && exec "$@"', path], {}, path

    def members(self, path):
        try:
            with open(os.path.join(path, 'cgroup.procs')) as f:
                return [int(p) for p in f.read().split()]
        except (OSError, ValueError):
            return []

    def owns(self, path, pid):
        try:
            with open('/proc/%d/cgroup' % pid) as f:
                return any(line.startswith('0::') and os.path.join(self._mount(), line[3:].strip().lstrip('/'))
                           == path for line in f.read().splitlines())
        except OSError:
            return False

    def _mount(self):
        return self.base[:self.base.index('/aft_service_manager/')]

    def signal(self, path):
        """SIGKILL every process of the instance now, without waiting for their end (the kernel's
        ``cgroup.kill`` reaches a process forking meanwhile too; without it, passes until no member
        is left, at most 50 ms)."""
        try:
            with open(os.path.join(path, 'cgroup.kill'), 'w') as f:
                f.write('1')
            return
        except OSError:
            pass   # before Linux 5.14, or gone: each member
        _kill_passes(lambda: self.members(path))

    def kill(self, path, timeout=2.0):
        """Kill every process of the instance; True once none is left (then the cgroup is removed)."""
        killer = os.path.join(path, 'cgroup.kill')
        deadline = time.monotonic() + timeout
        while True:   # one pass at least, then until none is left or the time is up
            pids = self.members(path)
            if not pids:
                break
            if os.path.exists(killer):
                try:
                    with open(killer, 'w') as f:
                        f.write('1')
                except OSError:
                    pass
            else:
                for pid in pids:
                    try:
                        os.kill(pid, signal.SIGKILL)
                    except OSError:
                        pass
            if time.monotonic() > deadline:
                break
            time.sleep(0.002)
        left = self.members(path)
        if not left:
            self.emptied.add(path)
            self.sweep()
        return not left

    def sweep(self):
        """Remove the emptied cgroups that can be (a zombie not yet reaped keeps one busy a while)."""
        for path in list(self.emptied):
            try:
                os.rmdir(path)
            except FileNotFoundError:
                pass
            except OSError:
                continue
            self.emptied.discard(path)

    def leftovers(self):
        """The instances an earlier manager of the same owner left (it was killed): their handles."""
        try:
            return sorted(os.path.join(self.base, d) for d in os.listdir(self.base)
                          if os.path.isdir(os.path.join(self.base, d)))
        except OSError:
            return []

    def close(self, timeout=1.0):
        deadline = time.monotonic() + timeout
        self.sweep()
        while self.emptied and time.monotonic() < deadline:
            time.sleep(0.01)
            self.sweep()
        for path in (self.base, os.path.dirname(self.base)):   # the parent too, once no manager uses it
            try:
                os.rmdir(path)
            except OSError:
                pass


class TaggedTree(object):
    """The fallback: a tag in the instance's environment, inherited by its descendants."""
    kind = 'tag'

    def __init__(self, owner):
        self.owner = owner
        self.bare = set()   # (pid, start time) of processes seen without an environment past an exec's wait

    def describe(self):
        return 'environment tag %s (no writable cgroup v2 here)' % TAG

    def prepare(self, instance):
        tag = '%s.%s.%s' % (self.owner, instance, uuid.uuid4().hex[:12])
        return [], {TAG: tag}, tag

    def members(self, tag):
        return _members(psutil.process_iter(), tag, self.bare)

    def owns(self, tag, pid):
        try:
            proc = psutil.Process(pid)
        except (psutil.Error, OSError):
            return False
        return _members([proc], tag, self.bare) == [pid]

    def signal(self, tag):
        _kill_passes(lambda: [p for p in self.members(tag) if p != os.getpid()])

    def kill(self, tag, timeout=2.0):
        deadline = time.monotonic() + timeout
        while True:   # one pass at least
            pids = [p for p in self.members(tag) if p != os.getpid()]
            alive = []
            for pid in pids:
                try:
                    if psutil.Process(pid).status() != psutil.STATUS_ZOMBIE:
                        os.kill(pid, signal.SIGKILL)
                        alive.append(pid)
                except (psutil.Error, OSError):
                    pass
            if not alive:
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)

    def sweep(self):
        pass

    def leftovers(self):
        found = set()
        for proc in psutil.process_iter(['pid']):
            try:
                tag = proc.environ().get(TAG, '')
            except (psutil.Error, OSError):
                continue
            if tag.startswith(self.owner + '.'):
                found.add(tag)
        return sorted(found)

    def close(self, timeout=0.0):
        pass


def _kill_passes(members, limit=0.05):
    """SIGKILL members() until a pass finds none alive that was not signalled already (a process
    forked during a pass is caught by the next), for at most ``limit`` seconds."""
    signalled, deadline = set(), time.monotonic() + limit
    while True:
        fresh = [p for p in members() if p not in signalled]
        for pid in fresh:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        signalled.update(fresh)
        if not fresh or time.monotonic() > deadline:
            return


def make(owner, prefer_cgroup=True):
    """A CgroupTree where a writable cgroup v2 hierarchy is mounted, else a TaggedTree."""
    root = cgroup2_root() if prefer_cgroup else None
    if root is not None:
        try:
            return CgroupTree(root, owner)
        except OSError:
            pass
    return TaggedTree(owner)
