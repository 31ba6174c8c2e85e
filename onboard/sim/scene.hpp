// A synthetic world for the simulated vehicle: axis-aligned boxes (floor, walls, obstacles)
// with a procedural solid texture, so that stereo matching has something to lock onto and
// the exact geometry is known for accuracy tests. Deterministic for a seed.
//
//   Scene room = Scene::makeRoom({.seed = 3});
//   auto hit = room.intersect(origin, direction, 20.0);
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <vector>

#include "common/geometry.hpp"

namespace stereomap::sim {

struct SceneBox {
  common::Vec3 min;
  common::Vec3 max;
  float albedo = 0.6f;  // base brightness of the texture, 0..1

  // Corner `i` of 8: bit 0 of `i` picks max x over min x, bit 1 max y, bit 2 max z.
  common::Vec3 corner(int i) const {
    return {(i & 1) ? max.x() : min.x(), (i & 2) ? max.y() : min.y(), (i & 4) ? max.z() : min.z()};
  }
};

// Paint on the top face of a box (a landing pad's T on a deck): a polygon in the face's x, y
// (map frame), drawn at `albedo` with the box's texture still showing through; or, with
// `shade`, a shadow that multiplies whatever is there by `albedo`.
struct SceneMarking {
  int box = 0;
  std::vector<Eigen::Vector2d> polygon;
  float albedo = 0.08f;
  bool shade = false;
};

struct RayHit {
  double t = 0;  // distance along the (not necessarily unit) direction
  int box = -1;
};

class Scene {
 public:
  struct RoomOptions {
    uint32_t seed = 1;
    double length = 12.0;  // x extent of the room, metres
    double width = 10.0;   // y extent
    double wall_height = 3.0;
    int obstacles = 10;
    // Obstacles keep this far from the flight ellipse (Flight's defaults) so it stays clear.
    double path_clearance = 0.9;
  };

  explicit Scene(std::vector<SceneBox> boxes, uint32_t texture_seed = 1);
  // A walled room with a floor (no ceiling) and seeded random obstacle boxes.
  static Scene makeRoom(const RoomOptions& options);

  const std::vector<SceneBox>& boxes() const { return boxes_; }
  common::Box3 bounds() const;

  // Nearest hit of origin + t * direction with t in (0, max_t]; nullopt when nothing is hit.
  std::optional<RayHit> intersect(const common::Vec3& origin, const common::Vec3& direction,
                                  double max_t) const;
  // Ray parameter t where origin + t * direction enters box `box` (direction given by its
  // component-wise inverse); negative when the ray misses it or starts inside. Inline: it is
  // the renderer's innermost loop.
  double entryDistance(size_t box, const common::Vec3& origin,
                       const common::Vec3& inverse_direction) const {
    // Slab test; an origin inside the box sees nothing of it (returns a negative value).
    const common::Vec3 t0 = (boxes_[box].min - origin).cwiseProduct(inverse_direction);
    const common::Vec3 t1 = (boxes_[box].max - origin).cwiseProduct(inverse_direction);
    const double t_near = t0.cwiseMin(t1).maxCoeff();
    const double t_far = t0.cwiseMax(t1).minCoeff();
    return t_near <= t_far ? t_near : -1.0;
  }
  // Distance from `p` to the nearest box surface (0 on a surface, inside counts as well).
  double distanceToSurface(const common::Vec3& p) const;

  // Paint on a box's top face; what a surface point looks like is SurfaceShader's.
  void addMarking(SceneMarking marking);
  const std::vector<SceneMarking>& markings() const { return markings_; }

 private:
  friend class SurfaceShader;

  std::vector<SceneBox> boxes_;
  std::vector<SceneMarking> markings_;
  std::vector<Eigen::AlignedBox2d> marking_bounds_;  // each polygon's, to skip it cheaply
  uint32_t texture_seed_;
};

}  // namespace stereomap::sim
