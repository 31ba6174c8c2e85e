// The pose graph on the odometry's keyframes (issue 18): the sim's looping flight, three
// loops with image noise, flown with loop closures against without.
#include <gtest/gtest.h>

#include "onboard/eval/metrics.hpp"
#include "onboard/eval/odometry_run.hpp"
#include "onboard/sim/sim_source.hpp"
#include "tests/support/sim_flights.hpp"

namespace stereomap::eval {
namespace {

double pathLength(const common::Trajectory& trajectory) {
  double length = 0;
  for (size_t i = 1; i < trajectory.size(); ++i) {
    length += (trajectory[i].pose.translation - trajectory[i - 1].pose.translation).norm();
  }
  return length;
}

TEST(OdometryGraph, LoopClosuresHalveTheErrorOfAThreeLoopFlight) {
  auto options = testing::noisyFlight(1);
  options.max_frames = 1200;  // 3 loops of 40 s
  sim::SimSource source(options);
  const auto run = runOdometryWithGraph(source, {});
  ASSERT_EQ(run.optimised.size(), run.estimate.size());
  const auto before = absoluteError(run.truth, run.estimate, Alignment::kSe3);
  const auto after = absoluteError(run.truth, run.optimised, Alignment::kSe3);
  const double path = pathLength(run.truth);
  const double end_error =
      (run.optimised.back().pose.translation - run.truth.back().pose.translation).norm();
  std::printf(
      "3 loops, %.1f m: %d keyframes, %d loop closures; ATE %.4f -> %.4f m; end error "
      "%.4f m (%.3f %% of the path); longest solve %.1f ms\n",
      path, run.keyframes, run.loops, before.translation.rmse, after.translation.rmse, end_error,
      100 * end_error / path, run.solve_ms_max);
  EXPECT_GT(run.loops, 20);
  EXPECT_LE(after.translation.rmse, 0.5 * before.translation.rmse);  // the issue
  EXPECT_LE(end_error, 0.002 * path);                                // the issue
}

}  // namespace
}  // namespace stereomap::eval
