"""For catkin_python_setup() only; pip builds the package from pyproject.toml (hatchling), which never
runs this file."""
from catkin_pkg.python_setup import generate_distutils_setup
from setuptools import setup

setup(**generate_distutils_setup(packages=["offload_cloud"], package_dir={"": "src"}))
