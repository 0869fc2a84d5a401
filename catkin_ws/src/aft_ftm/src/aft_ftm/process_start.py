"""When a process started, on the boot clock: what tells a process from a later one under the same pid,
agreed on by every process that asks, whatever the wall clock does. No ROS.

psutil's ``create_time`` is the boot time (``btime`` of /proc/stat) plus the process's start in clock
ticks. The kernel derives ``btime`` from the wall clock, so it moves when the clock is stepped (NTP at
a robot's start), and psutil reads it once per process: two processes that read it on either side of a
step disagree on the same process's create time. One that compared it with a value another had taken
(a site's incarnation told to the witness, a site launcher named to a guarded launch, a hosts record,
the service manager's pid file) took the same process for another: the only primary deposed, a site's
nodes stopped, a service killed instead of adopted. The start in clock ticks since boot (field 22 of
/proc/PID/stat) moves with no clock."""
import os

CLOCK_TICKS = os.sysconf('SC_CLK_TCK')


def started(pid, zombie=False, proc='/proc'):
    """Seconds from boot to the start of process ``pid`` (a multiple of 1/CLOCK_TICKS); None if there is
    no such process, or it is a zombie (it ran its course) unless ``zombie``."""
    try:
        with open('%s/%d/stat' % (proc, pid), 'rb') as f:
            data = f.read()
    except (FileNotFoundError, ProcessLookupError):
        return None
    fields = data[data.rindex(b')') + 2:].split()   # the command name, in brackets, may hold anything
    if fields[0] == b'Z' and not zombie:
        return None
    return int(fields[19]) / CLOCK_TICKS
