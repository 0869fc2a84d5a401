from catkin_pkg.python_setup import generate_distutils_setup
from setuptools import setup

setup(**generate_distutils_setup(packages=['aft_ftm', 'aft_ftm.ros'], package_dir={'': 'src'}))
