from catkin_pkg.python_setup import generate_distutils_setup
from setuptools import setup

setup(**generate_distutils_setup(packages=['aft_examples', 'aft_examples.ros'], package_dir={'': 'src'}))
