"""The fault matrix's stack (rtest_fault_matrix.py): a ROS master of the test's own, the map published by
the test so a fault can replace it, the planner node, the cloud server behind an in-process WAN emulator,
the bridge, the recorder and the learner, each restartable, and the decisions, outcomes and cloud timings
they publish. Imported before rospy anywhere else: it names the master first."""
import atexit
import os
import subprocess
import sys
import tempfile
import threading
import time
import xml.etree.ElementTree as ElementTree

import numpy as np


from offload_demos.loopback import free_port  # noqa: E402  (ROS-free: before the master is named)

MASTER_PORT = free_port()
os.environ["ROS_MASTER_URI"] = f"http://127.0.0.1:{MASTER_PORT}"
os.environ["ROS_IP"] = "127.0.0.1"
# The master is the test's own (the last fault restarts it), named before rospy reads ROS_MASTER_URI;
# every node the test starts inherits it.
sys.path.insert(0, os.path.dirname(os.path.realpath(__file__)))
from rtest_online_stack import CLOUD_TIMEOUT_S, WaitsForRecords, launch_file, spawn_cloud_server, start_learner_node, \
    stop  # noqa: E402

import rosgraph  # noqa: E402
import rospy  # noqa: E402
from nav_msgs.msg import MapMetaData, OccupancyGrid  # noqa: E402
from offload_msgs.msg import OffloadDecision, OffloadOutcome, PlanTiming  # noqa: E402
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse  # noqa: E402
from rospy.numpy_msg import numpy_msg  # noqa: E402

from offload_planner_cpp import free_cells, plan as plan_cells  # noqa: E402
from offload_planner_cpp._core import check_map  # noqa: E402
from offload_demos.wan_emulator import LinkModel, WanEmulator  # noqa: E402
from offload_planner_cpp.maps import OccupancyMap, load_map  # noqa: E402
from offload_planner_cpp.nodes.map_publisher import to_message  # noqa: E402

START = (-1.0, 0.5)
GOALS = [(1.0, 0.5), (-0.5, -1.5), (0.5, 1.7), (1.8, -0.2), (-1.8, 0.1)]
BORDER_CELLS = 10       # the replacement map is larger (so d_t shows which map the learner had)


def master_up(timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            rosgraph.Master("/rtest_fault_matrix_probe").getPid()
            return True
        except Exception:   # connection refused until it listens
            time.sleep(0.1)
    return False


def start_master() -> subprocess.Popen:
    master = subprocess.Popen(["rosmaster", "--core", "-p", str(MASTER_PORT), "__log:=/dev/null"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    if not master_up(30):
        stop(master)
        raise RuntimeError(f"rosmaster did not come up on port {MASTER_PORT}")
    return master


def replacement_map(original: OccupancyMap, start, goal) -> OccupancyMap:
    """The original with a border of BORDER_CELLS (world coordinates unchanged) and the middle of the
    original path from start to goal walled off, so a path from the old map crosses an obstacle of the
    new one. Checked: the goal stays reachable on the new map."""
    ok, geometry = check_map(original.width, original.height, original.grid.size, original.resolution,
                             original.origin_x, original.origin_y, (0.0, 0.0, 0.0, 1.0))
    assert ok.ok, ok.message
    a, b = geometry.world_to_cell(*start), geometry.world_to_cell(*goal)
    old_path = plan_cells(original.grid, a, b).path
    middle = old_path[len(old_path) // 2]
    grid = np.full((original.height + 2 * BORDER_CELLS, original.width + 2 * BORDER_CELLS), 100, np.int8)
    grid[BORDER_CELLS:-BORDER_CELLS, BORDER_CELLS:-BORDER_CELLS] = original.grid
    x, y = middle[0] + BORDER_CELLS, middle[1] + BORDER_CELLS
    grid[y - 2:y + 3, x - 2:x + 3] = 100
    new = OccupancyMap(grid, original.resolution, original.origin_x - BORDER_CELLS * original.resolution,
                       original.origin_y - BORDER_CELLS * original.resolution, name="replaced")
    shifted = (a[0] + BORDER_CELLS, a[1] + BORDER_CELLS), (b[0] + BORDER_CELLS, b[1] + BORDER_CELLS)
    plan_cells(grid, *shifted)   # raises NoPathError if the wall cut the goal off
    return new


class FaultStack(WaitsForRecords):
    """The whole online system on a master of the test's own, its processes restartable one by one, and
    what it publishes kept by request id."""
    wait_timeout_s = 60

    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.TemporaryDirectory()
        cls.processes = {}
        cls.emulator = None
        cls.addClassCleanup(cls.stop_all)
        atexit.register(cls.stop_all)   # also when rostest interrupts the test (time limit, Ctrl-C)
        cls.processes["master"] = start_master()
        rospy.init_node("rtest_fault_matrix", disable_signals=True)
        cls.lock = threading.Lock()
        cls.decisions, cls.outcomes, cls.cloud_timings = {}, {}, []
        rospy.Subscriber("/offload_learner/decision", OffloadDecision, cls.keep_by_id(cls.decisions))
        rospy.Subscriber("/offload_learner/outcome", OffloadOutcome, cls.keep_by_id(cls.outcomes))
        rospy.Subscriber("/cloud_bridge/timing", PlanTiming, cls.keep_timing)
        # The map is published by the test (as map_publisher does) so it can replace it mid-run.
        cls.map_pub = rospy.Publisher("map", numpy_msg(OccupancyGrid), queue_size=1, latch=True)
        cls.meta_pub = rospy.Publisher("map_metadata", MapMetaData, queue_size=1, latch=True)
        cls.original = load_map(os.path.join(rospy_package_path("offload_planner_cpp"), "maps",
                                             "turtlebot3_world", "map.yaml"))
        cls.publish_map(cls.original)
        cls.processes["planner"] = subprocess.Popen(["rosrun", "offload_planner_cpp", "planner_node",
                                                     "__name:=planner"],
                                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        cls.server_port = free_port()
        cls.start_server()
        cls.link = LinkModel()
        cls.emulator = WanEmulator("tcp://127.0.0.1:0", f"tcp://127.0.0.1:{cls.server_port}", cls.link)
        cls.emulator_started_at = time.monotonic()
        cls.emulator.start()
        cls.start_bridge()
        cls.bag_number = 0
        cls.bag_paths = []
        cls.start_recorder()
        cls.checkpoint = os.path.join(cls.tmp.name, "learner.pt")
        cls.start_learner()

    # --- processes ------------------------------------------------------------------------------
    @classmethod
    def start_server(cls):
        cls.processes["server"], _ = spawn_cloud_server(cls.server_port)

    @classmethod
    def start_bridge(cls):
        cls.processes["bridge"] = subprocess.Popen(
            [sys.executable, "-m", "offload_learner_py.nodes.cloud_bridge", "__name:=cloud_bridge",
             f"_endpoint:={cls.emulator.endpoint}", "_insecure:=true", f"_timeout_s:={CLOUD_TIMEOUT_S}",
             "_retries:=0", "_heartbeat_period_s:=0.2", "_heartbeat_timeout_s:=0.5"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        rospy.wait_for_service("/cloud_bridge/plan", timeout=60)

    @classmethod
    def start_recorder(cls):
        """offload_record, as launch/record.launch starts it on its topics (it execs the recorder, so SIGKILL reaches
        the recorder), into a new bag each time as a restarted robot should."""
        cls.bag_number += 1
        bag = os.path.join(cls.tmp.name, f"session{cls.bag_number}.bag")
        cls.bag_paths.append(bag)
        tokens = ElementTree.parse(launch_file("record.launch")).find("node").get("args").split()
        topics = tokens[tokens.index("--") + 1:]
        cls.processes["record"] = subprocess.Popen(
            [sys.executable, "-m", "offload_learner_py.nodes.record", "--bag", bag, "--", *topics,
             "__name:=offload_record"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    @classmethod
    def start_learner(cls):
        # map_wait_s generous: the grid follows its metadata 1 s later in test_1
        cls.processes["learner"] = start_learner_node(cls.checkpoint, "_breaker_failures:=0", "_map_wait_s:=10")
        cls.plan = rospy.ServiceProxy("/offload_learner/plan", PlanPath, persistent=True)

    @classmethod
    def stop_all(cls):
        if getattr(cls, "stopped", False):
            return
        cls.stopped = True
        plan = getattr(cls, "plan", None)
        if plan is not None:
            plan.close()
        for name in ("learner", "record", "bridge", "planner", "server"):
            stop(cls.processes.get(name))
        if cls.emulator is not None:
            cls.emulator.stop()
        rospy.signal_shutdown("fault matrix done")
        stop(cls.processes.get("master"))
        cls.tmp.cleanup()

    # --- inputs and records ---------------------------------------------------------------------
    @classmethod
    def publish_map(cls, occupancy: OccupancyMap):
        msg = to_message(occupancy, "map", rospy.Time.now())
        cls.map_in_force = (occupancy, msg.header.stamp)
        cls.meta_pub.publish(msg.info)
        cls.map_pub.publish(msg)

    @classmethod
    def keep_by_id(cls, into):
        def callback(msg):
            with cls.lock:
                into[msg.request_id] = msg
        return callback

    @classmethod
    def keep_timing(cls, msg):
        with cls.lock:
            cls.cloud_timings.append(msg)

    def request(self, goal_xy) -> PlanPathRequest:
        request = PlanPathRequest(tolerance=0.3)
        for pose, xy in ((request.start, START), (request.goal, goal_xy)):
            pose.header.frame_id = "map"
            pose.pose.position.x, pose.pose.position.y = xy
            pose.pose.orientation.w = 1.0
        return request

    def assert_path_on(self, response, occupancy: OccupancyMap, stamp):
        """The path was planned on this map and every pose of it is a free cell of it."""
        self.assertEqual(response.status, PlanPathResponse.OK, response.message)
        self.assertEqual(response.map_stamp, stamp, "a path from another map than the one in force")
        ok, geometry = check_map(occupancy.width, occupancy.height, occupancy.grid.size, occupancy.resolution,
                                 occupancy.origin_x, occupancy.origin_y, (0.0, 0.0, 0.0, 1.0))
        free = free_cells(occupancy.grid)
        self.assertGreater(len(response.path.poses), 0)
        for pose in response.path.poses:
            cell = geometry.world_to_cell(pose.pose.position.x, pose.pose.position.y)
            self.assertIsNotNone(cell, "a pose off the map")
            self.assertTrue(free[cell[1], cell[0]], f"the path crosses an obstacle at cell {cell}")


def rospy_package_path(package: str) -> str:
    import rospkg
    return rospkg.RosPack().get_path(package)
