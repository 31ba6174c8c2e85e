#include "server/viewers/view_planner.hpp"

#include <gtest/gtest.h>

#include <map>

namespace stereomap::viewers {
namespace {

// A row of full tiles along x: each level has 8^(6 - l) cells, as a solid tile would.
std::vector<tiles::TileInfo> rowOfTiles(int count) {
  std::vector<tiles::TileInfo> row;
  for (int x = 0; x < count; ++x) {
    tiles::TileInfo info;
    info.key = {x, 0, 0};
    info.version = 1;
    for (unsigned l = 0; l < tiles::kLevels; ++l) info.cells[l] = 1u << (3 * (6 - l));
    row.push_back(info);
  }
  return row;
}

TEST(ViewPlanner, CoarseEverywhereFirstThenFinerNearTheCamera) {
  const auto row = rowOfTiles(20);  // 20 tiles of 6.4 m at 0.1 m
  ViewRequest view;
  view.eye = {3.2, 3.2, 10};  // above the first tile
  view.budget = 300'000;
  const auto plan = planView(row, 0.1, view);
  ASSERT_EQ(plan.coarse_count, row.size());
  // The coarse pass fits a quarter of the budget: level 3 (512 cells per tile) does, level 2
  // (4096) does not.
  EXPECT_EQ(plan.coarse_level, 3u);
  EXPECT_EQ(plan.tiles[0].key, (tiles::TileKey{0, 0, 0}));  // nearest first
  for (size_t i = 0; i < plan.coarse_count; ++i) EXPECT_EQ(plan.tiles[i].level, 3u);
  ASSERT_GT(plan.tiles.size(), plan.coarse_count);
  std::map<int, unsigned> final_level;
  for (const auto& tile : plan.tiles) final_level[tile.key.x] = tile.level;
  EXPECT_LT(final_level[0], 3u);               // near: refined
  EXPECT_LE(final_level[0], final_level[10]);  // never coarser near than far
  EXPECT_EQ(final_level[19], 3u);              // far: the coarse pass is enough
  EXPECT_LE(plan.cells, view.budget);
  // A larger budget draws more, within it.
  view.budget = 3'000'000;
  const auto bigger = planView(row, 0.1, view);
  EXPECT_GT(bigger.cells, plan.cells);
  EXPECT_LE(bigger.cells, view.budget);
}

TEST(ViewPlanner, TilesOutsideTheFrustumStayCoarse) {
  const auto row = rowOfTiles(10);
  ViewRequest view;
  view.eye = {3.2, 3.2, 2};
  view.budget = 10'000'000;
  view.planes = {{-1, 0, 0, 12.7}};  // x <= 12.7: tiles 0 and 1 only
  const auto plan = planView(row, 0.1, view);
  for (size_t i = plan.coarse_count; i < plan.tiles.size(); ++i) {
    EXPECT_LE(plan.tiles[i].key.x, 1) << "tile " << plan.tiles[i].key.x << " refined";
  }
  EXPECT_EQ(levelFor({5, 0, 0}, 0.1, view, plan.coarse_level), plan.coarse_level);
  EXPECT_LT(levelFor({0, 0, 0}, 0.1, view, plan.coarse_level), plan.coarse_level);
}

TEST(ViewPlanner, AnEmptyMapPlansNothingAndATinyBudgetStillShowsTheCoarsest) {
  EXPECT_TRUE(planView({}, 0.1, {}).tiles.empty());
  ViewRequest view;
  view.budget = 1;
  const auto plan = planView(rowOfTiles(4), 0.1, view);
  EXPECT_EQ(plan.coarse_level, tiles::kLevels - 1);
  EXPECT_EQ(plan.tiles.size(), 4u);
}

}  // namespace
}  // namespace stereomap::viewers
