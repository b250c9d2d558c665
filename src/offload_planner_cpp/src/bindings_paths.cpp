// Paths planned elsewhere, in the pybind11 module: their world poses as the ROS planner node writes them
// (path_poses), and the check a cloud reply's path must pass (check_path, path_clear), by the core's own rules
// (plan_request.h, path_check.h). check_path_rows does both in one call for the cloud bridge, which meets a cold
// cache on every cloud plan: each call through pybind11's dispatcher costs it tens of microseconds there.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstring>
#include <string>
#include <utility>
#include <vector>

#include "bindings_grid.h"
#include "offload_planner_cpp/path_check.h"
#include "offload_planner_cpp/plan_request.h"
#include "offload_planner_cpp/planner_options.h"

namespace py = pybind11;
using offload_planner::Cell;
using offload_planner::MapGeometry;
using offload_planner::PlannerOptions;
using offload_planner::Pose;
using offload_planner_bindings::GridView;
using offload_planner_bindings::viewOf;

namespace {

using CellArray = py::array_t<std::int32_t, py::array::c_style | py::array::forcecast>;
static_assert(sizeof(Cell) == 2 * sizeof(std::int32_t), "Cell must be two packed ints");
static_assert(sizeof(Pose) == 7 * sizeof(double), "Pose must be seven packed doubles");

Pose poseOf(const std::vector<double>& v, const char* name) {
  if (v.size() != 7) throw py::value_error(std::string(name) + " must be (x, y, z, qx, qy, qz, qw)");
  return {v[0], v[1], v[2], v[3], v[4], v[5], v[6]};
}

// The count (uint32) then every pose's 7 doubles after the prefix, little-endian: a serialized array of messages
// whose rows differ only in their poses (the cloud bridge's PoseStamped rows, path_wire.py), written in one pass
// straight into the bytes object.
py::object poseRows(const MapGeometry& geometry, const Cell* cells, std::size_t n, const std::vector<double>& start,
                    const std::vector<double>& goal, bool reached_requested_goal, const std::string& prefix) {
  static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__, "rows are written in the host's byte order");
  const Pose start_pose = poseOf(start, "start"), goal_pose = poseOf(goal, "goal");
  const std::size_t row = prefix.size() + sizeof(Pose);
  if (n > 0xFFFFFFFFu) throw py::value_error("more poses than a uint32 count holds");
  const auto count = static_cast<std::uint32_t>(n);
  PyObject* bytes = PyBytes_FromStringAndSize(nullptr, static_cast<py::ssize_t>(sizeof(count) + count * row));
  if (bytes == nullptr) throw py::error_already_set();
  auto* out = reinterpret_cast<unsigned char*>(PyBytes_AS_STRING(bytes));
  std::memcpy(out, &count, sizeof(count));
  out += sizeof(count);
  for (std::size_t k = 0; k < n; ++k) std::memcpy(out + k * row, prefix.data(), prefix.size());
  offload_planner::writePathPoses(geometry, cells, n, start_pose, goal_pose, reached_requested_goal,
                                  out + prefix.size(), row);
  return py::reinterpret_steal<py::object>(bytes);
}

// N x 7 (x, y, z, qx, qy, qz, qw) poses; with a row prefix, poseRows' bytes instead.
py::object pathPoses(const MapGeometry& geometry, const CellArray& path, const std::vector<double>& start,
                     const std::vector<double>& goal, bool reached_requested_goal, const py::object& row_prefix) {
  if (path.ndim() != 2 || (path.shape(0) > 0 && path.shape(1) != 2)) {
    throw py::value_error("path must be an N x 2 array of (x, y) cells");
  }
  const auto* cells = reinterpret_cast<const Cell*>(path.data());
  const auto n = static_cast<std::size_t>(path.shape(0));
  if (!row_prefix.is_none()) {
    return poseRows(geometry, cells, n, start, goal, reached_requested_goal, row_prefix.cast<py::bytes>());
  }
  py::array_t<double> out({static_cast<py::ssize_t>(n), static_cast<py::ssize_t>(7)});
  offload_planner::writePathPoses(geometry, cells, n, poseOf(start, "start"), poseOf(goal, "goal"),
                                  reached_requested_goal, reinterpret_cast<unsigned char*>(out.mutable_data()),
                                  sizeof(Pose));
  return std::move(out);
}

const char* const kProblemNames[] = {"", "leaves_map", "wrong_start", "wrong_end", "repeats_corner",
                                     "not_8_connected", "blocked"};

offload_planner::PathCheck checkOf(const py::array& grid, const CellArray& path, std::pair<int, int> start,
                                   std::pair<int, int> reached_goal, bool any_angle, int lethal_threshold,
                                   bool unknown_is_obstacle) {
  const GridView view = viewOf(grid);
  if (path.ndim() != 2 || path.shape(1) != 2 || path.shape(0) < 1) {
    throw py::value_error("path must be an N x 2 array of (x, y) cells, N >= 1");
  }
  PlannerOptions options;
  options.lethal_threshold = lethal_threshold;
  options.unknown_is_obstacle = unknown_is_obstacle;
  return offload_planner::checkPath(view.data, view.width, view.height, reinterpret_cast<const Cell*>(path.data()),
                                    static_cast<std::size_t>(path.shape(0)), Cell{start.first, start.second},
                                    Cell{reached_goal.first, reached_goal.second}, any_angle, options);
}

}  // namespace

void definePaths(py::module_& m, const PlannerOptions& d) {
  m.def("path_poses", &pathPoses, py::arg("geometry"), py::arg("path"), py::arg("start_pose"), py::arg("goal_pose"),
        py::arg("reached_requested_goal"), py::arg("row_prefix") = py::none(),
        "N x 7 (x, y, z, qx, qy, qz, qw) world poses of a planned path, as the ROS planner node returns them; with "
        "row_prefix (bytes), bytes instead: the count (uint32) then each pose's 7 doubles after row_prefix, "
        "little-endian.");
  m.def(
      "path_clear",
      [](const py::array& grid, const CellArray& path, int lethal_threshold, bool unknown_is_obstacle) {
        const GridView view = viewOf(grid);
        if (path.ndim() != 2 || (path.shape(0) > 0 && path.shape(1) != 2)) {
          throw py::value_error("path must be an N x 2 array of (x, y) cells");
        }
        PlannerOptions options;
        options.lethal_threshold = lethal_threshold;
        options.unknown_is_obstacle = unknown_is_obstacle;
        auto p = path.unchecked<2>();
        for (py::ssize_t k = 0; k + 1 < path.shape(0); ++k) {
          if (!offload_planner::segmentClear(view.data, view.width, view.height, Cell{p(k, 0), p(k, 1)},
                                             Cell{p(k + 1, 0), p(k + 1, 1)}, options)) {
            return k;
          }
        }
        return py::ssize_t(-1);
      },
      py::arg("grid"), py::arg("path"), py::arg("lethal_threshold") = d.lethal_threshold,
      py::arg("unknown_is_obstacle") = d.unknown_is_obstacle,
      "Index of the first segment of `path` (N x 2 cells) that leaves the grid, crosses a blocked cell or cuts a "
      "blocked corner (the planner's line-of-sight rule); -1 when every segment is clear.");
  m.def(
      "check_path",
      [](const py::array& grid, const CellArray& path, std::pair<int, int> start, std::pair<int, int> reached_goal,
         bool any_angle, int lethal_threshold, bool unknown_is_obstacle) {
        const auto check = checkOf(grid, path, start, reached_goal, any_angle, lethal_threshold, unknown_is_obstacle);
        return py::make_tuple(kProblemNames[static_cast<int>(check.problem)], check.index, check.length_cells);
      },
      py::arg("grid"), py::arg("path"), py::arg("start"), py::arg("reached_goal"), py::arg("any_angle"),
      py::arg("lethal_threshold") = d.lethal_threshold, py::arg("unknown_is_obstacle") = d.unknown_is_obstacle,
      "(problem, segment, length in cells) of a path planned elsewhere, in one pass over its cells (path_check.h): "
      "problem is '' or one of leaves_map, wrong_start, wrong_end, repeats_corner, not_8_connected, blocked "
      "(segment: the first blocked one); the length is 0 unless the problem is ''.");
  m.def(
      "check_path_rows",
      [](const py::array& grid, const CellArray& path, std::pair<int, int> start, std::pair<int, int> reached_goal,
         bool any_angle, int lethal_threshold, bool unknown_is_obstacle, const MapGeometry& geometry,
         const std::vector<double>& start_pose, const std::vector<double>& goal_pose, bool reached_requested_goal,
         const py::bytes& row_prefix) {
        const auto check = checkOf(grid, path, start, reached_goal, any_angle, lethal_threshold, unknown_is_obstacle);
        py::object rows = py::bytes();
        if (check.problem == offload_planner::PathProblem::kNone) {
          rows = poseRows(geometry, reinterpret_cast<const Cell*>(path.data()), static_cast<std::size_t>(path.shape(0)),
                          start_pose, goal_pose, reached_requested_goal, row_prefix);
        }
        return py::make_tuple(kProblemNames[static_cast<int>(check.problem)], check.index, check.length_cells, rows);
      },
      py::arg("grid"), py::arg("path"), py::arg("start"), py::arg("reached_goal"), py::arg("any_angle"),
      py::arg("lethal_threshold"), py::arg("unknown_is_obstacle"), py::arg("geometry"), py::arg("start_pose"),
      py::arg("goal_pose"), py::arg("reached_requested_goal"), py::arg("row_prefix"),
      "check_path, then for a path without a problem path_poses' rows (row_prefix given) in the same call: (problem, "
      "segment, length in cells, rows), rows b'' on a problem.");
}
