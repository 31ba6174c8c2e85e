#include "onboard/stereo/depth.hpp"

#include <gtest/gtest.h>

#include "onboard/sim/flight.hpp"
#include "onboard/sim/renderer.hpp"

namespace stereomap::stereo {
namespace {

using common::Vec3;

const camera::StereoCamera kCamera;

// True disparity from true depth, quantised to the matchers' 1/16 px steps.
cv::Mat quantisedTrueDisparity(const cv::Mat& depth) {
  cv::Mat disparity(depth.size(), CV_32FC1, cv::Scalar(0));
  for (int v = 0; v < depth.rows; ++v) {
    for (int u = 0; u < depth.cols; ++u) {
      const float z = depth.at<float>(v, u);
      if (z > 0) {
        disparity.at<float>(v, u) = std::round(kCamera.disparityFromDepth(z) * 16.0) / 16.0f;
      }
    }
  }
  return disparity;
}

// Depth error bound of half a 1/16 px disparity step at depth z (eq. 4 of the mapping paper).
double quantisationBound(double z) { return z * z / (kCamera.fx * kCamera.baseline) / 32.0; }

TEST(CloudFromDisparity, EveryPointLiesOnTheRenderedGeometryWithinQuantisation) {
  const sim::Scene room = sim::Scene::makeRoom({.seed = 2});
  const sim::Renderer renderer(room, kCamera);
  const sim::Flight flight;
  const auto frame = renderer.render(flight.T_map_camera(5.0));
  const cv::Mat disparity = quantisedTrueDisparity(frame.depth);

  const auto cloud =
      cloudFromDisparity(disparity, frame.left, kCamera, {.block_cols = 1, .block_rows = 1});
  ASSERT_GT(cloud.size(), 50000u);
  size_t checked = 0;
  // Points come out row-major over valid pixels: walk them in the same order.
  size_t i = 0;
  for (int v = 0; v < kCamera.height; ++v) {
    for (int u = 0; u < kCamera.width; ++u) {
      const float d = disparity.at<float>(v, u);
      const double z_true = frame.depth.at<float>(v, u);
      if (d <= 0 || z_true > 6.0 || z_true < 0.3) continue;
      ASSERT_LT(i, cloud.size());
      const Vec3 p = cloud.points[i++].cast<double>();
      const Vec3 truth = kCamera.rayThrough(u, v) * z_true;
      const double bound = quantisationBound(z_true) * kCamera.rayThrough(u, v).norm();
      ASSERT_LE((p - truth).norm(), bound * 1.01 + 1e-5) << "pixel " << u << "," << v;
      ++checked;
    }
  }
  EXPECT_EQ(checked, cloud.size());
}

TEST(CloudFromDisparity, BlocksOfFiveByTwoOnAPlaneGiveOnePointEach) {
  const double z = 2.5;
  const cv::Mat disparity(kCamera.height, kCamera.width, CV_32FC1,
                          cv::Scalar(kCamera.disparityFromDepth(z)));
  const cv::Mat left(kCamera.height, kCamera.width, CV_8UC1, cv::Scalar(77));
  const auto cloud = cloudFromDisparity(disparity, left, kCamera);
  EXPECT_EQ(cloud.size(), static_cast<size_t>(128 * 240));
  ASSERT_EQ(cloud.intensity.size(), cloud.size());
  for (size_t i = 0; i < cloud.size(); ++i) {
    ASSERT_NEAR(cloud.points[i].z(), z, 1e-5);
    ASSERT_EQ(cloud.intensity[i], 77);
  }
}

TEST(CloudFromDisparity, InvalidAndOutOfRangeDisparitiesNeverBecomePoints) {
  cv::Mat disparity(kCamera.height, kCamera.width, CV_32FC1, cv::Scalar(-1));
  const cv::Mat left(disparity.size(), CV_8UC1, cv::Scalar(0));
  EXPECT_EQ(cloudFromDisparity(disparity, left, kCamera).size(), 0u);
  disparity.setTo(kCamera.disparityFromDepth(7.0));  // beyond max_range_m = 6
  EXPECT_EQ(cloudFromDisparity(disparity, left, kCamera).size(), 0u);
  disparity.setTo(kCamera.disparityFromDepth(5.0));
  EXPECT_GT(cloudFromDisparity(disparity, left, kCamera).size(), 0u);
}

// Measured on sim seed 2, t = 5 s (docs/BENCHMARKS.md): within 1 px BM 0.991, SGBM 0.992;
// density BM 0.931, SGBM 0.995. Thresholds sit a little below the measurement.
TEST(StereoMatcher, MatchersRecoverTheSimDisparity) {
  const sim::Scene room = sim::Scene::makeRoom({.seed = 2});
  const sim::Renderer renderer(room, kCamera);
  const auto frame = renderer.render(sim::Flight().T_map_camera(5.0));
  struct Expected {
    MatcherKind kind;
    double min_accuracy, min_density;
  };
  for (const auto& expected : {Expected{MatcherKind::kBlockMatching, 0.97, 0.88},
                               Expected{MatcherKind::kSemiGlobal, 0.97, 0.95}}) {
    const StereoMatcher matcher({.kind = expected.kind});
    const cv::Mat disparity = matcher.compute(frame.left, frame.right);
    size_t valid = 0, good = 0, surface = 0;
    for (int v = 0; v < kCamera.height; ++v) {
      for (int u = 100; u < kCamera.width; ++u) {  // left columns have no match in BM
        const float z = frame.depth.at<float>(v, u);
        if (z <= 0 || z > 6.0) continue;
        ++surface;
        const float d = disparity.at<float>(v, u);
        if (d <= 0) continue;
        ++valid;
        good += std::abs(d - kCamera.disparityFromDepth(z)) <= 1.0;
      }
    }
    const double accuracy = static_cast<double>(good) / valid;
    const double density = static_cast<double>(valid) / surface;
    std::printf("matcher %d: within 1 px %.3f, density %.3f\n", static_cast<int>(expected.kind),
                accuracy, density);
    EXPECT_GE(accuracy, expected.min_accuracy);
    EXPECT_GE(density, expected.min_density);
  }
}

}  // namespace
}  // namespace stereomap::stereo
