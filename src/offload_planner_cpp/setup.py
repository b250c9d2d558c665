"""Python side of the planner package, read by catkin_python_setup() (the compiled _core module is put
beside it in the devel space by CMake)."""
from catkin_pkg.python_setup import generate_distutils_setup
from setuptools import setup

setup(**generate_distutils_setup(
    packages=["offload_planner_cpp", "offload_planner_cpp.nodes"],
    package_dir={"": "src"}))
