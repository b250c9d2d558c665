"""offload_record: a bag of the offloading topics that never replaces a bag and fails loudly.

A recorder opening BAG truncates an existing file (a crashed session's .bag.active, or a finished bag), and
on a disk with too little free space records nothing, saying so only in its own log. This checks both before
it hands over to the recorder, offload_bag_recorder (exec: the recorder keeps this process, so signals reach
it), and exits non-zero with one line instead: record.launch marks it required, so the launch fails. The
recorder writes what `rosbag record` writes, with one callback thread instead of rosbag's ten
(src/bag_recorder.cpp says why).

    offload_record [--bag PATH | --prefix PREFIX] [--min-free-mib N] -- TOPIC...
"""
import argparse
import os
import shutil
import sys
import time

from offload_cloud.cli_args import bounded_int

MIN_FREE_MIB = 1024   # rosbag record's minimum free space (1 GB), which the recorder keeps: below it, it stops
RECORDER = "offload_bag_recorder"


def bag_path(bag: str, prefix: str, now: float) -> str:
    """The file the recorder will write: the bag asked for, with ".bag" appended as `rosbag record -O` appends it to
    a name without it (checking NAME while rosbag wrote NAME.bag replaced an earlier run's bag), else
    PREFIX-<local time>.bag, so a restart never reuses a name."""
    if not bag:
        return f"{prefix}-{time.strftime('%Y%m%d-%H%M%S', time.localtime(now))}.bag"
    return bag if bag.endswith(".bag") else bag + ".bag"


def problem(path: str, min_free_mib: int) -> str:
    """Why recording into `path` would lose or record nothing, or ""."""
    for existing in (path, path + ".active"):
        if os.path.lexists(existing):
            return f"{existing} exists: refusing to replace a recorded bag (give another bag:= name)"
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        return f"{directory} is not a directory"
    free_mib = shutil.disk_usage(directory).free // (1 << 20)
    if free_mib < min_free_mib:
        return (f"only {free_mib} MiB free in {directory}, under the {min_free_mib} MiB the recorder needs to record "
                f"(it would record nothing): free space or record elsewhere")
    return ""


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    ros_args = [arg for arg in argv if arg.startswith("__") and ":=" in arg]   # __name:=, __log:= from roslaunch
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bag", default="", help="exact bag file")
    parser.add_argument("--prefix", default=os.path.join(os.environ.get("ROS_HOME", "/tmp"), "offload"))
    parser.add_argument("--min-free-mib", type=bounded_int("--min-free-mib", 0, 1 << 30), default=MIN_FREE_MIB)
    parser.add_argument("topics", nargs="+")
    args = parser.parse_args([arg for arg in argv if arg not in ros_args])
    path = bag_path(args.bag, args.prefix, time.time())
    why = problem(path, args.min_free_mib)
    if why:
        raise SystemExit(f"offload_record: {why}")
    recorder = recorder_path()
    print(f"offload_record: recording {len(args.topics)} topics into {path}", flush=True)
    os.execv(recorder, [recorder, "--min-free-mib", str(args.min_free_mib), path, *args.topics, *ros_args])


def recorder_path() -> str:
    """offload_bag_recorder, where catkin put it (devel or install space)."""
    from roslib.packages import find_node   # only here: the checks above need no ROS
    found = find_node("offload_learner_py", RECORDER)
    if not found:
        raise SystemExit(f"offload_record: {RECORDER} not found: build the workspace (make build)")
    return found[0]


if __name__ == "__main__":
    main()
