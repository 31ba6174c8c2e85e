// Dense rasters of one map's space, for the alignment's millions of lookups: where a k-d tree
// search or an octree walk costs about a microsecond, a raster's costs a few nanoseconds. They
// answer exactly what the tree and the octree would (tests/align_test.cpp checks it).
//
//   const CellRaster cells(codes_at_depth, depth, map.cellSize(depth));
//   if (cells.near(p, 1.5 * edge)) ...   // an occupied cell's centre within reach of p
//   const int j = cells.nearest(p, 2.0 * edge);   // its number, -1 when none is in reach
//   const NeighbourRows rows = cells.around(5.0, 50);   // each cell's 50 nearest within 5
//   const ClassRaster space(map, map.occupiedBounds(), margin_m);
//   if (space.at(p) == fusion::Occupancy::kFree) ...   // map.query(p), cached
#pragma once

#include <cstddef>
#include <cstdint>
#include <unordered_map>
#include <vector>

#include "common/geometry.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace stereomap::align {

// Each of a raster's cells' neighbours, nearest first (the cell itself first): rows of `width`
// cell numbers and squared distances, `count` of them used.
struct NeighbourRows {
  int width = 0;
  std::vector<int> index;
  std::vector<double> distance2;
  std::vector<int> count;
  const int* indices(size_t cell) const { return index.data() + cell * width; }
  const double* distances2(size_t cell) const { return distance2.data() + cell * width; }
};

// A map's occupied cells at one depth of the octree (16: the finest voxels), each cell's number
// at its place on the lattice. The neighbour searches walk the lattice offsets around a point
// in order of distance: a few dozen raster reads, where a k-d tree's search cost microseconds
// and allocated its answer. Ties in distance go in a fixed order of offsets.
class CellRaster {
 public:
  // `codes`: the cells' Morton codes at `depth` (a voxel's code shifted right by 3 bits per
  // level up); cell i is codes[i]. `edge`: the cell's edge in metres.
  CellRaster(const std::vector<uint64_t>& codes, unsigned depth, double edge);
  // The same from the cells' centres, (key + 0.5) * edge.
  CellRaster(const std::vector<common::Vec3>& centres, double edge);
  // Above this many cells of bounding box, a hash map stands in for the dense raster (slower,
  // as exact).
  static constexpr size_t kMaxDenseCells = size_t{1} << 25;

  // The nearest cell (its number) whose centre is within `reach` of p, and its squared
  // distance; -1 when there is none.
  int nearest(const common::Vec3& p, double reach, double* distance2 = nullptr) const;
  // Squared distance from p to the nearest cell's centre if it is within `reach`, else a
  // negative value.
  double nearest2(const common::Vec3& p, double reach) const;
  // Whether a cell's centre is within `reach` (at most 1.5 edges) of p.
  bool near(const common::Vec3& p, double reach) const;
  // Every cell's nearest cells within `radius_cells` edges, at most `max_neighbours`.
  NeighbourRows around(double radius_cells, int max_neighbours) const;
  size_t size() const { return keys_.size() / 3; }
  double edge() const { return edge_; }

 private:
  void build();
  int at(int64_t x, int64_t y, int64_t z) const;

  double edge_;
  std::vector<int64_t> keys_;  // cell i's lattice key at 3i, 3i+1, 3i+2
  int64_t low_[3] = {0, 0, 0}, size_[3] = {0, 0, 0};
  std::vector<int32_t> dense_;  // x fastest, -1 where no cell; empty when hashed_ serves
  std::unordered_map<uint64_t, int32_t> hashed_;
};

// The class of every finest voxel of a map (what OccupancyMap::query answers) over its occupied
// bounds plus a margin; outside them, or when that box holds more than kMaxCells voxels, the
// octree answers.
class ClassRaster {
 public:
  // `occupied`: the map's occupied bounds (OccupancyMap::occupiedBounds, when the caller has
  // them already).
  ClassRaster(const fusion::OccupancyMap& map, const common::Box3& occupied, double margin_m);
  static constexpr size_t kMaxCells = size_t{1} << 28;  // 64 MB at 2 bits a voxel

  fusion::Occupancy at(const common::Vec3& p) const;

 private:
  const fusion::OccupancyMap& map_;
  double resolution_;
  int64_t low_[3] = {0, 0, 0}, size_[3] = {0, 0, 0};
  std::vector<uint8_t> classes_;  // 2 bits a voxel, x fastest; empty: the octree answers
};

}  // namespace stereomap::align
