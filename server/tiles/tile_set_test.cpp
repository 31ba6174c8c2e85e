#include "server/tiles/tile_set.hpp"

#include <gtest/gtest.h>

#include <random>

namespace stereomap::tiles {
namespace {

using common::Vec3;
using fusion::VoxelIndex;

// Points on a rough wall at distance x (sensor frame), `half` metres each way.
common::PointCloud wall(double x, double half, double spacing, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> jitter(-0.04, 0.04);
  common::PointCloud cloud;
  for (double y = -half; y <= half; y += spacing) {
    for (double z = -half; z <= half; z += spacing) {
      cloud.points.emplace_back(x + jitter(rng), y, z);
    }
  }
  return cloud;
}

// A solid block of points (pruned into blocks of the tree once saturated).
common::PointCloud block(const Vec3& low, double side, double spacing) {
  common::PointCloud cloud;
  for (double x = 0; x < side; x += spacing) {
    for (double y = 0; y < side; y += spacing) {
      for (double z = 0; z < side; z += spacing) {
        cloud.points.push_back((low + Vec3(x, y, z)).cast<float>());
      }
    }
  }
  return cloud;
}

// Cells of `level` from the tiles, as map cell indices (cell edge 2^level voxels).
std::vector<VoxelIndex> cellsAt(const TileSet& tiles, unsigned level) {
  std::vector<VoxelIndex> cells;
  const int32_t edge = 1 << (kTileBits - level);
  for (const auto& tile : tiles.all()) {
    for (const uint32_t code : tile->cells(level).codes) {
      const auto x = static_cast<int32_t>(fusion::detail::compactBits(code));
      const auto y = static_cast<int32_t>(fusion::detail::compactBits(code >> 1));
      const auto z = static_cast<int32_t>(fusion::detail::compactBits(code >> 2));
      cells.push_back(
          {tile->key().x * edge + x, tile->key().y * edge + y, tile->key().z * edge + z});
    }
  }
  std::sort(cells.begin(), cells.end());
  return cells;
}

void expectSameAsMap(const TileSet& tiles, const fusion::OccupancyMap& map) {
  for (unsigned level = 0; level < kLevels; ++level) {
    ASSERT_EQ(cellsAt(tiles, level), map.occupiedCells(fusion::kTreeDepth - level))
        << "level " << level;
  }
  const auto summary = tiles.summary();
  EXPECT_EQ(summary.occupied_voxels, map.occupiedCount());
  const auto bounds = map.occupiedBounds();
  ASSERT_EQ(summary.bounds.empty(), bounds.empty());
  if (!bounds.empty()) {
    EXPECT_LT((summary.bounds.min - bounds.min).norm(), 1e-5);
    EXPECT_LT((summary.bounds.max - bounds.max).norm(), 1e-5);
  }
  // Values too: a rebuild reads them from the tree itself.
  TileSet fresh(tiles.session(), tiles.resolution());
  fresh.rebuild(map);
  const auto a = tiles.all(), b = fresh.all();
  ASSERT_EQ(a.size(), b.size());
  for (size_t i = 0; i < a.size(); ++i) {
    ASSERT_EQ(a[i]->key(), b[i]->key());
    for (unsigned level = 0; level < kLevels; ++level) {
      ASSERT_EQ(a[i]->cells(level), b[i]->cells(level)) << "tile " << a[i]->key().text();
    }
  }
}

TEST(TileSet, FollowsEveryInsertionExactlyAtEveryLevel) {
  common::WorkerPool pool(1);
  fusion::OccupancyMap map({.resolution = 0.1, .pool = &pool});
  TileSet tiles("t", 0.1);
  fusion::MapChanges changes;
  const common::Rigid3 identity = common::Rigid3::identity();
  const common::Rigid3 turned{common::Quat(Eigen::AngleAxisd(2.5, Vec3::UnitZ())),
                              Vec3(0.3, -0.2, 0.4)};
  struct Step {
    common::PointCloud cloud;
    common::Rigid3 pose;
  };
  std::vector<Step> steps;
  for (unsigned i = 0; i < 3; ++i) steps.push_back({wall(3.0, 2.0, 0.03, i), identity});
  // A solid block seen again and again: saturated voxels are pruned into blocks, which later
  // insertions update as a whole.
  for (int i = 0; i < 6; ++i) steps.push_back({block(Vec3(4.0, -0.8, -0.8), 1.6, 0.05), identity});
  steps.push_back({wall(2.5, 1.0, 0.05, 9), turned});
  // A far wall seen through the near one: rays clear what was occupied.
  for (unsigned i = 0; i < 8; ++i) steps.push_back({wall(7.0, 2.5, 0.04, 20 + i), identity});
  size_t block_changes = 0, removals = 0;
  for (size_t i = 0; i < steps.size(); ++i) {
    map.insertCloud(steps[i].cloud, steps[i].pose, 12.0, &changes);
    for (const auto& change : changes.voxels) {
      block_changes += change.depth < fusion::kTreeDepth;
      removals += !change.occupied;
    }
    ASSERT_TRUE(tiles.apply(changes)) << "step " << i;
    SCOPED_TRACE("after step " + std::to_string(i));
    expectSameAsMap(tiles, map);
  }
  // The steps did remove voxels and change whole blocks (the test covers those paths).
  EXPECT_GT(block_changes, 0u);
  EXPECT_GT(removals, 0u);
}

TEST(TileSet, AFramesWorkDependsOnWhatItChangesNotOnTheMapsSize) {
  fusion::OccupancyMap small({.resolution = 0.1}), large({.resolution = 0.1});
  TileSet small_tiles("s", 0.1), large_tiles("l", 0.1);
  fusion::MapChanges changes;
  // The large map first gets a big structure far from where the frame looks.
  const common::Rigid3 away{common::Quat::Identity(), Vec3(-60, 0, 0)};
  for (unsigned i = 0; i < 4; ++i) {
    large.insertCloud(wall(-8.0 - i, 8.0, 0.05, i), away, 30.0, &changes);
    ASSERT_TRUE(large_tiles.apply(changes));
  }
  ASSERT_GT(large_tiles.summary().occupied_voxels, 40000u);
  const auto frame = wall(3.0, 2.0, 0.03, 77);
  small.insertCloud(frame, common::Rigid3::identity(), 10.0, &changes);
  const size_t small_changes = changes.voxels.size();
  const uint64_t small_before = small_tiles.summary().version;
  ASSERT_TRUE(small_tiles.apply(changes));
  large.insertCloud(frame, common::Rigid3::identity(), 10.0, &changes);
  const uint64_t large_before = large_tiles.summary().version;
  ASSERT_TRUE(large_tiles.apply(changes));
  // The same changed voxels, and the same number of tiles re-made, in both.
  EXPECT_EQ(changes.voxels.size(), small_changes);
  EXPECT_EQ(large_tiles.summary().version - large_before,
            small_tiles.summary().version - small_before);
  EXPECT_GT(small_changes, 0u);
}

// A map and its tiles, fed walls seen from the origin.
struct MappedWalls {
  explicit MappedWalls(double resolution)
      : map({.resolution = resolution}), tiles("t", resolution) {}
  void see(double x, double half, double spacing, unsigned seed) {
    map.insertCloud(wall(x, half, spacing, seed), common::Rigid3::identity(), 10.0, &changes);
    ASSERT_TRUE(tiles.apply(changes));
  }
  fusion::OccupancyMap map;
  TileSet tiles;
  fusion::MapChanges changes;
};

TEST(TileSet, ReportsChangedTilesOnceWithTheirNewestVersion) {
  MappedWalls mapped(0.1);
  const auto& tiles = mapped.tiles;
  mapped.see(3.0, 2.0, 0.05, 1);
  const uint64_t first = tiles.summary().version;
  auto all = tiles.changedSince(0);
  ASSERT_TRUE(all);
  EXPECT_EQ(all->size(), tiles.list().size());
  mapped.see(3.0, 2.0, 0.05, 2);
  auto later = tiles.changedSince(first);
  ASSERT_TRUE(later);
  for (const auto& [key, version] : *later) {
    EXPECT_GT(version, first);
    ASSERT_TRUE(tiles.find(key));
    EXPECT_EQ(tiles.find(key)->version(), version);
  }
  EXPECT_TRUE(tiles.changedSince(tiles.summary().version)->empty());
}

TEST(TileSet, EncodedTilesDecodeToTheirCells) {
  MappedWalls mapped(0.05);
  mapped.see(2.0, 1.5, 0.02, 4);
  for (const auto& tile : mapped.tiles.all()) {
    for (unsigned level = 0; level < kLevels; ++level) {
      auto decoded = proto::tiles::decodeTile(*tile->encoded(level));
      ASSERT_TRUE(decoded) << decoded.error().message;
      EXPECT_EQ(decoded->cells, tile->cells(level));
      EXPECT_EQ(decoded->header.version, tile->version());
      EXPECT_EQ(decoded->header.key, tile->key());
      EXPECT_EQ(decoded->header.session, "t");
    }
  }
}

}  // namespace
}  // namespace stereomap::tiles
