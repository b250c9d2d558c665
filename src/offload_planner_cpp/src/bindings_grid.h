// The planner grid as the pybind11 module borrows it from numpy (bindings.cpp, bindings_paths.cpp). Internal to
// the module: not part of the core's headers.
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstdint>
#include <string>

namespace offload_planner_bindings {

namespace py = pybind11;

struct GridView {
  const std::int8_t* data;
  std::size_t size;
  int width;
  int height;
};

// Borrows the array's buffer: only a C-contiguous 2-D int8 array is accepted, so nothing is converted.
inline GridView viewOf(const py::array& grid) {
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

}  // namespace offload_planner_bindings
