#include <gtest/gtest.h>

#include <random>

#include "onboard/landing/pad_detector.hpp"
#include "onboard/landing/pad_pose.hpp"
#include "onboard/sim/deck.hpp"

namespace stereomap::landing {
namespace {

using common::Quat;
using common::Rigid3;
using common::Vec3;

std::array<cv::Point2d, 8> project(const Rigid3& T_camera_pad, const camera::StereoCamera& camera,
                                   double shift = 0.0) {
  std::array<cv::Point2d, 8> out;
  for (int k = 0; k < 8; ++k) {
    Vec3 p = T_camera_pad * padModel()[k];
    p.x() -= shift;
    const auto uv = *camera.project(p);
    out[k] = {uv.x(), uv.y()};
  }
  return out;
}

Rigid3 randomView(std::mt19937& rng, double distance) {
  std::uniform_real_distribution<double> tilt(-0.3, 0.3), spin(-M_PI, M_PI), lateral(-2, 2);
  const Quat q = Quat(Eigen::AngleAxisd(spin(rng), Vec3::UnitZ())) *
                 Quat(Eigen::AngleAxisd(tilt(rng), Vec3::UnitX())) *
                 Quat(Eigen::AngleAxisd(tilt(rng), Vec3::UnitY()));
  // The pad's centre ahead of the camera at `distance`.
  const Vec3 centre(lateral(rng), lateral(rng), distance);
  return {q, centre - q * Vec3(1.5, 2.0, 0.0)};
}

// Without noise the patent's linear solution and the default solve are exact.
TEST(PadPose, BothModesAreExactOnNoiseFreeCorners) {
  std::mt19937 rng(3);
  const camera::StereoCamera camera;
  for (int trial = 0; trial < 50; ++trial) {
    const Rigid3 truth = randomView(rng, 8 + trial * 0.4);
    const auto left = project(truth, camera);
    const auto right = project(truth, camera, camera.baseline);
    const auto linear = patentLinearPose(left, camera);
    ASSERT_TRUE(linear) << trial;
    EXPECT_LT(linear->rotation.angularDistance(truth.rotation), 1e-6) << trial;
    EXPECT_LT((linear->translation - truth.translation).norm(), 1e-6) << trial;
    for (const PoseMode mode : {PoseMode::kDefault, PoseMode::kPatent}) {
      const PadPose pose = estimatePadPose(left, right, camera, {.mode = mode});
      ASSERT_TRUE(pose) << pose.reason;
      EXPECT_LT(pose.T_camera_pad.rotation.angularDistance(truth.rotation), 1e-6) << trial;
      EXPECT_LT((pose.T_camera_pad.translation - truth.translation).norm(), 1e-5) << trial;
    }
  }
}

// Corners that are not the pad's (two swapped) give a pose whose reprojection error is large:
// refused, in both modes.
TEST(PadPose, CornersThatAreNotThePadsAreRefused) {
  std::mt19937 rng(4);
  const camera::StereoCamera camera;
  auto left = project(randomView(rng, 10), camera);
  std::swap(left[1], left[5]);
  for (const PoseMode mode : {PoseMode::kDefault, PoseMode::kPatent}) {
    const PadPose pose = estimatePadPose(left, std::nullopt, camera, {.mode = mode});
    EXPECT_FALSE(pose);
    EXPECT_FALSE(pose.reason.empty());
  }
}

// The corners are named by the T's structure whatever the pad's rotation in the image; the
// patent's rule (smallest y first) gets an upright pad right and an upside-down one wrong.
TEST(PadCorners, NamedByStructureAtAnyRotation) {
  std::mt19937 rng(5);
  const camera::StereoCamera camera;
  for (int trial = 0; trial < 40; ++trial) {
    const auto truth = project(randomView(rng, 12), camera);
    std::vector<cv::Point2d> polygon(truth.begin(), truth.end());
    std::rotate(polygon.begin(), polygon.begin() + trial % 8, polygon.end());
    const auto named = orderTCorners(polygon);
    ASSERT_TRUE(named);
    for (int k = 0; k < 8; ++k) EXPECT_LT(cv::norm((*named)[k] - truth[k]), 1e-9) << trial;
  }
  const Rigid3 upright{Quat::Identity(), Vec3(-1.5, -2.0, 10.0)};
  const auto seen = project(upright, camera);
  std::vector<cv::Point2d> polygon(seen.begin(), seen.end());
  std::rotate(polygon.begin(), polygon.begin() + 3, polygon.end());
  EXPECT_LT(cv::norm(patentOrder(polygon)[0] - seen[0]), 1e-9);
  const Rigid3 upside_down{Quat(Eigen::AngleAxisd(M_PI, Vec3::UnitZ())), Vec3(1.5, 2.0, 10.0)};
  const auto turned = project(upside_down, camera);
  std::vector<cv::Point2d> turned_polygon(turned.begin(), turned.end());
  EXPECT_GT(cv::norm(patentOrder(turned_polygon)[0] - turned[0]), 10.0);
  ASSERT_TRUE(orderTCorners(turned_polygon));
  EXPECT_LT(cv::norm((*orderTCorners(turned_polygon))[0] - turned[0]), 1e-9);
}

// Rendered frames of the descent: the pad is found, its corners land near their true
// projections, and a frame of the deck without the pad finds nothing, with a reason.
TEST(PadDetector, FindsThePadOnRenderedDeckFramesAndNothingWithoutIt) {
  for (const double start : {4.0, 25.0, 40.0}) {
    sim::DeckSource source({.max_frames = 1, .start_s = start});
    const auto frame = source.next();
    ASSERT_TRUE(frame);
    const auto found = detectPad(frame->left);
    ASSERT_TRUE(found) << "at " << source.truth().distance_m << " m: " << found.reason;
    double worst = 0;
    for (int k = 0; k < 8; ++k) {
      const auto uv = *source.camera().project(source.truth().T_camera_pad * padModel()[k]);
      worst = std::max(worst, std::hypot(found.corners[k].x - uv.x(), found.corners[k].y - uv.y()));
    }
    std::printf("at %.1f m: worst corner %.3f px, shape error %.4f, contrast %.0f\n",
                source.truth().distance_m, worst, found.shape_error, found.contrast);
    EXPECT_LT(worst, 1.0) << "at " << source.truth().distance_m << " m";
  }
}

}  // namespace
}  // namespace stereomap::landing
