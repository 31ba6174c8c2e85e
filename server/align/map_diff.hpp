// What changed between two flights of one place, once aligned: occupied voxels that appeared
// (the first flight saw free space there) and disappeared (the second saw free space where
// the first had them). Unknown is not free: a voxel one flight did not observe is counted as
// unseen, never as a change. A lone changed voxel (no other change beside it) is dropped as
// the noise of ray casting at grazing angles.
#pragma once

#include <string>
#include <vector>

#include "common/geometry.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace stereomap::align {

struct MapDiff {
  std::vector<common::Vec3> appeared;     // B's voxel centres (in A's frame), A saw free there
  std::vector<common::Vec3> disappeared;  // A's voxel centres, B saw free there
  std::vector<common::Vec3> unchanged;    // A's voxel centres occupied in both (within a voxel)
  size_t unchanged_b = 0;                 // B's voxels occupied in both
  size_t unseen_by_a = 0;                 // B's occupied voxels A never observed
  size_t unseen_by_b = 0;                 // A's occupied voxels B never observed
};

// A is the earlier flight, B the later one; T_a_b puts B's frame into A's. Same resolution.
MapDiff diffMaps(const fusion::OccupancyMap& a, const fusion::OccupancyMap& b,
                 const common::Rigid3& T_a_b);

// ASCII PLY of the changes in A's frame: appeared green, disappeared red.
std::string diffPly(const MapDiff& diff);

// The diff as one map a session can hold (OctoMap's full format, .ot, in A's frame at A's
// resolution): its three classes told apart by occupancy probability, all occupied under
// either sensor model the server uses. Tiles carry round(255 P) (proto/tiles/FORMAT.md), and
// the viewer's "change" colour mode reads the bands: appeared >= 240, disappeared 200-239,
// unchanged below. At coarser tile levels a cell takes its most changed voxel's value.
inline constexpr double kDiffAppearedP = 0.971;    // OctoMap's clamp: 248
inline constexpr double kDiffDisappearedP = 0.85;  // 217
inline constexpr double kDiffUnchangedP = 0.72;    // 184
std::string diffOctomap(const MapDiff& diff, double resolution);

// "diff A B: N appeared, M disappeared, U unchanged; K not seen by A, L not seen by B"
std::string diffLine(const std::string& a, const std::string& b, const MapDiff& diff);

}  // namespace stereomap::align
