"""The one-machine demo and its benchmarks, apart from what ships to a robot (as grid_map keeps
grid_map_demos): the driver of `make demo` (cgroup budget, roslaunch, the run's summary and report), the
CURVE keys it makes, the robot workload, the cloud server and WAN emulator as roslaunch nodes, and the live
benchmarks (bench_online, bench_policies)."""
