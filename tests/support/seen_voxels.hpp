// The true surface voxels a simulated flight's camera saw, as both map scorers count them
// (map_score.hpp across processes, sim_map_accuracy in process): every second pixel of each
// pose's rendered depth up to max_depth, the voxel its surface point falls in, and, when the
// point lies on a voxel face (the rooms' walls are grid-aligned), the voxel on the other side
// too: such a surface passes through both, as precision counts them, so either one occupied
// covers it (which of the two the point falls in is floating-point rounding).
#pragma once

#include <cmath>
#include <map>
#include <set>
#include <tuple>
#include <vector>

#include "common/geometry.hpp"
#include "onboard/sim/renderer.hpp"

namespace stereomap::testing {

using VoxelKey = std::tuple<int, int, int>;

inline VoxelKey voxelKeyOf(const common::Vec3& p, double resolution) {
  return VoxelKey{static_cast<int>(std::floor(p.x() / resolution)),
                  static_cast<int>(std::floor(p.y() / resolution)),
                  static_cast<int>(std::floor(p.z() / resolution))};
}

// Seen voxel -> the voxels sharing a face the surface point was on. in_both_images: only
// pixels the right camera sees as well (u >= disparity).
inline std::map<VoxelKey, std::set<VoxelKey>> seenSurfaceVoxels(
    const sim::Renderer& renderer, const camera::StereoCamera& camera,
    const std::vector<common::Rigid3>& T_map_cameras, double resolution, double max_depth,
    bool in_both_images) {
  std::map<VoxelKey, std::set<VoxelKey>> seen;
  for (const auto& T_map_camera : T_map_cameras) {
    const cv::Mat depth = renderer.renderDepth(T_map_camera);
    for (int v = 0; v < depth.rows; v += 2) {
      for (int u = 0; u < depth.cols; u += 2) {
        const float z = depth.at<float>(v, u);
        if (z <= 0 || z > max_depth) continue;
        if (in_both_images && u < camera.disparityFromDepth(z)) continue;
        const common::Vec3 point = T_map_camera * (camera.rayThrough(u, v) * z);
        const VoxelKey key = voxelKeyOf(point, resolution);
        auto& sides = seen[key];
        for (int axis = 0; axis < 3; ++axis) {
          for (const double nudge : {-1e-6, 1e-6}) {
            common::Vec3 moved = point;
            moved[axis] += nudge;
            const VoxelKey other = voxelKeyOf(moved, resolution);
            if (other != key) sides.insert(other);
          }
        }
      }
    }
  }
  return seen;
}

// Share of the seen voxels covered by `occupied` (the voxel or one across its face).
inline double coverageOf(const std::map<VoxelKey, std::set<VoxelKey>>& seen,
                         const std::set<VoxelKey>& occupied) {
  if (seen.empty()) return 0;
  size_t covered = 0;
  for (const auto& [key, sides] : seen) {
    bool hit = occupied.count(key) > 0;
    for (const auto& side : sides) hit = hit || occupied.count(side) > 0;
    covered += hit;
  }
  return static_cast<double>(covered) / static_cast<double>(seen.size());
}

}  // namespace stereomap::testing
