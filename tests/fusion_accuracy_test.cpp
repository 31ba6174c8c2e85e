// Fusion accuracy on the simulator at 0.05 m (issue 5): the fast stereo preset's clouds of a
// scripted flight fused with the fast insertion, compared with the room's exact geometry.
// Figures are reported in docs/BENCHMARKS.md.
#include <gtest/gtest.h>

#include <set>

#include "onboard/sim/sim_source.hpp"
#include "onboard/stereo/depth.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace stereomap::testing {
namespace {

using common::Vec3;
using fusion::Occupancy;
using fusion::OccupancyMap;

constexpr double kResolution = 0.05;
constexpr double kMaxRange = 6.0;
constexpr int kFrames = 60;

TEST(FusionAccuracy, SimFlightAtFiveCentimetres) {
  sim::SimSource source({.seed = 1, .rate_hz = 10.0, .max_frames = kFrames});
  const auto& scene = source.scene();
  const camera::StereoCamera& camera = source.camera();
  const stereo::StereoMatcher matcher(stereo::MatcherOptions::fast());
  OccupancyMap map({.resolution = kResolution});
  std::vector<common::Rigid3> poses;
  while (auto frame = source.next()) {
    const auto T_map_camera = *frame->T_map_body * *frame->T_body_camera;
    const auto cloud = stereo::cloudFromDisparity(matcher.compute(frame->left, frame->right),
                                                  frame->left, camera, {.max_range_m = kMaxRange});
    map.insertCloud(cloud, T_map_camera, kMaxRange);
    poses.push_back(T_map_camera);
  }
  ASSERT_EQ(poses.size(), static_cast<size_t>(kFrames));

  // Precision: a true surface passes through the occupied voxel.
  const auto occupied = map.occupiedVoxels();
  const double half_diagonal = kResolution * std::sqrt(3.0) / 2;
  size_t correct = 0;
  for (const auto& v : occupied)
    correct += scene.distanceToSurface(map.voxelCentre(v)) <= half_diagonal;

  // Recall: the true surface voxels the camera saw (within range), occupied in the map; and
  // free space: voxels on the true rays, at least two voxels before the surface, free.
  using Key = std::tuple<int, int, int>;
  auto keyOf = [](const Vec3& p) {
    return Key{static_cast<int>(std::floor(p.x() / kResolution)),
               static_cast<int>(std::floor(p.y() / kResolution)),
               static_cast<int>(std::floor(p.z() / kResolution))};
  };
  const std::set<Key> occupied_keys = [&] {
    std::set<Key> keys;
    for (const auto& v : occupied) keys.insert({v.x, v.y, v.z});
    return keys;
  }();
  const sim::Renderer renderer(scene, camera);
  std::set<Key> seen;
  size_t free_checked = 0, free_correct = 0;
  for (const auto& T_map_camera : poses) {
    const cv::Mat depth = renderer.renderDepth(T_map_camera);
    for (int v = 0; v < depth.rows; v += 2) {
      for (int u = 0; u < depth.cols; u += 2) {
        const float z = depth.at<float>(v, u);
        if (z <= 0 || z > kMaxRange) continue;
        const Vec3 ray = camera.rayThrough(u, v);
        seen.insert(keyOf(T_map_camera * (ray * z)));
        if (u % 16 != 0 || v % 16 != 0) continue;
        const double length = ray.norm() * z;
        for (double s = kResolution; s < length - 2 * kResolution; s += kResolution) {
          ++free_checked;
          free_correct += map.query(T_map_camera * (ray * (s / ray.norm()))) == Occupancy::kFree;
        }
      }
    }
  }
  size_t recalled = 0;
  for (const auto& key : seen) recalled += occupied_keys.count(key);

  const double precision = static_cast<double>(correct) / occupied.size();
  const double recall = static_cast<double>(recalled) / seen.size();
  const double free_space = static_cast<double>(free_correct) / free_checked;
  std::printf(
      "fusion accuracy at %.2f m: precision %.4f (%zu voxels), recall %.4f (%zu seen), "
      "free space %.4f (%zu samples)\n",
      kResolution, precision, occupied.size(), recall, seen.size(), free_space, free_checked);
  RecordProperty("precision", std::to_string(precision));
  RecordProperty("recall", std::to_string(recall));
  RecordProperty("free_space", std::to_string(free_space));
  // Measured 0.9415 / 0.8113 / 0.9872 (docs/BENCHMARKS.md). The issue asks precision >= 0.95
  // and recall >= 0.90 at 0.05 m: not reached yet (stereo depth noise at 0.12 m baseline is
  // several 5 cm voxels at 6 m). These bars guard what we have; raise them as it improves.
  EXPECT_GE(precision, 0.93);
  EXPECT_GE(recall, 0.80);
  EXPECT_GE(free_space, 0.98);  // the issue asks >= 0.95
}

}  // namespace
}  // namespace stereomap::testing
