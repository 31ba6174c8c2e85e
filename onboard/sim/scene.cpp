#include "onboard/sim/scene.hpp"

#include <algorithm>
#include <cmath>
#include <random>

#include "onboard/sim/flight.hpp"

namespace stereomap::sim {

using common::Vec3;

namespace {

// Distance in the xy plane from point (px, py) to the rectangle of `box`.
double footprintDistance(const SceneBox& box, double px, double py) {
  const double dx = std::max({box.min.x() - px, 0.0, px - box.max.x()});
  const double dy = std::max({box.min.y() - py, 0.0, py - box.max.y()});
  return std::hypot(dx, dy);
}

}  // namespace

Scene::Scene(std::vector<SceneBox> boxes, uint32_t texture_seed)
    : boxes_(std::move(boxes)), texture_seed_(texture_seed) {}

Scene Scene::makeRoom(const RoomOptions& options) {
  const double hx = options.length / 2, hy = options.width / 2, h = options.wall_height;
  constexpr double kWall = 0.2;
  std::vector<SceneBox> boxes = {
      {Vec3(-hx - kWall, -hy - kWall, -kWall), Vec3(hx + kWall, hy + kWall, 0.0), 0.55f},  // floor
      {Vec3(-hx - kWall, -hy - kWall, 0), Vec3(-hx, hy + kWall, h), 0.75f},  // wall at -x
      {Vec3(hx, -hy - kWall, 0), Vec3(hx + kWall, hy + kWall, h), 0.7f},     // wall at +x
      {Vec3(-hx, -hy - kWall, 0), Vec3(hx, -hy, h), 0.8f},                   // wall at -y
      {Vec3(-hx, hy, 0), Vec3(hx, hy + kWall, h), 0.65f},                    // wall at +y
  };

  const FlightOptions path;
  std::mt19937 rng(options.seed);
  std::uniform_real_distribution<double> ux(-hx + 0.3, hx - 0.3), uy(-hy + 0.3, hy - 0.3);
  std::uniform_real_distribution<double> side(0.4, 1.2), height(0.5, 2.2), albedo(0.4, 0.9);
  int placed = 0;
  for (int attempt = 0; attempt < 2000 && placed < options.obstacles; ++attempt) {
    const double cx = ux(rng), cy = uy(rng), sx = side(rng) / 2, sy = side(rng) / 2;
    SceneBox box{Vec3(cx - sx, cy - sy, 0), Vec3(cx + sx, cy + sy, height(rng)),
                 static_cast<float>(albedo(rng))};
    if (box.min.x() < -hx + 0.3 || box.max.x() > hx - 0.3 || box.min.y() < -hy + 0.3 ||
        box.max.y() > hy - 0.3) {
      continue;
    }
    bool clear = true;
    for (int i = 0; i < 360 && clear; ++i) {
      const double a = 2 * M_PI * i / 360;
      clear = footprintDistance(box, path.radius_x * std::cos(a), path.radius_y * std::sin(a)) >=
              options.path_clearance;
    }
    for (size_t j = 5; j < boxes.size() && clear; ++j) {  // keep obstacles apart
      clear = footprintDistance(boxes[j], cx, cy) > std::max(sx, sy) + 0.3;
    }
    if (!clear) continue;
    boxes.push_back(box);
    ++placed;
  }
  return Scene(std::move(boxes), options.seed);
}

common::Box3 Scene::bounds() const {
  common::Box3 bounds;
  for (const auto& box : boxes_) {
    bounds.extend(box.min);
    bounds.extend(box.max);
  }
  return bounds;
}

std::optional<RayHit> Scene::intersect(const Vec3& origin, const Vec3& direction,
                                       double max_t) const {
  const Vec3 inverse = direction.cwiseInverse();
  std::optional<RayHit> best;
  double best_t = max_t;
  for (size_t i = 0; i < boxes_.size(); ++i) {
    const double t = entryDistance(i, origin, inverse);
    if (t > 0 && t <= best_t) {
      best_t = t;
      best = RayHit{t, static_cast<int>(i)};
    }
  }
  return best;
}

double Scene::distanceToSurface(const Vec3& p) const {
  double best = std::numeric_limits<double>::infinity();
  for (const auto& box : boxes_) {
    const Vec3 outside = (box.min - p).cwiseMax(p - box.max).cwiseMax(Vec3::Zero());
    double d = outside.norm();
    if (d == 0) {  // inside: distance to the nearest face
      d = std::min((p - box.min).minCoeff(), (box.max - p).minCoeff());
    }
    best = std::min(best, d);
  }
  return best;
}

void Scene::addMarking(SceneMarking marking) {
  Eigen::AlignedBox2d bounds;
  for (const auto& corner : marking.polygon) bounds.extend(corner);
  marking_bounds_.push_back(bounds);
  markings_.push_back(std::move(marking));
}

}  // namespace stereomap::sim
