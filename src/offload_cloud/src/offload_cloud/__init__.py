"""What a cloud host runs, without ROS: the wire protocol, the robot-side client library, the cloud planner
server (admission, connection guard, queue, auth, keys, map cache, stats, CLI) and its deploy recipes.

The planning itself is the C++ core's (offload_planner_cpp); nothing here imports rospy, and the rospy
bridge node that uses the client library lives in offload_learner_py.nodes."""
