"""ROS-free learner core of offload: decides per path-planning request whether to plan on the robot
(action 0, local) or in the cloud (action 1), with the DQN of Penmetcha and Min (IEEE Access 9, 2021) and its baselines.

Nothing in this package imports rospy; the ROS nodes live elsewhere and call into it."""

LOCAL = 0
CLOUD = 1
ACTION_NAMES = ("local", "cloud")
