"""The files tjp_sim ships (scenarios, adaptation scripts, the FMECA), found through the ROS package
path: the same in the source tree, a devel space or an install space (share/tjp_sim)."""
import os

from .errors import TjpConfigError


def package_dir():
    import rospkg
    try:
        return rospkg.RosPack().get_path('tjp_sim')
    except rospkg.ResourceNotFound:
        raise TjpConfigError('the ROS package tjp_sim is not on ROS_PACKAGE_PATH (%s): source the workspace\'s '
                             'setup.bash' % os.environ.get('ROS_PACKAGE_PATH', 'not set'))


def path(*parts):
    """A file or folder of the package, e.g. path('scenarios', 'steady.yaml')."""
    return os.path.join(package_dir(), *parts)
