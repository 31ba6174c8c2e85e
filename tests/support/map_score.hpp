// How right a server's map of the simulated room is: its occupied voxels (map.bt, as the
// server exports it) against the room's true surfaces. Shared by the cross-process accuracy
// tests.
//   precision: share of occupied voxels a true surface passes through (within one voxel:
//              precision_1);
//   coverage:  share of the true surface voxels the left camera saw within range that are
//              occupied (a surface on a voxel face: either side; seen_voxels.hpp).
#pragma once

#include <octomap/OcTree.h>

#include <cmath>
#include <optional>
#include <set>
#include <sstream>
#include <string>
#include <tuple>

#include "onboard/sim/sim_source.hpp"
#include "tests/support/seen_voxels.hpp"

namespace stereomap::testing {

struct MapScore {
  size_t occupied = 0, seen = 0;
  double precision = 0, precision_1 = 0, coverage = 0;
};

// The finest voxels a server's map (`bt`, OctoMap's binary) holds occupied; nullopt when it
// does not read. A pruned leaf stands for all the finest voxels inside it.
inline std::optional<std::set<VoxelKey>> occupiedVoxelsOf(const std::string& bt,
                                                          double resolution) {
  std::istringstream in(bt);
  octomap::OcTree map(resolution);
  if (!map.readBinary(in)) return std::nullopt;
  std::set<VoxelKey> occupied;
  for (auto it = map.begin_leafs(); it != map.end_leafs(); ++it) {
    if (!map.isNodeOccupied(*it)) continue;
    const int span = 1 << (16 - it.getDepth());
    const common::Vec3 corner =
        common::Vec3(it.getX(), it.getY(), it.getZ()) - common::Vec3::Constant(it.getSize() / 2);
    for (int dx = 0; dx < span; ++dx) {
      for (int dy = 0; dy < span; ++dy) {
        for (int dz = 0; dz < span; ++dz) {
          occupied.insert(voxelKeyOf(
              corner + (common::Vec3(dx, dy, dz) + common::Vec3::Constant(0.5)) * resolution,
              resolution));
        }
      }
    }
  }
  return occupied;
}

// `bt`: the map's OctoMap binary; `truth`: the room and flight the vehicle flew (its first
// `frames` frames at 10 Hz); `max_range`: the onboard cloud range.
inline MapScore scoreMap(const std::string& bt, double resolution, const sim::SimSource& truth,
                         int frames, double max_range) {
  MapScore score;
  const auto read = occupiedVoxelsOf(bt, resolution);
  if (!read) return score;
  const std::set<VoxelKey>& occupied = *read;
  const auto& scene = truth.scene();
  const double half_diagonal = resolution * std::sqrt(3.0) / 2.0;
  size_t correct = 0, within_one_voxel = 0;
  for (const auto& [x, y, z] : occupied) {
    const common::Vec3 centre((x + 0.5) * resolution, (y + 0.5) * resolution,
                              (z + 0.5) * resolution);
    const double distance = scene.distanceToSurface(centre);
    correct += distance <= half_diagonal;
    within_one_voxel += distance <= half_diagonal + resolution;
  }
  std::vector<common::Rigid3> poses;
  for (int i = 0; i < frames; ++i) poses.push_back(truth.flight().T_map_camera(i / 10.0));
  const auto seen = seenSurfaceVoxels(sim::Renderer(scene, truth.camera()), truth.camera(), poses,
                                      resolution, max_range, /*in_both_images=*/false);
  score.coverage = coverageOf(seen, occupied);
  score.occupied = occupied.size();
  score.seen = seen.size();
  if (!occupied.empty()) {
    score.precision = static_cast<double>(correct) / static_cast<double>(occupied.size());
    score.precision_1 =
        static_cast<double>(within_one_voxel) / static_cast<double>(occupied.size());
  }
  return score;
}

}  // namespace stereomap::testing
