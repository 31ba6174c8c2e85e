#include "tests/support/sim_map_accuracy.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <set>
#include <tuple>
#include <vector>

#include "common/statistics.hpp"
#include "onboard/sim/sim_source.hpp"
#include "tests/support/seen_voxels.hpp"

namespace stereomap::testing {

using common::Vec3;
using fusion::Occupancy;
using fusion::OccupancyMap;

SimMapAccuracy measureSimMap(const SimMapSetup& setup) {
  sim::SimSourceOptions source_options{
      .seed = setup.room, .rate_hz = 10.0, .max_frames = static_cast<uint64_t>(setup.frames)};
  source_options.render.camera = setup.camera;
  sim::SimSource source(source_options);
  const auto& scene = source.scene();
  const camera::StereoCamera& camera = source.camera();
  const double resolution = setup.map.resolution;
  const double seen_range = setup.seen_range_m;
  OccupancyMap map(setup.map);
  // The vehicle is told the map's resolution, and its depth range follows (rig_range.hpp).
  stereo::DepthOptions depth_options = setup.depth;
  if (depth_options.range) depth_options.range->map_resolution_m = resolution;
  stereo::DepthStep depth(camera, depth_options);
  const double max_range = depth.maxRange();
  std::vector<common::Rigid3> poses;
  std::vector<double> depth_ms;
  while (auto frame = source.next()) {
    const auto T_map_camera = *frame->T_map_body * *frame->T_body_camera;
    const auto start = std::chrono::steady_clock::now();
    auto cloud = depth.compute(frame->left, frame->right, T_map_camera);
    depth_ms.push_back(
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
            .count());
    poses.push_back(T_map_camera);
    if (setup.send && !setup.send(cloud, T_map_camera, frame->stamp_ns)) continue;
    // As the onboard client sends it: rays as long as the farthest point (corners exceed z).
    map.insertCloud(cloud, T_map_camera,
                    stereo::farthestPoint(cloud, static_cast<float>(max_range)) * 1.001);
  }

  SimMapAccuracy result;
  result.noise_sigma = depth.noiseSigma();
  result.level = depth.level();
  result.depth_ms = common::median(std::move(depth_ms)).value_or(0.0);
  const auto occupied = map.occupiedVoxels();
  const double half_diagonal = resolution * std::sqrt(3.0) / 2;
  size_t correct = 0, within_1 = 0, within_2 = 0;
  for (const auto& v : occupied) {
    const double distance = scene.distanceToSurface(map.voxelCentre(v));
    correct += distance <= half_diagonal;
    within_1 += distance <= half_diagonal + resolution;
    within_2 += distance <= half_diagonal + 2 * resolution;
  }

  std::set<VoxelKey> occupied_keys;
  for (const auto& v : occupied) occupied_keys.insert({v.x, v.y, v.z});
  const sim::Renderer renderer(scene, camera);
  const auto seen =
      seenSurfaceVoxels(renderer, camera, poses, resolution, seen_range, /*in_both_images=*/true);
  result.recall = coverageOf(seen, occupied_keys);
  // Free space: samples along every 16th pixel's true ray, up to two voxels before the surface.
  size_t free_correct = 0;
  for (const auto& T_map_camera : poses) {
    const cv::Mat depth = renderer.renderDepth(T_map_camera);
    for (int v = 0; v < depth.rows; v += 16) {
      for (int u = 0; u < depth.cols; u += 16) {
        const float z = depth.at<float>(v, u);
        if (z <= 0 || z > seen_range || u < camera.disparityFromDepth(z)) continue;
        const Vec3 ray = camera.rayThrough(u, v);
        const double length = ray.norm() * z;
        for (double s = resolution; s < length - 2 * resolution; s += resolution) {
          ++result.free_samples;
          free_correct += map.query(T_map_camera * (ray * (s / ray.norm()))) == Occupancy::kFree;
        }
      }
    }
  }
  result.occupied = occupied.size();
  result.seen = seen.size();
  if (result.occupied > 0) {
    result.precision = static_cast<double>(correct) / result.occupied;
    result.precision_1 = static_cast<double>(within_1) / result.occupied;
    result.precision_2 = static_cast<double>(within_2) / result.occupied;
  }
  if (result.free_samples > 0)
    result.free_space = static_cast<double>(free_correct) / result.free_samples;
  return result;
}

}  // namespace stereomap::testing
