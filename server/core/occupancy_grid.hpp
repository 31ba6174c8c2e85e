// A height band of a session's octree seen from above, as ground robots use maps: ROS
// map_server's files (a PGM image and its YAML) and the cells of a foxglove.Grid. Known free
// space comes from the octree's free nodes, not only the occupied ones: a cell is occupied
// when a voxel of its column in the band is, free when one is known free and none occupied,
// unknown otherwise.
//
//   auto grid = occupancyGrid(map, 0.2, 1.5);    // voxel centres 0.2..1.5 m
//   files: gridPgm(*grid), gridYaml(*grid, "map.pgm")
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "common/result.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace stereomap::core {

struct OccupancyGrid {
  static constexpr int8_t kUnknown = -1, kFree = 0, kOccupied = 100;  // nav_msgs' values
  double resolution = 0;              // metres per cell (the map's voxel)
  double origin_x = 0, origin_y = 0;  // the lower-left cell's lower-left corner, map frame
  int width = 0, height = 0;          // cells
  std::vector<int8_t> cells;          // row-major from the lower-left (row = y)
  int8_t at(int column, int row) const { return cells[static_cast<size_t>(row) * width + column]; }
};

// The grid covers the footprint of what is known in the band. kNotFound when nothing is,
// kInvalidArgument for a band that is not one, kTooLarge above kMaxGridCells.
constexpr size_t kMaxGridCells = 64u << 20;
common::Result<OccupancyGrid> occupancyGrid(const fusion::OccupancyMap& map, double z_min,
                                            double z_max);

// map_server's trinary PGM (P5): occupied 0, free 254, unknown 205; the first row is the top
// (largest y), as map_server reads it.
std::string gridPgm(const OccupancyGrid& grid);
// Its YAML: image, mode trinary, resolution, origin [x, y, yaw] of the lower-left pixel,
// negate 0, occupied_thresh 0.65, free_thresh 0.196.
std::string gridYaml(const OccupancyGrid& grid, const std::string& image);

}  // namespace stereomap::core
