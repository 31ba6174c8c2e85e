#include "server/align/map_diff.hpp"

#include <octomap/OcTree.h>
#include <array>
#include <cmath>
#include <cstdio>

#include <set>
#include <sstream>

namespace stereomap::align {

namespace {

using common::Vec3;
using fusion::Occupancy;
using fusion::OccupancyMap;

// Occupied at p or one voxel from it along an axis: two grids never line up exactly, so a
// surface seen by both may sit one voxel apart.
bool occupiedNear(const OccupancyMap& map, const Vec3& p) {
  if (map.query(p) == Occupancy::kOccupied) return true;
  const double v = map.resolution();
  for (int axis = 0; axis < 3; ++axis) {
    for (const double step : {-v, v}) {
      Vec3 q = p;
      q[axis] += step;
      if (map.query(q) == Occupancy::kOccupied) return true;
    }
  }
  return false;
}

// Keeps the changes that have another within one voxel (26 neighbours): a lone voxel is the
// noise of two flights' ray casting at grazing angles, a real change is an object.
void dropLoneVoxels(std::vector<Vec3>& points, double v) {
  const auto key = [v](const Vec3& p) {
    return std::array<int64_t, 3>{std::llround(std::floor(p.x() / v)),
                                  std::llround(std::floor(p.y() / v)),
                                  std::llround(std::floor(p.z() / v))};
  };
  std::set<std::array<int64_t, 3>> cells;
  for (const auto& p : points) cells.insert(key(p));
  std::erase_if(points, [&](const Vec3& p) {
    const auto k = key(p);
    for (int dx = -1; dx <= 1; ++dx) {
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dz = -1; dz <= 1; ++dz) {
          if ((dx || dy || dz) && cells.count({k[0] + dx, k[1] + dy, k[2] + dz})) return false;
        }
      }
    }
    return true;
  });
}

}  // namespace

MapDiff diffMaps(const OccupancyMap& a, const OccupancyMap& b, const common::Rigid3& T_a_b) {
  MapDiff diff;
  const common::Rigid3 T_b_a = T_a_b.inverse();
  for (const auto& voxel : b.occupiedVoxels()) {
    const Vec3 p = T_a_b * b.voxelCentre(voxel);
    if (occupiedNear(a, p)) {
      ++diff.unchanged_b;
    } else if (a.query(p) == Occupancy::kFree) {
      diff.appeared.push_back(p);
    } else {
      ++diff.unseen_by_a;
    }
  }
  for (const auto& voxel : a.occupiedVoxels()) {
    const Vec3 p = a.voxelCentre(voxel);
    const Vec3 q = T_b_a * p;
    if (occupiedNear(b, q)) {
      diff.unchanged.push_back(p);
    } else if (b.query(q) == Occupancy::kFree) {
      diff.disappeared.push_back(p);
    } else {
      ++diff.unseen_by_b;
    }
  }
  dropLoneVoxels(diff.appeared, b.resolution());
  dropLoneVoxels(diff.disappeared, a.resolution());
  return diff;
}

std::string diffPly(const MapDiff& diff) {
  std::string out =
      "ply\nformat ascii 1.0\ncomment stereomap diff: green appeared, red "
      "disappeared\nelement vertex " +
      std::to_string(diff.appeared.size() + diff.disappeared.size()) +
      "\nproperty float x\nproperty float y\nproperty float z\nproperty uchar "
      "red\nproperty uchar green\nproperty uchar blue\nend_header\n";
  char line[96];
  for (const auto* points : {&diff.appeared, &diff.disappeared}) {
    const bool appeared = points == &diff.appeared;
    for (const auto& p : *points) {
      std::snprintf(line, sizeof(line), "%.4f %.4f %.4f %s\n", p.x(), p.y(), p.z(),
                    appeared ? "40 200 60" : "220 40 40");
      out += line;
    }
  }
  return out;
}

std::string diffOctomap(const MapDiff& diff, double resolution) {
  octomap::OcTree tree(resolution);
  // Written from the least to the most changed: where two classes meet in one voxel (B's
  // voxels snap onto A's grid), the change wins.
  const std::pair<const std::vector<Vec3>*, double> classes[] = {
      {&diff.unchanged, kDiffUnchangedP},
      {&diff.disappeared, kDiffDisappearedP},
      {&diff.appeared, kDiffAppearedP}};
  for (const auto& [points, p] : classes) {
    const float log_odds = octomap::logodds(p);
    for (const auto& v : *points) {
      tree.setNodeValue(octomap::point3d(static_cast<float>(v.x()), static_cast<float>(v.y()),
                                         static_cast<float>(v.z())),
                        log_odds, /*lazy_eval=*/true);
    }
  }
  tree.updateInnerOccupancy();
  std::ostringstream out;
  tree.write(out);
  return out.str();
}

std::string diffLine(const std::string& a, const std::string& b, const MapDiff& diff) {
  char text[320];
  std::snprintf(text, sizeof(text),
                "diff %s %s: %zu appeared, %zu disappeared, %zu unchanged; %zu not seen by %s, "
                "%zu not seen by %s",
                a.c_str(), b.c_str(), diff.appeared.size(), diff.disappeared.size(),
                diff.unchanged.size(), diff.unseen_by_a, a.c_str(), diff.unseen_by_b, b.c_str());
  return text;
}

}  // namespace stereomap::align
