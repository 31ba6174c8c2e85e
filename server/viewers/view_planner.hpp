// Which tiles a viewer gets, at which level of detail, in which order, for where its camera
// is (the "view" message of protocol 2, docs/PROTOCOL.md). Coarse everywhere first, so a new
// viewer sees the whole map at once; then finer where the camera is near, by screen-space
// error (a cell's projected size in pixels), until the viewer's cell budget is spent.
// Pure: no threads, no I/O.
//
//   ViewRequest view{.eye = {0, 0, 10}, .fov_y_rad = 1.0, .height_px = 900, .budget = 1e6};
//   ViewPlan plan = planView(tiles.list(), tiles.resolution(), view);
//   // send plan.tiles in order: the first plan.coarse_count are the coarse pass
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include "common/geometry.hpp"
#include "server/tiles/tile_set.hpp"

namespace stereomap::viewers {

struct ViewRequest {
  common::Vec3 eye = common::Vec3::Zero();  // camera position, map frame (metres)
  // Frustum planes (a, b, c, d) with a*x + b*y + c*z + d >= 0 inside, map frame; none: every
  // tile counts as visible.
  std::vector<std::array<double, 4>> planes;
  double fov_y_rad = 1.0;       // vertical field of view
  double height_px = 900;       // viewport height
  uint64_t budget = 1'000'000;  // cells the viewer will draw at most
  double error_px = 2.0;        // a cell may look this large before a finer level is due
};

struct PlannedTile {
  tiles::TileKey key;
  unsigned level = 0;
};

struct ViewPlan {
  // The coarse pass (every tile at `coarse_level`, nearest first), then the tiles refined
  // beyond it at their final level (nearest, i.e. most needed, first).
  std::vector<PlannedTile> tiles;
  size_t coarse_count = 0;
  unsigned coarse_level = tiles::kLevels - 1;
  uint64_t cells = 0;  // what the plan draws, <= the budget unless even level 6 exceeds it
};

ViewPlan planView(const std::vector<tiles::TileInfo>& tiles, double resolution,
                  const ViewRequest& view);

// The level for a tile that appeared after the plan (a live map grows): as fine as its
// distance calls for when visible, never coarser than the plan's coarse pass.
unsigned levelFor(const tiles::TileKey& key, double resolution, const ViewRequest& view,
                  unsigned coarse_level);

}  // namespace stereomap::viewers
