"""Launch files read as roslaunch reads them: the nodes a launch starts, which of them are required.

Used by the Adaptation Engine (which nodes a retired node's roslaunch would stop with it) and by the
crash detector (the required nodes of its site, whose death it reports at once: aft_ftm.site_watch).
"""
import os

import psutil
import rosgraph
import rospkg

from ..adaptation import ScriptError


def resolve_launch_file(spec):
    """``package/file.launch`` (found in the package's launch/ folder or anywhere in it) or a path."""
    if os.path.isfile(spec):
        return os.path.abspath(spec)
    package, _, name = spec.partition('/')
    try:
        root = rospkg.RosPack().get_path(package)
    except rospkg.ResourceNotFound:
        raise ScriptError('launch file %s: no such file, and no ROS package %r' % (spec, package))
    for folder, _, files in os.walk(root):
        if name in files:
            return os.path.join(folder, name)
    raise ScriptError('launch file %s: package %s has no file %s' % (spec, package, name))


def launch_nodes(path, args, namespace='/'):
    """The absolute names of the nodes a launch file starts with these arguments (it must load), run by a
    roslaunch in namespace (its ROS_NAMESPACE; not this process's: a node's is its own namespace)."""
    import roslaunch.config
    import roslaunch.xmlloader
    config = roslaunch.config.ROSLaunchConfig()
    loader = roslaunch.xmlloader.XmlLoader()
    loader.ignore_unset_args = False
    try:
        loader.load(path, config, argv=['%s:=%s' % a for a in args] + ['__ns:=' + namespace], verbose=False)
    except Exception as e:   # roslaunch raises several kinds; all mean "this launch cannot start"
        raise ScriptError('launch file %s does not load with %s: %s'
                          % (path, ' '.join('%s:=%s' % a for a in args) or 'no arguments', e))
    return [rosgraph.names.ns_join(n.namespace, n.name) for n in config.nodes], config


def stopped_with(pid, node):
    """The other nodes that stop when node (process pid) dies: those of the roslaunch that started it,
    if it started it with required="true" (roslaunch then shuts the whole launch down); [] where that
    cannot be known (a node started otherwise). See stopped_by_launch."""
    try:
        parent = psutil.Process(pid).parent()
        argv = parent.cmdline() if parent is not None else []
    except (psutil.Error, OSError):
        return []
    return stopped_by_launch(argv, node)


def launch_of(argv, namespace='/'):
    """(node names, loaded configuration) of the launch a roslaunch process run as argv (in namespace)
    starts, read from its launch file and arguments; None if argv is not a roslaunch whose file loads."""
    at = [i for i, a in enumerate(argv[:2]) if os.path.basename(a) == 'roslaunch']
    if not at:
        return None
    rest = argv[at[0] + 1:]
    positional = [a for a in rest if not a.startswith('-') and ':=' not in a]   # a path, or package and file
    args = [tuple(a.split(':=', 1)) for a in rest if ':=' in a and not a.startswith('__')]
    if len(positional) not in (1, 2):
        return None
    try:
        return launch_nodes(resolve_launch_file('/'.join(positional)), args, namespace)
    except ScriptError:
        return None


def required_by_launch(argv, namespace='/'):
    """The nodes a roslaunch run as argv (in namespace) starts with required="true" (the death of one
    shuts the whole launch down); empty if argv is not a roslaunch whose file loads."""
    loaded = launch_of(argv, namespace)
    if loaded is None:
        return set()
    return {rosgraph.names.ns_join(n.namespace, n.name) for n in loaded[1].nodes if n.required}


STAGE_TYPES = ('protocol', 'before', 'proceed', 'after')   # aft_ftm executables an adaptation may replace


def replaceable_by_launch(argv, namespace='/'):
    """The FTM stage nodes (aft_ftm's protocol, before, proceed, after) a roslaunch run as argv starts
    without required="true": in an adaptable site, those an adaptation may retire and replace (a
    nested mechanism's included). Empty if argv is not a roslaunch whose file loads."""
    loaded = launch_of(argv, namespace)
    if loaded is None:
        return set()
    return {rosgraph.names.ns_join(n.namespace, n.name) for n in loaded[1].nodes
            if not n.required and n.package == 'aft_ftm' and n.type in STAGE_TYPES}


def stopped_by_launch(argv, node):
    """The nodes other than node that a roslaunch run as argv stops when node dies (node required
    there), read from its launch file and arguments; [] if argv is not a roslaunch whose file loads."""
    loaded = launch_of(argv)
    if loaded is None:
        return []
    names, config = loaded
    required = {rosgraph.names.ns_join(n.namespace, n.name) for n in config.nodes if n.required}
    return [n for n in names if n != node] if node in required else []
