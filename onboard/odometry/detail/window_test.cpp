// The odometry's sliding window: which frames and landmarks it keeps, which landmarks it
// adjusts, and that adjusting moves a perturbed newest pose back onto its observations.
#include "onboard/odometry/detail/window.hpp"

#include <gtest/gtest.h>

namespace stereomap::odometry::detail {
namespace {

const camera::StereoCamera kCamera;

common::Rigid3 poseAt(int frame) {
  return {common::Quat(Eigen::AngleAxisd(0.02 * frame, Eigen::Vector3d::UnitY())),
          common::Vec3(0.03 * frame, 0.0, 0.2 * frame)};
}

// Points 2-8 m ahead on a grid; landmark id = index.
std::vector<common::Vec3> points() {
  std::vector<common::Vec3> p;
  for (int i = 0; i < 60; ++i) {
    const int column = i % 10, row = i / 10;  // a grid of 10 columns
    p.emplace_back(-1.5 + 0.3 * column, -0.5 + 0.2 * row, 2.0 + 0.1 * i);
  }
  return p;
}

// Adds frame `frame` at `T_world_camera` seeing landmarks [first, last) exactly.
void addFrame(SlidingWindow& window, int frame, const common::Rigid3& T_world_camera, int first,
              int last, const std::vector<common::Vec3>& world) {
  window.addFrame(frame, T_world_camera);
  const common::Rigid3 truth_inverse = poseAt(frame).inverse();
  for (int i = first; i < last; ++i) {
    const common::Vec3 c = truth_inverse * world[static_cast<size_t>(i)];
    const Eigen::Vector2d left(kCamera.fx * c.x() / c.z() + kCamera.cx,
                               kCamera.fy * c.y() / c.z() + kCamera.cy);
    const Eigen::Vector2d right(kCamera.fx * (c.x() - kCamera.baseline) / c.z() + kCamera.cx,
                                left.y());
    window.observe({i, left, right}, world[static_cast<size_t>(i)]);
  }
}

TEST(SlidingWindow, KeepsTheLastFramesAndForgetsLandmarksNoFrameSees) {
  const auto world = points();
  SlidingWindow window(kCamera, 3);
  addFrame(window, 1, poseAt(1), 0, 10, world);  // landmarks 0-9 only here
  for (int f = 2; f <= 4; ++f) addFrame(window, f, poseAt(f), 10, 60, world);
  EXPECT_FALSE(window.pose(1).has_value());
  ASSERT_TRUE(window.pose(4).has_value());
  double offset = 0;
  ASSERT_TRUE(window.adjust(5, 1.0, offset, 0.0));
  EXPECT_FALSE(window.adjustedLandmark(5).has_value());
  EXPECT_TRUE(window.adjustedLandmark(20).has_value());
}

TEST(SlidingWindow, AdjustsOnlyLandmarksSeenTwiceAndPullsThePoseBack) {
  const auto world = points();
  SlidingWindow window(kCamera, 5);
  addFrame(window, 1, poseAt(1), 0, 50, world);
  common::Rigid3 off = poseAt(2);
  off.translation += common::Vec3(0.02, -0.01, 0.03);
  off.rotation = off.rotation * common::Quat(Eigen::AngleAxisd(0.01, Eigen::Vector3d::UnitX()));
  addFrame(window, 2, off, 0, 40, world);
  double offset = 0;
  ASSERT_TRUE(window.adjust(10, 1.0, offset, 0.0));
  EXPECT_TRUE(window.adjustedLandmark(10).has_value());
  EXPECT_FALSE(window.adjustedLandmark(45).has_value());  // seen by frame 1 only
  const common::Rigid3 error = poseAt(2).inverse() * *window.pose(2);
  EXPECT_LT(error.translation.norm(), 1e-4);
  EXPECT_LT(error.rotation.angularDistance(common::Quat::Identity()), 1e-5);
  EXPECT_EQ(offset, 0.0);
}

TEST(SlidingWindow, NothingToAdjustWithOneFrame) {
  const auto world = points();
  SlidingWindow window(kCamera, 5);
  addFrame(window, 1, poseAt(1), 0, 50, world);
  double offset = 0;
  EXPECT_FALSE(window.adjust(5, 1.0, offset, 0.1));
  EXPECT_FALSE(window.adjustedLandmark(3).has_value());
}

}  // namespace
}  // namespace stereomap::odometry::detail
