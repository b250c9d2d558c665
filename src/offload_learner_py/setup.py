"""Installs the learner core. Under catkin, catkin_python_setup() reads this; on a laptop without ROS,
`pip install ./src/offload_learner_py` installs the ROS-free core the same way."""
PACKAGES = ["offload_learner_py", "offload_learner_py.core", "offload_learner_py.data", "offload_learner_py.offline",
            "offload_learner_py.online", "offload_learner_py.nodes"]

try:
    from catkin_pkg.python_setup import generate_distutils_setup
    from setuptools import setup

    setup(**generate_distutils_setup(packages=PACKAGES, package_dir={"": "src"},
                                     package_data={"offload_learner_py.data": ["*.npz"]}))
except ImportError:  # no catkin_pkg: plain setuptools install of the core
    from setuptools import setup

    setup(name="offload_learner_py", version="0.1.0", packages=PACKAGES,
          package_dir={"": "src"}, package_data={"offload_learner_py.data": ["*.npz"]})
