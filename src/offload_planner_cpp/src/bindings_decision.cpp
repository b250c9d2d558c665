// The compiled decision in the pybind11 module (q_network.h): QNetworkForward, built from the learner's numpy
// weights once per model, then q_values(*state) per request, one call through the dispatcher.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <stdexcept>
#include <string>
#include <vector>

#include "offload_planner_cpp/q_network.h"

namespace py = pybind11;
using offload_planner::DenseLayer;
using offload_planner::InputScaling;
using offload_planner::QNetworkForward;

namespace {

using FloatArray = py::array_t<float, py::array::c_style | py::array::forcecast>;

QNetworkForward build(const std::vector<FloatArray>& weights, const std::vector<FloatArray>& biases,
                      std::vector<double> mean, std::vector<double> inverse_scale, std::vector<double> log_floor) {
  if (weights.size() != biases.size())
    throw py::value_error("one bias per weight matrix: got " + std::to_string(weights.size()) + " and " +
                          std::to_string(biases.size()));
  std::vector<DenseLayer> layers;
  for (std::size_t i = 0; i < weights.size(); ++i) {
    const FloatArray& w = weights[i];
    const FloatArray& b = biases[i];
    if (w.ndim() != 2 || b.ndim() != 1)
      throw py::value_error("layer " + std::to_string(i) + ": weights must be 2-D (inputs x outputs), bias 1-D");
    DenseLayer layer;
    layer.inputs = static_cast<std::size_t>(w.shape(0));
    layer.outputs = static_cast<std::size_t>(w.shape(1));
    layer.weights.assign(w.data(), w.data() + w.size());
    layer.bias.assign(b.data(), b.data() + b.size());
    layers.push_back(std::move(layer));
  }
  try {
    return QNetworkForward(std::move(layers),
                           InputScaling{std::move(mean), std::move(inverse_scale), std::move(log_floor)});
  } catch (const std::invalid_argument& error) {
    throw py::value_error(error.what());
  }
}

py::tuple qValues(const QNetworkForward& network, const py::args& state) {
  const std::size_t n = network.inputs();
  if (state.size() != n)
    throw py::type_error("a state has " + std::to_string(n) + " fields, got " + std::to_string(state.size()));
  double raw[64];
  std::vector<double> heap;
  double* x = raw;
  if (n > 64) {
    heap.resize(n);
    x = heap.data();
  }
  for (std::size_t i = 0; i < n; ++i) {
    try {
      x[i] = py::cast<double>(state[i]);
    } catch (const py::cast_error&) {
      throw py::type_error("state field " + std::to_string(i) + " is not a number");
    }
  }
  std::vector<double> q(network.outputs());
  network.qValues(x, q.data());
  py::tuple values(q.size());
  for (std::size_t j = 0; j < q.size(); ++j) values[j] = py::float_(q[j]);
  return values;
}

}  // namespace

void defineDecision(py::module_& m) {
  py::class_<QNetworkForward>(m, "QNetworkForward",
                              "A ReLU Q-network's forward pass for one raw state (q_network.h): each field scaled "
                              "(log(max(x, 0) + log_floor) where log_floor > 0, then (x - mean) * inverse_scale), "
                              "ReLU hidden layers, a linear last layer.")
      .def(py::init(&build), py::arg("weights"), py::arg("biases"), py::arg("mean"), py::arg("inverse_scale"),
           py::arg("log_floor"),
           "weights: (inputs x outputs) float32 matrices, first layer first; biases: one vector per layer; "
           "mean, inverse_scale, log_floor: one value per input. ValueError when they do not fit together.")
      .def_property_readonly("inputs", &QNetworkForward::inputs)
      .def_property_readonly("outputs", &QNetworkForward::outputs)
      .def("q_values", &qValues, "The Q-values (a tuple, one per action) of one raw state given field by field; "
                                 "TypeError when the count of fields is not `inputs`.");
}
