// Dense rasters of one map's space, for the alignment's millions of lookups: where a k-d tree
// search or an octree walk costs about a microsecond, a raster's costs a few nanoseconds. They
// answer exactly what the tree and the octree would (tests/align_test.cpp checks it).
//
//   const CellRaster cells(codes_at_depth, depth, map.cellSize(depth));
//   if (cells.near(p, 1.5 * edge)) ...   // an occupied cell's centre within reach of p
//   const ClassRaster space(map, margin_m);
//   if (space.at(p) == fusion::Occupancy::kFree) ...   // map.query(p), cached
#pragma once

#include <cstddef>
#include <cstdint>
#include <unordered_set>
#include <vector>

#include "common/geometry.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace stereomap::align {

// A map's occupied cells at one depth of the octree (16: the finest voxels).
class CellRaster {
 public:
  // `codes`: the cells' Morton codes at `depth` (a voxel's code shifted right by 3 bits per
  // level up), any order; `edge`: the cell's edge in metres. Above kMaxDenseCells cells of
  // bounding box, a hash set stands in for the dense raster (slower, as exact).
  CellRaster(const std::vector<uint64_t>& codes, unsigned depth, double edge);
  static constexpr size_t kMaxDenseCells = size_t{1} << 27;

  // Squared distance from p to the nearest occupied cell's centre if it is within `reach`
  // (at most 1.5 edges), else a negative value.
  double nearest2(const common::Vec3& p, double reach) const;
  // Whether an occupied cell's centre is within `reach` (at most 1.5 edges) of p.
  bool near(const common::Vec3& p, double reach) const;
  double edge() const { return edge_; }

 private:
  bool occupied(int64_t x, int64_t y, int64_t z) const;
  template <bool kFirst>
  double search(const common::Vec3& p, double reach) const;

  double edge_;
  int64_t low_[3] = {0, 0, 0}, size_[3] = {0, 0, 0};
  std::vector<uint8_t> dense_;  // x fastest; empty when hashed_ serves
  std::unordered_set<uint64_t> hashed_;
};

// The class of every finest voxel of a map (what OccupancyMap::query answers) over its occupied
// bounds plus a margin; outside them, or when that box holds more than kMaxCells voxels, the
// octree answers.
class ClassRaster {
 public:
  ClassRaster(const fusion::OccupancyMap& map, double margin_m);
  static constexpr size_t kMaxCells = size_t{1} << 28;  // 64 MB at 2 bits a voxel

  fusion::Occupancy at(const common::Vec3& p) const;

 private:
  const fusion::OccupancyMap& map_;
  double resolution_;
  int64_t low_[3] = {0, 0, 0}, size_[3] = {0, 0, 0};
  std::vector<uint8_t> classes_;  // 2 bits a voxel, x fastest; empty: the octree answers
};

}  // namespace stereomap::align
