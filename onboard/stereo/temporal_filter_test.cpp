#include "onboard/stereo/temporal_filter.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

namespace stereomap::stereo {
namespace {

using common::Rigid3;
using common::Vec3;

const camera::StereoCamera kCamera;

// The block grid of a plane n . p = 1 (camera frame) seen from the camera, plus noise.
BlockDisparity planeBlocks(const Vec3& n, double noise_px = 0, std::mt19937* random = nullptr) {
  BlockDisparity blocks{
      .disparity = cv::Mat(kCamera.height / 2, kCamera.width / 5, CV_32FC1),
      .intensity = cv::Mat(kCamera.height / 2, kCamera.width / 5, CV_8UC1, cv::Scalar(128)),
      .block_cols = 5,
      .block_rows = 2};
  std::normal_distribution<double> gauss(0.0, noise_px);
  for (int by = 0; by < blocks.disparity.rows; ++by) {
    for (int bx = 0; bx < blocks.disparity.cols; ++bx) {
      const double z = 1.0 / n.dot(kCamera.rayThrough(blocks.uCentre(bx), blocks.vCentre(by)));
      double d = z > 0 ? kCamera.disparityFromDepth(z) : -1;
      if (random != nullptr && d > 0) d += gauss(*random);
      blocks.disparity.at<float>(by, bx) = static_cast<float>(d);
    }
  }
  return blocks;
}

int pointsOf(const BlockDisparity& blocks) { return cv::countNonZero(blocks.disparity > 0); }

TEST(TemporalFilter, ABlockSeenOnceGivesNoPointAndSeenAgainIsConfirmed) {
  TemporalFilter filter(kCamera, {.min_frames = 2, .max_frames = 8, .gate_px = 1.0});
  const Vec3 wall(0, 0, 1.0 / 3.0);  // z = 3 m
  auto first = planeBlocks(wall);
  filter.apply(first, Rigid3::identity());
  EXPECT_EQ(pointsOf(first), 0);
  auto second = planeBlocks(wall);
  filter.apply(second, Rigid3::identity());
  EXPECT_EQ(pointsOf(second), second.disparity.rows * second.disparity.cols);
  // A measurement that disagrees by more than the gate starts afresh: no point.
  auto moved = planeBlocks(Vec3(0, 0, 1.0 / 2.0));
  filter.apply(moved, Rigid3::identity());
  EXPECT_EQ(pointsOf(moved), 0);
}

TEST(TemporalFilter, NoiseIsAveragedOverFrames) {
  std::mt19937 random(7);
  TemporalFilter filter(kCamera, {.min_frames = 2, .max_frames = 8, .gate_px = 1.0});
  const Vec3 wall(0, 0, 1.0 / 5.0);  // 5 m: 11.8 px
  const double truth = kCamera.disparityFromDepth(5.0);
  double squares = 0;
  int count = 0;
  for (int frame = 0; frame < 8; ++frame) {
    auto blocks = planeBlocks(wall, 0.2, &random);
    filter.apply(blocks, Rigid3::identity());
    if (frame < 7) continue;
    for (int by = 0; by < blocks.disparity.rows; ++by) {
      for (int bx = 0; bx < blocks.disparity.cols; ++bx) {
        const float d = blocks.disparity.at<float>(by, bx);
        if (d <= 0) continue;
        squares += (d - truth) * (d - truth);
        ++count;
      }
    }
  }
  ASSERT_GT(count, 0.95 * 240 * 128);  // nearly every block within the 5-sigma gate
  // Eight frames of 0.2 px noise average to 0.2 / sqrt(8) = 0.071 px.
  EXPECT_LT(std::sqrt(squares / count), 0.08);
}

TEST(TemporalFilter, AveragedBlocksReachFartherTheMoreFramesTheyAverage) {
  // One frame's far limit at 20 px: a wall at 13.5 px (2/3 of it) needs a mean of n frames
  // with n^(1/4) >= 20 / 13.5, n >= 4.8: its points come from the fifth frame on.
  TemporalFilter filter(kCamera, {.min_frames = 2, .max_frames = 8, .far_disparity_px = 20});
  const double z = kCamera.depthFromDisparity(13.5);
  for (int frame = 1; frame <= 6; ++frame) {
    auto blocks = planeBlocks(Vec3(0, 0, 1.0 / z));
    filter.apply(blocks, Rigid3::identity());
    EXPECT_EQ(pointsOf(blocks) > 0, frame >= 5) << "frame " << frame;
  }
}

TEST(TemporalFilter, NearBlocksAgreeWithinAVoxelOfDepth) {
  // At 0.5 m (118 px) a pose error of 1 % moves the disparity by more than the 1 px gate, and
  // the depth by 5 mm: within a 0.1 m voxel it is the same surface.
  TemporalFilter pixels(kCamera, {.min_frames = 2, .gate_px = 1.0});
  TemporalFilter voxel(kCamera, {.min_frames = 2, .gate_px = 1.0, .gate_depth_m = 0.1});
  for (TemporalFilter* filter : {&pixels, &voxel}) {
    auto first = planeBlocks(Vec3(0, 0, 1.0 / 0.5));
    filter->apply(first, Rigid3::identity());
    auto second = planeBlocks(Vec3(0, 0, 1.0 / 0.505));
    filter->apply(second, Rigid3::identity());
    EXPECT_EQ(pointsOf(second) > 0, filter == &voxel);
  }
}

TEST(TemporalFilter, CarriedDepthFollowsTheCameraOverASlantedPlane) {
  TemporalFilter filter(kCamera, {.min_frames = 2, .max_frames = 8, .gate_px = 1.0});
  // A floor-like plane, steep in the image (disparity changes by 0.05 px per pixel), seen
  // from two poses 8 cm apart and turned by 1 degree: the second frame's blocks must hold the
  // plane's exact disparity, so the carried values were moved to the blocks' centres.
  const Vec3 plane_world = Vec3(0.4, 0.3, 1.0) / 3.0;
  const Rigid3 T_world_first = Rigid3::identity();
  const Rigid3 T_world_second{common::Quat(Eigen::AngleAxisd(1.0 * M_PI / 180, Vec3::UnitY())),
                              Vec3(0.08, 0.02, 0)};
  auto planeIn = [&](const Rigid3& T_world_camera) {
    // n_c . p_c = 1 with p_w = R p_c + t: n_w . (R p_c + t) = 1.
    const Vec3 n = T_world_camera.rotation.inverse() * plane_world /
                   (1.0 - plane_world.dot(T_world_camera.translation));
    return planeBlocks(n);
  };
  auto first = planeIn(T_world_first);
  filter.apply(first, T_world_first);
  auto second = planeIn(T_world_second);
  const cv::Mat exact = second.disparity.clone();
  filter.apply(second, T_world_second);
  double worst = 0;
  int confirmed = 0;
  for (int by = 2; by < exact.rows - 2; ++by) {
    for (int bx = 2; bx < exact.cols - 2; ++bx) {
      const float d = second.disparity.at<float>(by, bx);
      if (d <= 0 || exact.at<float>(by, bx) <= 0) continue;
      ++confirmed;
      worst = std::max(worst, std::abs(static_cast<double>(d - exact.at<float>(by, bx))));
    }
  }
  EXPECT_GT(confirmed, 0.8 * exact.rows * exact.cols);
  EXPECT_LT(worst, 0.005);
}

}  // namespace
}  // namespace stereomap::stereo
