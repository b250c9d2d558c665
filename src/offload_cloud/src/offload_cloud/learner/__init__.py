"""The fleet learner (`offload-cloud-learner`): pools every robot's decision/outcome rows as ROS 1 bags, trains the
DQN from them, gates each new model by off-policy evaluation on each robot's recent rows, and serves
content-addressed model versions. Unlike the rest of offload_cloud it needs the learner's code: torch, rosbags and
offload_learner_py (the `learner` extra of the pip package). The planner server and the client library never
import this subpackage.

Modules by job: `rows.py` (a ROWS batch checked by the bag reader and written as the robot's bytes), `pool.py`
(the experience pool: per-robot bags, rotation, rates and the disk budget), `store.py` (versions, history, pins),
`gate.py` (the publication rule), `training.py` (a training round), `service.py` (the socket loop and the
trainer thread), `cli.py` (the command line)."""
