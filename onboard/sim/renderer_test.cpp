#include "onboard/sim/renderer.hpp"

#include <gtest/gtest.h>

#include "onboard/sim/flight.hpp"

namespace stereomap::sim {
namespace {

using common::Rigid3;
using common::Vec3;

// A wall facing the camera (OpenCV frame: z forward) at depth `z`, much wider than the view.
Scene wallAt(double z) { return Scene({{Vec3(-100, -100, z), Vec3(100, 100, z + 1)}}); }

TEST(Renderer, DepthOfAFrontoParallelPlaneIsExact) {
  const Scene scene = wallAt(3.0);
  const Renderer renderer(scene, camera::StereoCamera{});
  const StereoFrame frame = renderer.render(Rigid3::identity());
  ASSERT_EQ(frame.depth.size(), cv::Size(640, 480));
  double lo, hi;
  cv::minMaxLoc(frame.depth, &lo, &hi);
  EXPECT_EQ(lo, 3.0);
  EXPECT_EQ(hi, 3.0);
}

TEST(Renderer, DepthOfATiltedPlaneMatchesTheRayIntersection) {
  // Floor 1.5 m below a camera looking along the horizon: depth = 1.5 * fy / (v - cy).
  const Scene scene({{Vec3(-50, 1.5, -50), Vec3(50, 2.5, 50)}});
  const camera::StereoCamera camera;
  const Renderer renderer(scene, camera);
  const cv::Mat depth = renderer.renderDepth(Rigid3::identity());
  for (int v : {300, 400, 479}) {  // nearer than max_depth
    const double expected = 1.5 * camera.fy / (v - camera.cy);
    EXPECT_NEAR(depth.at<float>(v, 100), expected, 1e-5 * expected) << "row " << v;
  }
  EXPECT_EQ(depth.at<float>(100, 100), 0.0f);  // above the horizon: no surface
}

TEST(Renderer, RightImageIsTheLeftShiftedByTheTrueDisparity) {
  const camera::StereoCamera camera;
  const int disparity = 20;
  const Scene scene = wallAt(camera.depthFromDisparity(disparity));
  const Renderer renderer(scene, camera);
  const StereoFrame frame = renderer.render(Rigid3::identity());
  int worst = 0;
  for (int v = 0; v < camera.height; v += 7) {
    for (int u = disparity; u < camera.width; u += 3) {
      worst = std::max(worst, std::abs(frame.left.at<uint8_t>(v, u) -
                                       frame.right.at<uint8_t>(v, u - disparity)));
    }
  }
  EXPECT_LE(worst, 1);
  // The texture has contrast for the matcher to use.
  cv::Scalar mean, stddev;
  cv::meanStdDev(frame.left, mean, stddev);
  EXPECT_GT(stddev[0], 15.0);
}

TEST(Renderer, IsDeterministicForASeed) {
  const Scene a = Scene::makeRoom({.seed = 4});
  const Scene b = Scene::makeRoom({.seed = 4});
  const Scene c = Scene::makeRoom({.seed = 5});
  const Flight flight;
  const Renderer ra(a, {}), rb(b, {}), rc(c, {});
  const auto pose = flight.T_map_camera(3.0);
  EXPECT_EQ(cv::norm(ra.render(pose).left, rb.render(pose).left, cv::NORM_INF), 0.0);
  EXPECT_GT(cv::norm(ra.render(pose).left, rc.render(pose).left, cv::NORM_L1), 0.0);
}

TEST(Flight, StaysInsideTheRoomAndClearOfObstacles) {
  for (uint32_t seed : {1u, 2u, 3u}) {
    const Scene room = Scene::makeRoom({.seed = seed});
    EXPECT_GE(room.boxes().size(), 10u) << "seed " << seed;  // 5 walls/floor + obstacles
    const Flight flight;
    for (double t = 0; t < flight.options().period_s; t += 0.25) {
      const Vec3 p = flight.T_map_body(t).translation;
      EXPECT_GT(room.distanceToSurface(p), 0.5) << "seed " << seed << " t " << t;
      EXPECT_TRUE(room.bounds().contains(p));
    }
  }
}

TEST(Flight, CameraLooksForwardAndSlightlyDown) {
  const Flight flight;
  const auto T_map_body = flight.T_map_body(0);
  const Vec3 optical_axis = flight.T_map_camera(0).rotation * Vec3::UnitZ();
  const Vec3 body_forward = T_map_body.rotation * Vec3::UnitX();
  EXPECT_GT(optical_axis.dot(body_forward), 0.95);
  EXPECT_LT(optical_axis.z(), 0.0);
}

}  // namespace
}  // namespace stereomap::sim
