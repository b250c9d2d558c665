"""ROS-free learner core of offload: decides per path-planning request whether to plan on the robot
(action 0, local) or in the cloud (action 1), with the DQN of Penmetcha and Min (IEEE Access 9, 2021) and its baselines.

Only the `nodes` subpackage (the learner, cloud bridge and recorder nodes) imports rospy; everything else
(core, data, online, offline) is a ROS-free library they call into."""

LOCAL = 0
CLOUD = 1
OTHER = {LOCAL: CLOUD, CLOUD: LOCAL}   # the action not taken
ACTION_NAMES = ("local", "cloud")
