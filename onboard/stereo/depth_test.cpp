#include "onboard/stereo/depth.hpp"

#include <gtest/gtest.h>

#include "onboard/sim/flight.hpp"
#include "onboard/sim/renderer.hpp"
#include "onboard/stereo/disparity_io.hpp"
#include "testing/data.hpp"

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
    ASSERT_NEAR(cloud.points[i].z(), z, quantisationBound(z) * 1.01);  // d kept in 1/16 px
    ASSERT_EQ(cloud.intensity[i], 77);
  }
}

TEST(CloudFromDisparity, TheDisparityOffsetCorrectsDepth) {
  // The matcher saw 1 px less than the truth (right image 1 px off): the offset puts it back.
  const double z = 4.0, offset = 1.0;
  const cv::Mat disparity(kCamera.height, kCamera.width, CV_32FC1,
                          cv::Scalar(kCamera.disparityFromDepth(z) - offset));
  const cv::Mat left(kCamera.height, kCamera.width, CV_8UC1, cv::Scalar(77));
  const auto biased = cloudFromDisparity(disparity, left, kCamera);
  const auto corrected =
      cloudFromDisparity(disparity, left, kCamera, {.disparity_offset_px = offset});
  ASSERT_EQ(corrected.size(), static_cast<size_t>(128 * 240));
  EXPECT_GT(biased.points[0].z(), z + 0.2);
  for (const auto& p : corrected.points) ASSERT_NEAR(p.z(), z, quantisationBound(z) * 1.01);
  // A raw invalid disparity stays invalid whatever the offset.
  const cv::Mat invalid(kCamera.height, kCamera.width, CV_32FC1, cv::Scalar(-1));
  EXPECT_EQ(cloudFromDisparity(invalid, left, kCamera, {.disparity_offset_px = 3.0}).size(), 0u);
}

TEST(CloudFromDisparity, SpecklesOfBlocksAreDropped) {
  // A plane at 2.5 m with a 3x3-block island at another depth: the island is a speckle.
  cv::Mat disparity(kCamera.height, kCamera.width, CV_32FC1,
                    cv::Scalar(kCamera.disparityFromDepth(2.5)));
  disparity(cv::Rect(100, 100, 15, 6)).setTo(kCamera.disparityFromDepth(1.5));
  const cv::Mat left(disparity.size(), CV_8UC1, cv::Scalar(0));
  const auto filtered = cloudFromDisparity(disparity, left, kCamera);
  EXPECT_EQ(filtered.size(), static_cast<size_t>(128 * 240 - 9));
  const auto unfiltered = cloudFromDisparity(disparity, left, kCamera, {.speckle_blocks = 0});
  EXPECT_EQ(unfiltered.size(), static_cast<size_t>(128 * 240));
}

TEST(VoxelGrid, KeepsOneCentroidPerVoxel) {
  common::PointCloud cloud;
  cloud.points = {{0.01f, 0.01f, 1.01f}, {0.03f, 0.05f, 1.09f}, {0.25f, 0.0f, 1.0f}};
  cloud.intensity = {10, 30, 200};
  const auto thinned = voxelGridDownsample(cloud, 0.1);
  ASSERT_EQ(thinned.size(), 2u);
  EXPECT_NEAR(thinned.points[0].x(), 0.02f, 1e-6);
  EXPECT_NEAR(thinned.points[0].z(), 1.05f, 1e-6);
  EXPECT_EQ(thinned.intensity[0], 20);
  EXPECT_EQ(thinned.intensity[1], 200);
  // Negative coordinates land in their own voxels (floor, not truncation).
  cloud.points = {{-0.01f, 0, 1}, {0.01f, 0, 1}};
  cloud.intensity.clear();
  EXPECT_EQ(voxelGridDownsample(cloud, 0.1).size(), 2u);
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

// Measured on sim seed 2, t = 5 s (docs/BENCHMARKS.md): within 1 px fast 0.980, with rows in
// pairs 0.982, accurate 0.991; density fast 0.944, in pairs 0.922, accurate 0.994. Thresholds
// sit a little below the measurement.
TEST(StereoMatcher, MatchersRecoverTheSimDisparity) {
  const sim::Scene room = sim::Scene::makeRoom({.seed = 2});
  const sim::Renderer renderer(room, kCamera);
  const auto frame = renderer.render(sim::Flight().T_map_camera(5.0));
  struct Expected {
    const char* name;
    MatcherOptions options;
    double min_accuracy, min_density;
  };
  // The fast preset as the depth step runs it: from the cloud's range on.
  const MatcherOptions fast = fitToRange(MatcherOptions::fast(), kCamera, 6.0);
  MatcherOptions pairs = fast;
  pairs.row_groups = 2;
  for (const auto& expected :
       {Expected{"fast", fast, 0.97, 0.88}, Expected{"fast, rows in pairs", pairs, 0.97, 0.90},
        Expected{"accurate", MatcherOptions::accurate(), 0.97, 0.95}}) {
    const StereoMatcher matcher(expected.options);
    const cv::Mat disparity = matcher.compute(frame.left, frame.right);
    ASSERT_EQ(disparity.size(), frame.left.size());
    size_t valid = 0, good = 0, surface = 0;
    for (int v = 0; v < kCamera.height; ++v) {
      for (int u = 100; u < kCamera.width; ++u) {  // left columns have no match in BM
        const float z = frame.depth.at<float>(v, u);
        if (z <= 0 || z > 6.0) continue;
        ++surface;
        const float d = disparity.at<float>(v, u);
        if (d < 0) continue;
        ++valid;
        good += std::abs(d - kCamera.disparityFromDepth(z)) <= 1.0;
      }
    }
    const double accuracy = static_cast<double>(good) / valid;
    const double density = static_cast<double>(valid) / surface;
    std::printf("%s: within 1 px %.3f, density %.3f\n", expected.name, accuracy, density);
    EXPECT_GE(accuracy, expected.min_accuracy);
    EXPECT_GE(density, expected.min_density);
  }
}

}  // namespace
}  // namespace stereomap::stereo

namespace stereomap::stereo {
namespace {

// Middlebury (GT known, non-occluded): the accurate preset against stock StereoSGBM, whose
// figures the data set's README measures (bad 3.63 / 1.28 / 8.70 / 6.74 %). Ours, measured
// by stereomap-bench-stereo (docs/BENCHMARKS.md): 2.75 / 0.72 / 6.28 / 5.52 % at density
// 98.7 / 99.3 / 96.5 / 95.5 %. Each threshold sits a little above our figure and below
// stock's.
TEST(StereoMatcher, AccurateBeatsStockSgbmOnEveryMiddleburyPair) {
  struct Expected {
    const char* pair;
    double max_bad, stock_bad;
  };
  for (const auto& expected :
       {Expected{"tsukuba", 0.0300, 0.0363}, Expected{"venus", 0.0085, 0.0128},
        Expected{"teddy", 0.0660, 0.0870}, Expected{"aloe", 0.0580, 0.0674}}) {
    const auto dir = testing::kDataDir / "middlebury" / expected.pair;
    STEREOMAP_SKIP_WITHOUT(dir);
    auto pair = loadMiddleburyPair(dir);
    ASSERT_TRUE(pair.ok()) << pair.error().message;
    MatcherOptions options = MatcherOptions::accurate();
    options.num_disparities = disparitiesFor(pair->max_disparity);
    const auto score =
        scoreDisparity(StereoMatcher(options).compute(pair->left, pair->right), *pair);
    std::printf("%s: bad %.2f%%, density %.2f%%\n", expected.pair, 100 * score.bad,
                100 * score.density);
    EXPECT_LT(score.bad, expected.max_bad) << expected.pair;
    EXPECT_LT(score.bad, expected.stock_bad) << expected.pair;
    EXPECT_GE(score.density, 0.95) << expected.pair;  // the issue asks >= 0.85
  }
}

TEST(DisparityIo, PngRoundTripKeepsSubPixelAndInvalid) {
  cv::Mat disparity(4, 5, CV_32FC1, cv::Scalar(12.3125f));
  disparity.at<float>(1, 2) = -1.0f;
  disparity.at<float>(2, 3) = 200.5f;
  const auto path = std::filesystem::temp_directory_path() / "stereomap-disparity-test.png";
  ASSERT_TRUE(writeDisparityPng(path, disparity).ok());
  auto back = readDisparityPng(path);
  ASSERT_TRUE(back.ok()) << back.error().message;
  EXPECT_FLOAT_EQ(back->at<float>(0, 0), 12.3125f);  // multiples of 1/256 survive exactly
  EXPECT_LT(back->at<float>(1, 2), 0.0f);
  EXPECT_FLOAT_EQ(back->at<float>(2, 3), 200.5f);
  std::filesystem::remove(path);
}

TEST(StereoMatcher, GroupedRowsShareTheirGroupsDisparity) {
  const sim::Scene room = sim::Scene::makeRoom({.seed = 2});
  const auto frame = sim::Renderer(room, kCamera).render(sim::Flight().T_map_camera(5.0));
  MatcherOptions options = fitToRange(MatcherOptions::fast(), kCamera, 6.0);
  options.row_groups = 2;
  options.smooth_sigma_px = 1.5;  // along the rows only
  options.ground = false;         // the ground pass gives each row its plane's disparity
  const cv::Mat disparity = StereoMatcher(options).compute(frame.left, frame.right);
  ASSERT_EQ(disparity.size(), frame.left.size());
  for (int v = 0; v < disparity.rows; v += 2) {
    ASSERT_EQ(cv::norm(disparity.row(v), disparity.row(v + 1), cv::NORM_INF), 0.0) << "row " << v;
  }
}

TEST(FitToRange, TheSearchStartsAtTheCloudsRange) {
  // The sim camera: b f = 59.1 px m, so 6 m is 9.85 px and the window of 48 reaches 1.04 m.
  const MatcherOptions fitted = fitToRange(MatcherOptions::fast(), kCamera, 6.0);
  EXPECT_EQ(fitted.min_disparity, 9);
  EXPECT_EQ(fitted.num_disparities, MatcherOptions::fast().num_disparities);
  EXPECT_NEAR(kCamera.depthFromDisparity(fitted.min_disparity + fitted.num_disparities), 1.04,
              0.01);
  // A start already nearer (the paper's rule) is kept.
  MatcherOptions paper = MatcherOptions::fast();
  paper.min_disparity = 20;
  EXPECT_EQ(fitToRange(paper, kCamera, 6.0).min_disparity, 20);
}

TEST(MinimumDisparity, FollowsThePapersRule) {
  // b = 0.09 m, f = 350 px (a 320x240 webcam), r = 0.05 m, dd = 0.5: sqrt(315) = 17.7 -> 18.
  EXPECT_EQ(minimumDisparity(0.09, 350.0, 0.05), 18);
  EXPECT_EQ(disparitiesFor(53), 64);
  EXPECT_EQ(disparitiesFor(64), 64);
}

}  // namespace
}  // namespace stereomap::stereo
