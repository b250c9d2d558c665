// The Q-network's forward pass for one state (q_network.h).
#include "offload_planner_cpp/q_network.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>
#include <utility>

namespace offload_planner {

QNetworkForward::QNetworkForward(std::vector<DenseLayer> layers, InputScaling scaling)
    : layers_(std::move(layers)), scaling_(std::move(scaling)) {
  if (layers_.empty()) throw std::invalid_argument("a Q-network needs at least one layer");
  for (std::size_t i = 0; i < layers_.size(); ++i) {
    const DenseLayer& layer = layers_[i];
    const std::string name = "layer " + std::to_string(i);
    if (layer.inputs == 0 || layer.outputs == 0) throw std::invalid_argument(name + " has no inputs or outputs");
    if (layer.weights.size() != layer.inputs * layer.outputs || layer.bias.size() != layer.outputs)
      throw std::invalid_argument(name + "'s weights or bias do not match its shape");
    if (i > 0 && layer.inputs != layers_[i - 1].outputs)
      throw std::invalid_argument(name + " takes " + std::to_string(layer.inputs) + " inputs, the layer before gives " +
                                  std::to_string(layers_[i - 1].outputs));
    widest_ = std::max({widest_, layer.inputs, layer.outputs});
  }
  const std::size_t n = inputs();
  if (scaling_.mean.size() != n || scaling_.inverse_scale.size() != n || scaling_.log_floor.size() != n)
    throw std::invalid_argument("the input scaling needs one mean, inverse scale and log floor per input (" +
                                std::to_string(n) + ")");
  for (std::size_t i = 0; i < n; ++i)
    if (!std::isfinite(scaling_.mean[i]) || !std::isfinite(scaling_.inverse_scale[i]) ||
        !std::isfinite(scaling_.log_floor[i]) || scaling_.log_floor[i] < 0.0)
      throw std::invalid_argument("input " + std::to_string(i) +
                                  ": the mean and inverse scale must be finite, the log floor finite and >= 0 (0: "
                                  "no log)");
}

// Compiled twice, for AVX2 with FMA and for any x86-64, the loader picking the one this CPU runs: the wide
// instructions take a third off a decision where the robot has them, and a robot without them still runs.
#if defined(__x86_64__) && defined(__GNUC__)
__attribute__((target_clones("avx2,fma", "default")))
#endif
void QNetworkForward::qValues(const double* state, double* q) const {
  // Two buffers of the widest layer: on the stack for any network a robot decides with, no allocation per decision.
  constexpr std::size_t kOnStack = 1024;
  float stack_a[kOnStack], stack_b[kOnStack];
  std::vector<float> heap_a, heap_b;
  float* a = stack_a;
  float* b = stack_b;
  if (widest_ > kOnStack) {
    heap_a.resize(widest_);
    heap_b.resize(widest_);
    a = heap_a.data();
    b = heap_b.data();
  }
  for (std::size_t i = 0; i < inputs(); ++i) {
    double x = state[i];
    if (scaling_.log_floor[i] > 0.0) x = std::log(std::max(x, 0.0) + scaling_.log_floor[i]);
    a[i] = static_cast<float>((x - scaling_.mean[i]) * scaling_.inverse_scale[i]);
  }
  float* in = a;
  float* out = b;
  const std::size_t last = layers_.size() - 1;
  for (std::size_t l = 0; l <= last; ++l) {
    const DenseLayer& layer = layers_[l];
    std::copy(layer.bias.begin(), layer.bias.end(), out);
    for (std::size_t i = 0; i < layer.inputs; ++i) {
      const float x = in[i];
      if (x == 0.0f) continue;  // after a ReLU most inputs are: their rows are not read
      const float* row = layer.weights.data() + i * layer.outputs;
      for (std::size_t j = 0; j < layer.outputs; ++j) out[j] += x * row[j];
    }
    if (l != last)
      for (std::size_t j = 0; j < layer.outputs; ++j) out[j] = std::max(out[j], 0.0f);
    std::swap(in, out);
  }
  for (std::size_t j = 0; j < outputs(); ++j) q[j] = in[j];
}

}  // namespace offload_planner
