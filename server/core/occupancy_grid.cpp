#include "server/core/occupancy_grid.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <limits>

namespace stereomap::core {

common::Result<OccupancyGrid> occupancyGrid(const fusion::OccupancyMap& map, double z_min,
                                            double z_max) {
  if (!(z_min <= z_max) || !std::isfinite(z_min) || !std::isfinite(z_max)) {
    return common::makeError(common::ErrorCode::kInvalidArgument,
                             "the band's zmin and zmax must be finite, zmin not above zmax");
  }
  const double r = map.resolution();
  const double huge = std::numeric_limits<double>::max();
  // Nodes with a voxel centre in the band: a node [z0, z0 + edge) holds centres from
  // z0 + r/2 to z0 + edge - r/2.
  common::Box3 band;
  band.min = common::Vec3(-huge, -huge, z_min - r / 2);
  band.max = common::Vec3(huge, huge, z_max + r / 2);
  auto inBand = [&](const common::Vec3& corner, double edge) {
    return corner.z() + r / 2 <= z_max + 1e-9 * r && corner.z() + edge - r / 2 >= z_min - 1e-9 * r;
  };
  auto index = [&](double coordinate) {
    return static_cast<int64_t>(std::llround(coordinate / r));
  };
  // First the footprint (two walks of the band rather than a copy of its nodes).
  int64_t x0 = std::numeric_limits<int64_t>::max(), y0 = x0,
          x1 = std::numeric_limits<int64_t>::min(), y1 = x1;
  map.visitKnown(band, [&](const common::Vec3& corner, double edge, fusion::Occupancy) {
    if (!inBand(corner, edge)) return;
    const int64_t n = index(edge);
    x0 = std::min(x0, index(corner.x()));
    y0 = std::min(y0, index(corner.y()));
    x1 = std::max(x1, index(corner.x()) + n);
    y1 = std::max(y1, index(corner.y()) + n);
  });
  if (x0 > x1) {
    return common::makeError(common::ErrorCode::kNotFound, "nothing is known in the band " +
                                                               std::to_string(z_min) + " .. " +
                                                               std::to_string(z_max) + " m");
  }
  OccupancyGrid grid;
  grid.resolution = r;
  grid.origin_x = static_cast<double>(x0) * r;
  grid.origin_y = static_cast<double>(y0) * r;
  const int64_t width = x1 - x0, height = y1 - y0;
  if (static_cast<double>(width) * static_cast<double>(height) > kMaxGridCells) {
    return common::makeError(common::ErrorCode::kTooLarge,
                             "the grid would have " + std::to_string(width) + " x " +
                                 std::to_string(height) + " cells (at most " +
                                 std::to_string(kMaxGridCells) + ")");
  }
  grid.width = static_cast<int>(width);
  grid.height = static_cast<int>(height);
  grid.cells.assign(static_cast<size_t>(width * height), OccupancyGrid::kUnknown);
  map.visitKnown(band, [&](const common::Vec3& corner, double edge, fusion::Occupancy occupancy) {
    if (!inBand(corner, edge)) return;
    const int64_t n = index(edge), cx = index(corner.x()) - x0, cy = index(corner.y()) - y0;
    const int8_t value =
        occupancy == fusion::Occupancy::kOccupied ? OccupancyGrid::kOccupied : OccupancyGrid::kFree;
    for (int64_t y = cy; y < cy + n; ++y) {
      int8_t* row = grid.cells.data() + y * width;
      for (int64_t x = cx; x < cx + n; ++x) {
        if (row[x] != OccupancyGrid::kOccupied) row[x] = value;  // occupied wins
      }
    }
  });
  return grid;
}

std::string gridPgm(const OccupancyGrid& grid) {
  std::string out =
      "P5\n" + std::to_string(grid.width) + " " + std::to_string(grid.height) + "\n255\n";
  const size_t header = out.size();
  out.resize(header + grid.cells.size());
  for (int row = 0; row < grid.height; ++row) {
    char* pixels = out.data() + header + static_cast<size_t>(grid.height - 1 - row) * grid.width;
    for (int column = 0; column < grid.width; ++column) {
      const int8_t cell = grid.at(column, row);
      pixels[column] = static_cast<char>(cell == OccupancyGrid::kOccupied ? 0
                                         : cell == OccupancyGrid::kFree   ? 254
                                                                          : 205);
    }
  }
  return out;
}

std::string gridYaml(const OccupancyGrid& grid, const std::string& image) {
  auto number = [](double value) {  // the shortest text that reads back exactly
    char text[32];
    return std::string(text, std::to_chars(text, text + sizeof text, value).ptr);
  };
  return "image: " + image + "\nmode: trinary\nresolution: " + number(grid.resolution) +
         "\norigin: [" + number(grid.origin_x) + ", " + number(grid.origin_y) +
         ", 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n";
}

}  // namespace stereomap::core
