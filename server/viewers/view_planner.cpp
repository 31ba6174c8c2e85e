#include "server/viewers/view_planner.hpp"

#include <algorithm>
#include <cmath>
#include <queue>

namespace stereomap::viewers {

namespace {

using common::Vec3;

constexpr int kTileVoxels = 1 << tiles::kTileBits;

struct Placed {
  double distance = 0;  // eye to the tile's box (0 inside it)
  bool visible = true;
  unsigned wanted = 0;  // the coarsest level whose cells look no larger than error_px
  unsigned level = 0;   // chosen
};

// The tile's box in the map frame: voxel v spans [v, v + 1) * resolution.
common::Box3 boxOf(const tiles::TileKey& key, double resolution) {
  const double edge = kTileVoxels * resolution;
  common::Box3 box;
  box.min = Vec3(key.x, key.y, key.z) * edge;
  box.max = box.min + Vec3::Constant(edge);
  return box;
}

bool intersects(const common::Box3& box, const std::vector<std::array<double, 4>>& planes) {
  for (const auto& p : planes) {
    // The box corner furthest along the plane's normal: outside if even it is outside.
    const Vec3 corner(p[0] >= 0 ? box.max.x() : box.min.x(), p[1] >= 0 ? box.max.y() : box.min.y(),
                      p[2] >= 0 ? box.max.z() : box.min.z());
    if (p[0] * corner.x() + p[1] * corner.y() + p[2] * corner.z() + p[3] < 0) return false;
  }
  return true;
}

double focalPx(const ViewRequest& view) {
  return 0.5 * view.height_px / std::tan(0.5 * std::clamp(view.fov_y_rad, 0.01, 3.1));
}

// How large a cell of `level` looks at `distance`, in pixels.
double errorPx(unsigned level, double distance, double resolution, double focal_px) {
  return resolution * static_cast<double>(1u << level) * focal_px / std::max(distance, resolution);
}

Placed place(const tiles::TileKey& key, double resolution, const ViewRequest& view,
             double focal_px) {
  const auto box = boxOf(key, resolution);
  const Vec3 nearest = view.eye.cwiseMax(box.min).cwiseMin(box.max);
  Placed p;
  p.distance = (view.eye - nearest).norm();
  p.visible = view.planes.empty() || intersects(box, view.planes);
  while (p.wanted < tiles::kLevels - 1 &&
         errorPx(p.wanted + 1, p.distance, resolution, focal_px) <= view.error_px) {
    ++p.wanted;
  }
  return p;
}

}  // namespace

unsigned levelFor(const tiles::TileKey& key, double resolution, const ViewRequest& view,
                  unsigned coarse_level) {
  const Placed p = place(key, resolution, view, focalPx(view));
  return p.visible ? std::min(p.wanted, coarse_level) : coarse_level;
}

ViewPlan planView(const std::vector<tiles::TileInfo>& tiles, double resolution,
                  const ViewRequest& view) {
  ViewPlan plan;
  if (tiles.empty()) return plan;
  constexpr unsigned kCoarsest = tiles::kLevels - 1;
  const double focal_px = focalPx(view);
  auto error = [&](unsigned level, double distance) {
    return errorPx(level, distance, resolution, focal_px);
  };

  // The coarse pass: the finest level at which every tile together fits a quarter of the
  // budget (a whole-map overview that leaves room to refine).
  std::array<uint64_t, tiles::kLevels> total{};
  for (const auto& tile : tiles) {
    for (unsigned l = 0; l < tiles::kLevels; ++l) total[l] += tile.cells[l];
  }
  plan.coarse_level = kCoarsest;
  for (unsigned l = 0; l < tiles::kLevels; ++l) {
    if (total[l] <= view.budget / 4) {
      plan.coarse_level = l;
      break;
    }
  }
  plan.cells = total[plan.coarse_level];

  std::vector<Placed> placed(tiles.size());
  for (size_t i = 0; i < tiles.size(); ++i) {
    placed[i] = place(tiles[i].key, resolution, view, focal_px);
    placed[i].level = plan.coarse_level;
  }

  // Refinement: always the visible tile whose cells look largest, one level at a time, while
  // the budget allows (a tile that no longer fits stops; smaller ones may still fit).
  using Candidate = std::pair<double, size_t>;  // (error in pixels, tile)
  std::priority_queue<Candidate> queue;
  for (size_t i = 0; i < tiles.size(); ++i) {
    const Placed& p = placed[i];
    if (p.visible && p.level > p.wanted) queue.emplace(error(p.level, p.distance), i);
  }
  while (!queue.empty()) {
    const size_t i = queue.top().second;
    queue.pop();
    Placed& p = placed[i];
    const uint64_t cost = tiles[i].cells[p.level - 1] - tiles[i].cells[p.level];
    if (plan.cells + cost > view.budget) continue;
    plan.cells += cost;
    --p.level;
    if (p.level > p.wanted) queue.emplace(error(p.level, p.distance), i);
  }

  std::vector<size_t> order(tiles.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::sort(order.begin(), order.end(),
            [&](size_t a, size_t b) { return placed[a].distance < placed[b].distance; });
  plan.tiles.reserve(tiles.size());
  for (size_t i : order) plan.tiles.push_back({tiles[i].key, plan.coarse_level});
  plan.coarse_count = plan.tiles.size();
  // Refined tiles replace their coarse pass, nearest (largest error) first.
  for (size_t i : order) {
    if (placed[i].level < plan.coarse_level) plan.tiles.push_back({tiles[i].key, placed[i].level});
  }
  return plan;
}

}  // namespace stereomap::viewers
