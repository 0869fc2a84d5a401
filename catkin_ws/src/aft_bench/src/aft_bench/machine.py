"""A description of the machine a benchmark ran on: every figure of a report is stamped with it."""
import os
import platform
import subprocess


def _first(path, prefix, sep=':'):
    try:
        with open(path) as f:
            return next((line.split(sep, 1)[1].strip().strip('"') for line in f if line.startswith(prefix)), None)
    except OSError:
        return None


def _sysctl(name):
    try:
        with open('/proc/sys/' + name.replace('.', '/')) as f:
            return ' '.join(f.read().split())
    except OSError:
        return None


def _ros_versions():
    try:
        done = subprocess.run(['rosversion', 'ros_comm'], capture_output=True, text=True, timeout=10)
        ros_comm = done.stdout.strip() if done.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        ros_comm = None
    try:
        import rospkg
        rospy = rospkg.RosPack().get_manifest('rospy').version
    except Exception as e:   # describe, do not fail, on a machine without rospkg's view of rospy
        rospy = 'unknown (%s)' % e
    # Debian's packages have no ros_comm metapackage: rospy's version stands for it then.
    return ros_comm or 'rospy %s' % rospy, rospy


def describe():
    """A JSON-serialisable dict: CPUs and their model, memory, kernel, Python, ROS, load, TCP buffers."""
    ros_comm, rospy = _ros_versions()
    memory = _first('/proc/meminfo', 'MemTotal')   # '24684092 kB'
    if memory and memory.endswith(' kB') and memory[:-3].isdigit():
        memory = '%.1f GiB' % (int(memory[:-3]) / 1048576.0)
    try:
        load = list(os.getloadavg())
    except OSError:
        load = None
    return {'cpus': os.cpu_count(), 'cpu_model': _first('/proc/cpuinfo', 'model name') or 'unknown',
            'memory': memory or 'unknown', 'system': '%s %s' % (platform.system(), platform.release()),
            'distribution': _first('/etc/os-release', 'PRETTY_NAME=', '=') or platform.platform(),
            'python': platform.python_version(), 'ros_distro': os.environ.get('ROS_DISTRO', 'debian'),
            'ros_comm': ros_comm, 'rospy': rospy, 'host': platform.node(), 'load_average': load,
            'tcp_rmem': _sysctl('net.ipv4.tcp_rmem'), 'tcp_wmem': _sysctl('net.ipv4.tcp_wmem')}


def one_line(machine):
    """The description in one line, for the top of a report."""
    return '%s CPU(s) (%s), %s RAM, %s, Python %s, %s' % (
        machine.get('cpus'), machine.get('cpu_model'), machine.get('memory'), machine.get('system'),
        machine.get('python'), machine.get('ros_comm'))
