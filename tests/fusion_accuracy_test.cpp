// Fusion accuracy on the simulator at 0.05 m (issue 5): the fast stereo preset's clouds of
// scripted flights through three seeded rooms, fused with the fast insertion, compared with
// the rooms' exact geometry. Figures are reported in docs/BENCHMARKS.md.
#include <gtest/gtest.h>

#include <map>
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
constexpr double kMaxRange = 6.0;  // depth (z) limit of the clouds
constexpr int kFrames = 60;

struct Accuracy {
  double precision = 0, recall = 0, free_space = 0;
  size_t occupied = 0, seen = 0, free_samples = 0;
};

Accuracy measure(uint32_t seed) {
  sim::SimSource source({.seed = seed, .rate_hz = 10.0, .max_frames = kFrames});
  const auto& scene = source.scene();
  const camera::StereoCamera& camera = source.camera();
  const stereo::StereoMatcher matcher(stereo::MatcherOptions::fast());
  OccupancyMap map({.resolution = kResolution});
  std::vector<common::Rigid3> poses;
  while (auto frame = source.next()) {
    const auto T_map_camera = *frame->T_map_body * *frame->T_body_camera;
    const auto cloud = stereo::cloudFromDisparity(matcher.compute(frame->left, frame->right),
                                                  frame->left, camera, {.max_range_m = kMaxRange});
    // As the onboard client sends it: rays as long as the farthest point (corners exceed z).
    map.insertCloud(cloud, T_map_camera, stereo::farthestPoint(cloud, kMaxRange) * 1.001);
    poses.push_back(T_map_camera);
  }
  EXPECT_EQ(poses.size(), static_cast<size_t>(kFrames));

  // Precision: a true surface passes through the occupied voxel.
  Accuracy result;
  const auto occupied = map.occupiedVoxels();
  const double half_diagonal = kResolution * std::sqrt(3.0) / 2;
  size_t correct = 0;
  for (const auto& v : occupied)
    correct += scene.distanceToSurface(map.voxelCentre(v)) <= half_diagonal;

  // Recall: the voxels of the true surface points that the stereo camera saw (in both images,
  // depth within range) that are occupied. A point on a voxel face (the rooms' floors and
  // walls lie on the grid) belongs to the voxels on both sides, as precision counts them.
  // Free space: points on the true rays, at least two voxels before the surface, free.
  using Key = std::tuple<int, int, int>;
  auto keyOf = [](const Vec3& p) {
    return Key{static_cast<int>(std::floor(p.x() / kResolution)),
               static_cast<int>(std::floor(p.y() / kResolution)),
               static_cast<int>(std::floor(p.z() / kResolution))};
  };
  std::set<Key> occupied_keys;
  for (const auto& v : occupied) occupied_keys.insert({v.x, v.y, v.z});
  const sim::Renderer renderer(scene, camera);
  std::map<Key, std::set<Key>> seen;  // voxel -> the voxels sharing a face the point is on
  size_t free_correct = 0;
  for (const auto& T_map_camera : poses) {
    const cv::Mat depth = renderer.renderDepth(T_map_camera);
    for (int v = 0; v < depth.rows; v += 2) {
      for (int u = 0; u < depth.cols; u += 2) {
        const float z = depth.at<float>(v, u);
        if (z <= 0 || z > kMaxRange || u < camera.disparityFromDepth(z)) continue;
        const Vec3 ray = camera.rayThrough(u, v);
        const Vec3 point = T_map_camera * (ray * z);
        auto& sides = seen[keyOf(point)];
        for (int axis = 0; axis < 3; ++axis) {
          for (const double nudge : {-1e-6, 1e-6}) {
            Vec3 moved = point;
            moved[axis] += nudge;
            if (keyOf(moved) != keyOf(point)) sides.insert(keyOf(moved));
          }
        }
        if (u % 16 != 0 || v % 16 != 0) continue;
        const double length = ray.norm() * z;
        for (double s = kResolution; s < length - 2 * kResolution; s += kResolution) {
          ++result.free_samples;
          free_correct += map.query(T_map_camera * (ray * (s / ray.norm()))) == Occupancy::kFree;
        }
      }
    }
  }
  size_t recalled = 0;
  for (const auto& [key, sides] : seen) {
    bool hit = occupied_keys.count(key) > 0;
    for (const auto& side : sides) hit = hit || occupied_keys.count(side) > 0;
    recalled += hit;
  }
  result.occupied = occupied.size();
  result.seen = seen.size();
  result.precision = static_cast<double>(correct) / result.occupied;
  result.recall = static_cast<double>(recalled) / result.seen;
  result.free_space = static_cast<double>(free_correct) / result.free_samples;
  std::printf(
      "room %u, fusion accuracy at %.2f m: precision %.4f (%zu voxels), recall %.4f (%zu seen), "
      "free space %.4f (%zu samples)\n",
      seed, kResolution, result.precision, result.occupied, result.recall, result.seen,
      result.free_space, result.free_samples);
  return result;
}

class FusionAccuracy : public ::testing::TestWithParam<uint32_t> {};

TEST_P(FusionAccuracy, SimFlightAtFiveCentimetres) {
  const Accuracy a = measure(GetParam());
  RecordProperty("precision", std::to_string(a.precision));
  RecordProperty("recall", std::to_string(a.recall));
  RecordProperty("free_space", std::to_string(a.free_space));
  // Measured on rooms 1-3: precision 0.965-0.969, recall 0.943-0.954, free space 0.997
  // (docs/BENCHMARKS.md). The issue asks >= 0.95, >= 0.90 and >= 0.95.
  EXPECT_GE(a.precision, 0.95);
  EXPECT_GE(a.recall, 0.93);
  EXPECT_GE(a.free_space, 0.99);
}

INSTANTIATE_TEST_SUITE_P(Rooms, FusionAccuracy, ::testing::Values(1u, 2u, 3u));

}  // namespace
}  // namespace stereomap::testing
