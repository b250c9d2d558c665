// The robot's offloading decision compiled: the forward pass of a ReLU Q-network for one state (no ROS).
// The learner (Python) trains the network with torch and hands its weights here, so that a decision on the cold
// caches a robot's request meets is one call: numpy's dispatch, a few calls a layer, cost it ~150 us there
// against the ~3 ms plans of a small map (BENCHMARKS.md, "The decision compiled").
#pragma once

#include <cstddef>
#include <vector>

namespace offload_planner {

// One fully connected layer: out = in * weights + bias.
struct DenseLayer {
  std::size_t inputs = 0;
  std::size_t outputs = 0;
  std::vector<float> weights;  // inputs x outputs, row-major: row i holds input i's weight to every output
  std::vector<float> bias;     // outputs
};

// How a raw state becomes the network's input, field by field: log(max(x, 0) + log_floor) where log_floor > 0
// (the fields the learner's normalisation sees on a log scale), then (x - mean) * inverse_scale.
struct InputScaling {
  std::vector<double> mean;
  std::vector<double> inverse_scale;
  std::vector<double> log_floor;  // 0: the field as it is; never negative
};

// Hidden layers are ReLU, the last is linear (the Q-values, one per action).
class QNetworkForward {
 public:
  // Throws std::invalid_argument when there is no layer, the layers do not chain, a layer's arrays do not match
  // its shape, or the scaling's three vectors are not one finite value per input (a log floor >= 0).
  QNetworkForward(std::vector<DenseLayer> layers, InputScaling scaling);

  std::size_t inputs() const { return layers_.front().inputs; }
  std::size_t outputs() const { return layers_.back().outputs; }

  // The Q-values of one raw state: `state` holds inputs() values, `q` receives outputs() values.
  void qValues(const double* state, double* q) const;

 private:
  std::vector<DenseLayer> layers_;
  InputScaling scaling_;
  std::size_t widest_ = 0;
};

}  // namespace offload_planner
