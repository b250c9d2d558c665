// pybind11 module of the planner core: offload_planner_cpp._core. The Python package wraps plan_raw()
// into plan(), which raises; this layer never copies the grid and releases the GIL while planning. It
// also exposes the request contract (plan_request.h) so the cloud bridge answers exactly as the ROS
// node, the status codes, so Python never types them again, and the planner options table
// (planner_options.h): nothing here validates an option or converts metres itself.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstring>
#include <sstream>

#include "offload_planner_cpp/dijkstra.h"
#include "offload_planner_cpp/inflation.h"
#include "offload_planner_cpp/plan_request.h"
#include "offload_planner_cpp/planner_options.h"
#include "offload_planner_cpp/planner_pool.h"
#include "bindings_grid.h"

namespace py = pybind11;
using offload_planner::Cell;
using offload_planner::CellRequest;
using offload_planner::PlannerPool;
using offload_planner::MapGeometry;
using offload_planner::MapInfo;
using offload_planner::Outcome;
using offload_planner::PlannerOptions;
using offload_planner::PlanResult;
using offload_planner::PlanStatus;
using offload_planner_bindings::GridView;
using offload_planner_bindings::viewOf;

// planner_options.h's table, its checks and conversions: bindings_options.cpp.
void defineOptions(py::module_& m);
// Paths planned elsewhere: their poses and their check (bindings_paths.cpp).
void definePaths(py::module_& m, const PlannerOptions& defaults);
// The learner's decision, compiled (bindings_decision.cpp).
void defineDecision(py::module_& m);

namespace {

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

// Raises ValueError with the core's reason when `options` are not acceptable.
void check(const PlannerOptions& options) {
  const std::string problem = offload_planner::optionsProblem(options);
  if (!problem.empty()) throw py::value_error(problem);
}

py::dict planRaw(const py::array& grid, const py::object& start, const py::object& goal, int lethal_threshold,
                 bool unknown_is_obstacle, double goal_tolerance, bool stop_at_goal, const std::string& algorithm,
                 bool any_angle, double cost_factor, double neutral_cost, double inflation_radius_cells,
                 double robot_radius_cells, double inflation_decay) {
  const GridView view = viewOf(grid);
  PlannerOptions options;
  options.lethal_threshold = lethal_threshold;
  options.unknown_is_obstacle = unknown_is_obstacle;
  options.goal_tolerance_cells = goal_tolerance;
  options.stop_at_goal = stop_at_goal;
  const std::string unknown = offload_planner::algorithmOf(algorithm, &options.algorithm);
  if (!unknown.empty()) throw py::value_error(unknown);   // a name that is no algorithm; values: INVALID_REQUEST
  options.any_angle = any_angle;
  options.cost_factor = cost_factor;
  options.neutral_cost = neutral_cost;
  options.inflation_radius_cells = inflation_radius_cells;
  options.robot_radius_cells = robot_radius_cells;
  options.inflation_decay = inflation_decay;
  const Cell s = cellOf(start, "start");
  const Cell g = cellOf(goal, "goal");
  // Plans that overlap run in parallel, each on a planner of its own; one at a time reuse one (planner_pool.h).
  // Never destroyed: a daemon thread may still be planning, the GIL released, while the interpreter exits.
  static PlannerPool& planners = *new PlannerPool;
  PlanResult result;
  {
    py::gil_scoped_release release;  // the grid stays alive: the caller's reference holds it
    result = planners.borrow()->plan(view.data, view.size, view.width, view.height, s, g, options);
  }
  py::array_t<std::int32_t> path({static_cast<py::ssize_t>(result.path.size()), static_cast<py::ssize_t>(2)});
  static_assert(sizeof(Cell) == 2 * sizeof(std::int32_t), "Cell must be two packed ints");
  if (!result.path.empty()) std::memcpy(path.mutable_data(), result.path.data(), result.path.size() * sizeof(Cell));
  py::dict out;
  out["status"] = result.status;
  out["message"] = result.message;
  out["path"] = path;
  out["cost"] = result.cost;
  out["weighted_cost"] = result.weighted_cost;
  out["goal"] = py::make_tuple(result.goal.x, result.goal.y);
  out["expansions"] = result.expansions;
  out["seconds"] = result.seconds;
  out["grid_address"] = reinterpret_cast<std::uintptr_t>(result.grid);
  return out;
}

py::object cellOrNone(bool ok, Cell c) { return ok ? py::object(py::make_tuple(c.x, c.y)) : py::object(py::none()); }

}  // namespace

PYBIND11_MODULE(_core, m) {
  m.doc() = "Dijkstra on an OccupancyGrid-convention int8 grid (8-connected, no corner cutting).";

  // pybind11 before 2.12 fills the numpy API table in a function-local static on first use. Its first user
  // imports numpy's C module and may release the GIL inside the static's guard; a second thread then blocks
  // on that guard holding the GIL and both wait forever. Filling it here, while the import holds the GIL and
  // no other thread can be in this module, leaves nothing for concurrent first calls to initialise.
  py::detail::npy_api::get();
  (void)py::dtype::of<std::int8_t>();
  (void)py::array_t<std::int32_t>(0);
  (void)py::array_t<double>(0);
  (void)py::array_t<bool>(0);

  const PlannerOptions d;   // every keyword's default is the core's (planner_options.h)
  defineOptions(m);

  // Names come from the core (statusName), values from the enum: nothing is typed twice.
  py::enum_<PlanStatus> status(m, "PlanStatus", "Status of a planning request; the offload_msgs/PlanPath codes.");
  for (int code = 0; code < offload_planner::kPlanStatusCount; ++code) {
    const auto value = static_cast<PlanStatus>(code);
    status.value(offload_planner::statusName(value), value);
  }

  py::class_<Outcome>(m, "Outcome", "A status and, unless OK, why.")
      .def_readonly("status", &Outcome::status)
      .def_readonly("message", &Outcome::message)
      .def_property_readonly("ok", &Outcome::ok)
      .def("__repr__", [](const Outcome& o) {
        return "Outcome(" + std::string(offload_planner::statusName(o.status)) + ", '" + o.message + "')";
      });

  py::class_<MapGeometry>(m, "MapGeometry", "World <-> cell conversion of a checked map (see check_map).")
      .def_readonly("resolution", &MapGeometry::resolution)
      .def_readonly("origin_x", &MapGeometry::origin_x)
      .def_readonly("origin_y", &MapGeometry::origin_y)
      .def_readonly("origin_yaw", &MapGeometry::origin_yaw)
      .def_readonly("width", &MapGeometry::width)
      .def_readonly("height", &MapGeometry::height)
      .def(
          "world_to_cell",
          [](const MapGeometry& g, double x, double y) {
            Cell c;
            const bool ok = g.worldToCell(x, y, &c);
            return cellOrNone(ok, c);
          },
          py::arg("x"), py::arg("y"), "Cell (x, y) containing the world point, or None off the grid.")
      .def(
          "cell_to_world",
          [](const MapGeometry& g, int x, int y) {
            double wx, wy;
            g.cellToWorld(Cell{x, y}, &wx, &wy);
            return py::make_tuple(wx, wy);
          },
          py::arg("x"), py::arg("y"), "World coordinates of the cell's centre.");

  m.def(
      "check_map",
      [](std::uint64_t width, std::uint64_t height, std::size_t data_size, double resolution, double origin_x,
         double origin_y, const std::vector<double>& orientation, std::uint64_t max_cells) {
        if (orientation.size() != 4) throw py::value_error("orientation must be (qx, qy, qz, qw)");
        MapInfo info;
        info.width = width;
        info.height = height;
        info.data_size = data_size;
        info.resolution = resolution;
        info.origin_x = origin_x;
        info.origin_y = origin_y;
        info.qx = orientation[0];
        info.qy = orientation[1];
        info.qz = orientation[2];
        info.qw = orientation[3];
        MapGeometry geometry;
        const Outcome outcome = offload_planner::checkMap(info, max_cells, &geometry);
        return py::make_tuple(outcome, outcome.ok() ? py::cast(geometry) : py::object(py::none()));
      },
      py::arg("width"), py::arg("height"), py::arg("data_size"), py::arg("resolution"), py::arg("origin_x"),
      py::arg("origin_y"), py::arg("orientation"), py::arg("max_cells") = 0,
      "(Outcome, MapGeometry or None) of an OccupancyGrid's metadata: INVALID_MAP and why when unusable.");
  m.def("no_map_outcome", &offload_planner::noMapOutcome, py::arg("last_rejection"),
        "The NO_MAP answer, naming why the last map was refused if one was.");
  m.def("in_map_frame", &offload_planner::inMapFrame, py::arg("frame"), py::arg("map_frame"));
  m.def(
      "resolve_request",
      [](const MapGeometry& g, const std::string& map_frame, const std::string& start_frame, double start_x,
         double start_y, const std::string& goal_frame, double goal_x, double goal_y, float tolerance_m) {
        // A plain tuple, not a bound object: each attribute of one is a trip through pybind11's dispatcher, and
        // the cloud bridge resolves every cloud request on a cold cache (#30's bridge CPU bar).
        const CellRequest r = offload_planner::resolveRequest(g, map_frame, {start_frame, start_x, start_y},
                                                              {goal_frame, goal_x, goal_y}, tolerance_m);
        if (!r.outcome.ok()) return py::make_tuple(r.outcome, py::none(), py::none(), py::none());
        return py::make_tuple(py::none(), py::make_tuple(r.start.x, r.start.y), py::make_tuple(r.goal.x, r.goal.y),
                              r.tolerance_cells);
      },
      py::arg("geometry"), py::arg("map_frame"), py::arg("start_frame"), py::arg("start_x"), py::arg("start_y"),
      py::arg("goal_frame"), py::arg("goal_x"), py::arg("goal_y"), py::arg("tolerance_m"),
      "Checks a PlanPath request against the map and converts it to cells (tolerance is float32 as in the "
      "service): (None, start (x, y), goal (x, y), tolerance in cells), or (the refusing Outcome, None, None, None).");
  m.def(
      "free_cells",
      [](const py::array& grid, int lethal_threshold, bool unknown_is_obstacle) {
        const GridView view = viewOf(grid);
        PlannerOptions options;
        options.lethal_threshold = lethal_threshold;
        options.unknown_is_obstacle = unknown_is_obstacle;
        check(options);
        py::array_t<bool> free({static_cast<py::ssize_t>(view.height), static_cast<py::ssize_t>(view.width)});
        bool* out = free.mutable_data();
        for (std::size_t k = 0; k < view.size; ++k) out[k] = offload_planner::isPassable(view.data[k], options);
        return free;
      },
      py::arg("grid"), py::arg("lethal_threshold") = d.lethal_threshold,
      py::arg("unknown_is_obstacle") = d.unknown_is_obstacle,
      "Boolean [y, x] mask of the cells the planner may enter, by its own rule.");
  m.def("plan_raw", &planRaw, py::arg("grid"), py::arg("start"), py::arg("goal"),
        py::arg("lethal_threshold") = d.lethal_threshold, py::arg("unknown_is_obstacle") = d.unknown_is_obstacle,
        py::arg("goal_tolerance") = d.goal_tolerance_cells, py::arg("stop_at_goal") = d.stop_at_goal, py::kw_only(),
        py::arg("algorithm") = std::string(offload_planner::algorithmName(d.algorithm)),
        py::arg("any_angle") = d.any_angle, py::arg("cost_factor") = d.cost_factor,
        py::arg("neutral_cost") = d.neutral_cost, py::arg("inflation_radius_cells") = d.inflation_radius_cells,
        py::arg("robot_radius_cells") = d.robot_radius_cells, py::arg("inflation_decay") = d.inflation_decay,
        "Plan without raising on planning failures: returns a dict with status (PlanStatus), message, path, "
        "cost (length in cells), weighted_cost (in the cost model planned with), goal, expansions, seconds and "
        "grid_address (the buffer planned on). Malformed arguments raise ValueError.");
  definePaths(m, d);
  defineDecision(m);
  m.def(
      "inflate",
      [](const py::array& grid, double robot_radius_cells, double inflation_radius_cells, double inflation_decay,
         int lethal_threshold, bool unknown_is_obstacle) {
        const GridView view = viewOf(grid);
        PlannerOptions options;
        options.lethal_threshold = lethal_threshold;
        options.unknown_is_obstacle = unknown_is_obstacle;
        options.robot_radius_cells = robot_radius_cells;
        options.inflation_radius_cells = inflation_radius_cells;
        options.inflation_decay = inflation_decay;
        check(options);
        std::vector<std::int8_t> out;
        {
          py::gil_scoped_release release;
          offload_planner::inflate(view.data, view.width, view.height, options, &out);
        }
        py::array_t<std::int8_t> inflated({static_cast<py::ssize_t>(view.height), static_cast<py::ssize_t>(view.width)});
        std::memcpy(inflated.mutable_data(), out.data(), out.size());
        return inflated;
      },
      py::arg("grid"), py::arg("robot_radius_cells"), py::arg("inflation_radius_cells"),
      py::arg("inflation_decay") = d.inflation_decay, py::arg("lethal_threshold") = d.lethal_threshold,
      py::arg("unknown_is_obstacle") = d.unknown_is_obstacle,
      "The grid the planner plans on with these inflation options (a copy; see inflation.h).");
}
