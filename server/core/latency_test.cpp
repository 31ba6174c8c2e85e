#include "server/core/latency.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <random>
#include <vector>

namespace stereomap::core {
namespace {

TEST(LatencyHistogram, QuantilesAreUpperBoundsWithinABucket) {
  LatencyHistogram lag;
  EXPECT_EQ(lag.quantile(0.5), 0.0);
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> ms(1, 100);
  std::vector<double> all;
  for (int i = 0; i < 10000; ++i) {
    all.push_back(ms(rng) / 1000);
    lag.add(all.back());
  }
  std::sort(all.begin(), all.end());
  for (const double q : {0.5, 0.95, 0.99}) {
    const double truth = all[static_cast<size_t>(q * all.size()) - 1];
    EXPECT_GE(lag.quantile(q), truth) << q;
    EXPECT_LE(lag.quantile(q), truth * 1.1) << q;
  }
  EXPECT_EQ(lag.count(), 10000u);
  EXPECT_DOUBLE_EQ(lag.quantile(1.0), all.back());
}

TEST(LatencyHistogram, MergesAndTakesOddValues) {
  LatencyHistogram a, b;
  a.add(0.001);
  b.add(0.2);
  b.add(-1);   // a clock stepping back: no lag
  b.add(1e6);  // beyond the last bucket: the longest lag
  a.merge(b);
  EXPECT_EQ(a.count(), 4u);
  EXPECT_EQ(a.quantile(0.25), 1e-4);  // the negative one, at the first edge
  EXPECT_NEAR(a.quantile(0.75), 0.2, 0.2 * 0.1);
  EXPECT_EQ(a.quantile(1.0), 1e6);
}

}  // namespace
}  // namespace stereomap::core
