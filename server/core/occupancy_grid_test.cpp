#include "server/core/occupancy_grid.hpp"

#include <gtest/gtest.h>

#include <cmath>

namespace stereomap::core {
namespace {

// A room's corner seen from 1 m up: two walls, a post, free space between (and pruned free
// blocks), unknown behind the walls.
std::unique_ptr<fusion::OccupancyMap> roomMap() {
  auto map =
      std::make_unique<fusion::OccupancyMap>(fusion::OccupancyMap::Options{.resolution = 0.1});
  common::PointCloud cloud;
  for (double a = -0.6; a <= 1.2; a += 0.004) {
    for (double h = -0.8; h <= 1.0; h += 0.05) {
      const double d = std::abs(std::cos(a)) > 0.3 ? 4.0 / std::cos(a) : 6.0;
      cloud.points.emplace_back(static_cast<float>(d * std::cos(a)),
                                static_cast<float>(d * std::sin(a)), static_cast<float>(h));
    }
  }
  for (double h = -0.8; h <= 0.6; h += 0.05)
    cloud.points.emplace_back(2.0f, 0.5f, static_cast<float>(h));
  common::Rigid3 pose;
  pose.translation = common::Vec3(0, 0, 1.0);
  for (int i = 0; i < 3; ++i) map->insertCloud(cloud, pose, 8.0);
  return map;
}

// Cell by cell against the octree's own answer for every voxel of the band.
TEST(OccupancyGrid, EveryCellIsItsColumnInTheBand) {
  const auto map = roomMap();
  const double z_min = 0.45, z_max = 1.45;
  auto grid = occupancyGrid(*map, z_min, z_max);
  ASSERT_TRUE(grid) << grid.error().message;
  const double r = grid->resolution;
  int occupied = 0, free = 0, unknown = 0;
  for (int row = -2; row < grid->height + 2; ++row) {
    for (int column = -2; column < grid->width + 2; ++column) {
      const double x = grid->origin_x + (column + 0.5) * r, y = grid->origin_y + (row + 0.5) * r;
      int8_t expected = OccupancyGrid::kUnknown;
      for (double z = (std::ceil(z_min / r - 0.5) + 0.5) * r; z <= z_max + 1e-9; z += r) {
        const auto c = map->query(common::Vec3(x, y, z));
        if (c == fusion::Occupancy::kOccupied) expected = OccupancyGrid::kOccupied;
        if (c == fusion::Occupancy::kFree && expected == OccupancyGrid::kUnknown) {
          expected = OccupancyGrid::kFree;
        }
      }
      const bool inside = row >= 0 && column >= 0 && row < grid->height && column < grid->width;
      if (!inside) {
        EXPECT_EQ(expected, OccupancyGrid::kUnknown)
            << "known outside the grid at " << x << ", " << y;
        continue;
      }
      ASSERT_EQ(grid->at(column, row), expected) << "cell " << column << ", " << row;
      (expected == OccupancyGrid::kOccupied ? occupied
       : expected == OccupancyGrid::kFree   ? free
                                            : unknown)++;
    }
  }
  EXPECT_GT(occupied, 50);
  EXPECT_GT(free, 500);
  EXPECT_GT(unknown, 10);
}

TEST(OccupancyGrid, MapServersFiles) {
  const auto map = roomMap();
  auto grid = occupancyGrid(*map, 0.45, 1.45);
  ASSERT_TRUE(grid);
  const std::string pgm = gridPgm(*grid);
  const std::string header =
      "P5\n" + std::to_string(grid->width) + " " + std::to_string(grid->height) + "\n255\n";
  ASSERT_EQ(pgm.compare(0, header.size(), header), 0);
  ASSERT_EQ(pgm.size(), header.size() + grid->cells.size());
  // The first row is the top: the grid's last row.
  for (int column = 0; column < grid->width; ++column) {
    const auto pixel = static_cast<uint8_t>(pgm[header.size() + column]);
    const int8_t cell = grid->at(column, grid->height - 1);
    EXPECT_EQ(pixel, cell == OccupancyGrid::kOccupied ? 0
                     : cell == OccupancyGrid::kFree   ? 254
                                                      : 205);
  }
  const std::string yaml = gridYaml(*grid, "flight.pgm");
  EXPECT_NE(yaml.find("image: flight.pgm\n"), std::string::npos);
  EXPECT_NE(yaml.find("resolution: 0.1"), std::string::npos);
  EXPECT_NE(yaml.find("occupied_thresh: 0.65\nfree_thresh: 0.196\n"), std::string::npos);
  EXPECT_NE(yaml.find("mode: trinary"), std::string::npos);
}

TEST(OccupancyGrid, AnEmptyBandOrABackwardOneIsAnError) {
  const auto map = roomMap();
  auto empty = occupancyGrid(*map, 40, 50);
  ASSERT_FALSE(empty);
  EXPECT_EQ(empty.error().code, common::ErrorCode::kNotFound);
  auto backward = occupancyGrid(*map, 2, 1);
  ASSERT_FALSE(backward);
  EXPECT_EQ(backward.error().code, common::ErrorCode::kInvalidArgument);
  EXPECT_FALSE(occupancyGrid(*map, std::nan(""), 1));
}

}  // namespace
}  // namespace stereomap::core
