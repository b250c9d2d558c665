// pybind11 module of the planner core: offload_planner_cpp._core. The Python package wraps plan_raw()
// into plan(), which raises; this layer never copies the grid and releases the GIL while planning.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstring>
#include <sstream>

#include "offload_planner_cpp/dijkstra.h"

namespace py = pybind11;
using offload_planner::Cell;
using offload_planner::DijkstraPlanner;
using offload_planner::PlannerOptions;
using offload_planner::PlanResult;

namespace {

struct GridView {
  const std::int8_t* data;
  std::size_t size;
  int width;
  int height;
};

// Borrows the array's buffer: only a C-contiguous 2-D int8 array is accepted, so nothing is converted.
GridView viewOf(const py::array& grid) {
  if (grid.ndim() != 2) {
    throw py::value_error("grid must be a 2-D array indexed [y, x], got " + std::to_string(grid.ndim()) +
                          " dimensions");
  }
  if (!grid.dtype().is(py::dtype::of<std::int8_t>())) {
    throw py::value_error("grid must have dtype int8 (OccupancyGrid convention), got " +
                          std::string(py::str(grid.dtype())) + "; convert with grid.astype(numpy.int8)");
  }
  if (!(grid.flags() & py::array::c_style)) {
    throw py::value_error("grid must be C-contiguous; pass numpy.ascontiguousarray(grid)");
  }
  return {static_cast<const std::int8_t*>(grid.data()), static_cast<std::size_t>(grid.size()),
          static_cast<int>(grid.shape(1)), static_cast<int>(grid.shape(0))};
}

Cell cellOf(const py::handle& obj, const char* name) {
  try {
    auto seq = py::cast<py::sequence>(obj);
    if (py::len(seq) != 2) throw py::value_error("");
    return {py::cast<int>(seq[0]), py::cast<int>(seq[1])};
  } catch (const py::error_already_set&) {
  } catch (const py::cast_error&) {
  } catch (const py::value_error&) {
  }
  throw py::value_error(std::string(name) + " must be an (x, y) pair of integer cells");
}

py::dict planRaw(const py::array& grid, const py::object& start, const py::object& goal, int lethal_threshold,
                 bool unknown_is_obstacle, double goal_tolerance, bool stop_at_goal) {
  const GridView view = viewOf(grid);
  PlannerOptions options;
  options.lethal_threshold = lethal_threshold;
  options.unknown_is_obstacle = unknown_is_obstacle;
  options.goal_tolerance_cells = goal_tolerance;
  options.stop_at_goal = stop_at_goal;
  const Cell s = cellOf(start, "start");
  const Cell g = cellOf(goal, "goal");
  // One planner per thread keeps the buffers warm and lets threads plan in parallel.
  static thread_local DijkstraPlanner planner;
  PlanResult result;
  {
    py::gil_scoped_release release;  // the grid stays alive: the caller's reference holds it
    result = planner.plan(view.data, view.size, view.width, view.height, s, g, options);
  }
  py::array_t<std::int32_t> path({static_cast<py::ssize_t>(result.path.size()), static_cast<py::ssize_t>(2)});
  static_assert(sizeof(Cell) == 2 * sizeof(std::int32_t), "Cell must be two packed ints");
  if (!result.path.empty()) std::memcpy(path.mutable_data(), result.path.data(), result.path.size() * sizeof(Cell));
  py::dict out;
  out["status"] = offload_planner::statusName(result.status);
  out["message"] = result.message;
  out["path"] = path;
  out["cost"] = result.cost;
  out["goal"] = py::make_tuple(result.goal.x, result.goal.y);
  out["expansions"] = result.expansions;
  out["seconds"] = result.seconds;
  return out;
}

}  // namespace

PYBIND11_MODULE(_core, m) {
  m.doc() = "Dijkstra on an OccupancyGrid-convention int8 grid (8-connected, no corner cutting).";
  m.def("plan_raw", &planRaw, py::arg("grid"), py::arg("start"), py::arg("goal"), py::arg("lethal_threshold") = 50,
        py::arg("unknown_is_obstacle") = true, py::arg("goal_tolerance") = 0.0, py::arg("stop_at_goal") = true,
        "Plan without raising on planning failures: returns a dict with status, message, path, cost, goal, "
        "expansions, seconds. Malformed arguments raise ValueError.");
  m.def(
      "grid_address", [](const py::array& grid) { return reinterpret_cast<std::uintptr_t>(viewOf(grid).data); },
      py::arg("grid"), "Address of the buffer the planner reads for `grid` (proves it is not copied).");
}
