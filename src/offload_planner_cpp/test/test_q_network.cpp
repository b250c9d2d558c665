// The compiled decision's forward pass (q_network.h) against Q-values worked out by hand.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <stdexcept>
#include <vector>

#include "offload_planner_cpp/q_network.h"

using offload_planner::DenseLayer;
using offload_planner::InputScaling;
using offload_planner::QNetworkForward;

namespace {

DenseLayer layer(std::size_t inputs, std::size_t outputs, std::vector<float> weights, std::vector<float> bias) {
  DenseLayer l;
  l.inputs = inputs;
  l.outputs = outputs;
  l.weights = std::move(weights);
  l.bias = std::move(bias);
  return l;
}

// 2 inputs -> 3 ReLU units -> 2 Q-values.
QNetworkForward small(InputScaling scaling = {{0.0, 0.0}, {1.0, 1.0}, {0.0, 0.0}}) {
  std::vector<DenseLayer> layers;
  // hidden = relu([x0, x1] * [[1, -1, 2], [3, 1, -1]] + [0.5, 0, -1])
  layers.push_back(layer(2, 3, {1, -1, 2, 3, 1, -1}, {0.5f, 0.0f, -1.0f}));
  // q = hidden * [[1, 0], [2, 1], [-1, 4]] + [0.25, -0.5]
  layers.push_back(layer(3, 2, {1, 0, 2, 1, -1, 4}, {0.25f, -0.5f}));
  return QNetworkForward(std::move(layers), std::move(scaling));
}

std::vector<double> q(const QNetworkForward& network, std::vector<double> state) {
  std::vector<double> values(network.outputs());
  network.qValues(state.data(), values.data());
  return values;
}

}  // namespace

TEST(QNetworkForward, HiddenUnitsAndBiasesByHand) {
  const QNetworkForward network = small();
  EXPECT_EQ(network.inputs(), 2u);
  EXPECT_EQ(network.outputs(), 2u);
  // x = (1, 2): pre-activations (7.5, 1, -1) -> hidden (7.5, 1, 0) -> q (9.75, 0.5)
  std::vector<double> v = q(network, {1.0, 2.0});
  EXPECT_DOUBLE_EQ(v[0], 9.75);
  EXPECT_DOUBLE_EQ(v[1], 0.5);
  // x = (2, -1): pre-activations (-0.5, -3, 4) -> hidden (0, 0, 4): the ReLU cut two units -> q (-3.75, 15.5)
  v = q(network, {2.0, -1.0});
  EXPECT_DOUBLE_EQ(v[0], -3.75);
  EXPECT_DOUBLE_EQ(v[1], 15.5);
  // x = (0, 0): only the biases: hidden (0.5, 0, 0) -> q (0.75, -0.5)
  v = q(network, {0.0, 0.0});
  EXPECT_DOUBLE_EQ(v[0], 0.75);
  EXPECT_DOUBLE_EQ(v[1], -0.5);
}

TEST(QNetworkForward, ScalesEachFieldAndTakesLogsWhereAsked) {
  // field 0: log(max(x, 0) + 1), then (.. - 0) * 1; field 1: (x - 4) * 0.5
  const QNetworkForward network = small({{0.0, 4.0}, {1.0, 0.5}, {1.0, 0.0}});
  const std::vector<double> direct = q(small(), {1.0, 2.0});
  std::vector<double> v = q(network, {std::exp(1.0) - 1.0, 8.0});  // -> (1, 2)
  EXPECT_NEAR(v[0], direct[0], 1e-5);
  EXPECT_NEAR(v[1], direct[1], 1e-5);
  v = q(network, {-5.0, 4.0});  // a negative input on the log scale counts as 0: log(1) = 0 -> (0, 0)
  EXPECT_DOUBLE_EQ(v[0], 0.75);
  EXPECT_DOUBLE_EQ(v[1], -0.5);
}

TEST(QNetworkForward, RefusesLayersThatDoNotChainAndScalingOfTheWrongWidth) {
  std::vector<DenseLayer> broken;
  broken.push_back(layer(2, 3, std::vector<float>(6), std::vector<float>(3)));
  broken.push_back(layer(4, 2, std::vector<float>(8), std::vector<float>(2)));
  EXPECT_THROW(QNetworkForward(broken, {{0, 0}, {1, 1}, {0, 0}}), std::invalid_argument);
  std::vector<DenseLayer> short_weights;
  short_weights.push_back(layer(2, 3, std::vector<float>(5), std::vector<float>(3)));
  EXPECT_THROW(QNetworkForward(short_weights, {{0, 0}, {1, 1}, {0, 0}}), std::invalid_argument);
  std::vector<DenseLayer> one;
  one.push_back(layer(2, 2, std::vector<float>(4), std::vector<float>(2)));
  EXPECT_THROW(QNetworkForward(one, {{0, 0, 0}, {1, 1, 1}, {0, 0, 0}}), std::invalid_argument);
  EXPECT_THROW(QNetworkForward({}, {}), std::invalid_argument);
}

TEST(QNetworkForward, RefusesScalingThatIsNotFiniteOrANegativeLogFloor) {
  auto two = [] {
    std::vector<DenseLayer> layers;
    layers.push_back(layer(2, 2, std::vector<float>(4), std::vector<float>(2)));
    return layers;
  };
  const double inf = std::numeric_limits<double>::infinity();
  EXPECT_NO_THROW(QNetworkForward(two(), {{0, 0}, {1, 1}, {0, 0.5}}));
  EXPECT_THROW(QNetworkForward(two(), {{0, 0}, {1, 1}, {0, -1}}), std::invalid_argument);
  EXPECT_THROW(QNetworkForward(two(), {{0, std::nan("")}, {1, 1}, {0, 0}}), std::invalid_argument);
  EXPECT_THROW(QNetworkForward(two(), {{0, 0}, {inf, 1}, {0, 0}}), std::invalid_argument);
  EXPECT_THROW(QNetworkForward(two(), {{0, 0}, {1, 1}, {inf, 0}}), std::invalid_argument);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
