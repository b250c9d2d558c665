"""rospy nodes of offload_learner_py, each a main() reached from a two-line script in scripts/."""
