// The planner options table of the core (planner_options.h) in the pybind11 module: ALGORITHM_NAMES,
// options_table(), validate_options(**values) and options_in_cells(resolution, **metres). Python checks
// and converts planner options with these and nothing of its own, so every layer refuses the same values
// with the same words.
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <string>

#include "offload_planner_cpp/planner_options.h"

namespace py = pybind11;
using offload_planner::OptionScope;
using offload_planner::OptionSpec;
using offload_planner::OptionType;
using offload_planner::PlannerParameters;

namespace {

const char* typeName(OptionType type) {
  switch (type) {
    case OptionType::kBool: return "bool";
    case OptionType::kInt: return "int";
    case OptionType::kReal: return "float";
    case OptionType::kAlgorithm: return "algorithm";
  }
  return "unknown";
}

// A row's value as Python has it: bool, int, float, or the algorithm's name.
py::object pythonValue(const OptionSpec& spec, double value) {
  switch (spec.type) {
    case OptionType::kBool: return py::bool_(value != 0.0);
    case OptionType::kInt: return py::int_(static_cast<long long>(value));
    case OptionType::kReal: return py::float_(value);
    case OptionType::kAlgorithm:
      return py::str(offload_planner::algorithmName(static_cast<offload_planner::Algorithm>(static_cast<int>(value))));
  }
  return py::none();
}

const OptionSpec& rowOf(const std::string& name) {
  const OptionSpec* spec = offload_planner::findOption(name);
  if (spec == nullptr) {
    std::string names;
    for (const OptionSpec& row : offload_planner::optionsTable()) {
      names += (names.empty() ? "" : ", ") + std::string(row.name);
    }
    throw py::type_error("unknown planner option '" + name + "'; the options are " + names);
  }
  return *spec;
}

// A Python value for `spec` as the table's number; ValueError (the core's wording) when it is not one.
double numberOf(const OptionSpec& spec, const py::handle& value) {
  const std::string got = py::repr(value);
  switch (spec.type) {
    case OptionType::kBool:
      if (!py::isinstance<py::bool_>(value)) throw py::value_error(offload_planner::optionProblem(spec, got));
      return value.cast<bool>() ? 1.0 : 0.0;
    case OptionType::kAlgorithm: {
      if (!py::isinstance<py::str>(value)) throw py::value_error(offload_planner::optionProblem(spec, got));
      offload_planner::Algorithm algorithm;
      const std::string problem = offload_planner::algorithmOf(value.cast<std::string>(), &algorithm);
      if (!problem.empty()) throw py::value_error(problem);
      return static_cast<double>(static_cast<int>(algorithm));
    }
    case OptionType::kInt:
    case OptionType::kReal:
      break;
  }
  // Numbers only (int, float, numpy scalars): not text that float() would parse, not a bool.
  if (py::isinstance<py::str>(value) || py::isinstance<py::bytes>(value) || py::isinstance<py::bool_>(value)) {
    throw py::value_error(offload_planner::optionProblem(spec, got));
  }
  try {
    return value.cast<double>();
  } catch (const py::cast_error&) {
    throw py::value_error(offload_planner::optionProblem(spec, got));
  }
}

}  // namespace

void defineOptions(py::module_& m) {
  py::tuple names(offload_planner::kAlgorithmCount);
  for (int k = 0; k < offload_planner::kAlgorithmCount; ++k) names[k] = py::str(offload_planner::kAlgorithmNames[k]);
  m.attr("ALGORITHM_NAMES") = names;   // an algorithm's code (the enum, the wire protocol's byte) is its index

  m.def(
      "options_table",
      [names]() {
        py::list rows;
        for (const OptionSpec& spec : offload_planner::optionsTable()) {
          py::dict row;
          row["name"] = spec.name;
          row["type"] = typeName(spec.type);
          row["scope"] = spec.scope == OptionScope::kCells ? "cells" : "metres";
          row["node_parameter"] = spec.node_parameter;
          row["default"] = pythonValue(spec, spec.default_value);
          row["min"] = spec.min;
          row["max"] = spec.max;
          row["min_open"] = spec.min_open;
          row["rule"] = offload_planner::optionRule(spec);
          row["unit"] = spec.unit;
          row["meaning"] = spec.meaning;
          row["in_cells"] = spec.in_cells ? py::object(py::str(spec.in_cells)) : py::object(py::none());
          row["resolution_power"] = spec.resolution_power;
          row["choices"] = spec.type == OptionType::kAlgorithm ? py::object(names) : py::object(py::none());
          rows.append(row);
        }
        return rows;
      },
      "The core's planner options, one dict a row (name, type, scope 'cells' or 'metres', node_parameter, "
      "default, min, max, min_open, rule, unit, meaning, in_cells and resolution_power for a metre "
      "parameter, choices for the algorithm), plan options first, in the order they are checked.");

  m.def(
      "validate_options",
      [](const py::kwargs& values) {
        PlannerParameters parameters;
        for (const auto& item : values) {
          const OptionSpec& spec = rowOf(item.first.cast<std::string>());
          const double number = numberOf(spec, item.second);
          const std::string problem = offload_planner::optionProblem(spec, number);
          if (!problem.empty()) throw py::value_error(problem);
          spec.set(parameters, number);
        }
        // Each value is acceptable alone; the rule between two of them (jps needs cost_factor 0) remains.
        const std::string pair = offload_planner::optionsProblem(parameters.options);
        if (!pair.empty()) throw py::value_error(pair);
        py::dict out;
        for (const OptionSpec& spec : offload_planner::optionsTable()) {
          out[spec.name] = pythonValue(spec, spec.get(parameters));
        }
        return out;
      },
      "Checks planner options and node parameters given by their table names (e.g. lethal_threshold=50, "
      "algorithm='astar', robot_radius=0.2): ValueError with the core's reason for a refused value, TypeError "
      "for a name that is no option. Returns every option of the table, the defaults filled in.");

  m.def(
      "options_in_cells",
      [](double resolution, const py::kwargs& metres) {
        PlannerParameters parameters;
        for (const auto& item : metres) {
          const OptionSpec& spec = rowOf(item.first.cast<std::string>());
          if (spec.scope != OptionScope::kMetres) {
            throw py::type_error(std::string(spec.name) + " is not a parameter in metres");
          }
          spec.set(parameters, numberOf(spec, item.second));
        }
        const std::string problem =
            offload_planner::optionsInCells(resolution, parameters.inflation, &parameters.options);
        if (!problem.empty()) throw py::value_error(problem);
        py::dict out;
        for (const OptionSpec& spec : offload_planner::optionsTable()) {
          if (spec.scope != OptionScope::kMetres) continue;
          const OptionSpec& cells = rowOf(spec.in_cells);
          out[cells.name] = cells.get(parameters);
        }
        return out;
      },
      py::arg("resolution"),
      "The cell options (robot_radius_cells, inflation_radius_cells, inflation_decay) of the metre parameters "
      "(robot_radius, inflation_radius, cost_scaling_factor; the defaults for those not given) on a map of "
      "`resolution` m per cell, as the planner node converts them. Values are converted, not checked: "
      "validate_options checks them.");
}
