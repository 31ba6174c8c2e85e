// A synthetic world for the simulated vehicle: axis-aligned boxes (floor, walls, obstacles)
// with a procedural solid texture, so that stereo matching has something to lock onto and
// the exact geometry is known for accuracy tests. Deterministic for a seed.
//
//   Scene room = Scene::makeRoom({.seed = 3});
//   auto hit = room.intersect(origin, direction, 20.0);
#pragma once

#include <cstdint>
#include <optional>
#include <vector>

#include "common/geometry.hpp"

namespace stereomap::sim {

struct SceneBox {
  common::Vec3 min;
  common::Vec3 max;
  float albedo = 0.6f;  // base brightness of the texture, 0..1
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
  // component-wise inverse); negative when the ray misses it or starts inside.
  double entryDistance(size_t box, const common::Vec3& origin,
                       const common::Vec3& inverse_direction) const;
  // Distance from `p` to the nearest box surface (0 on a surface, inside counts as well).
  double distanceToSurface(const common::Vec3& p) const;
  // Grey value (0..255) of the solid texture at a surface point of box `box`.
  uint8_t textureAt(const common::Vec3& p, int box) const;

  void addMarking(SceneMarking marking) { markings_.push_back(std::move(marking)); }

 private:
  std::vector<SceneBox> boxes_;
  std::vector<SceneMarking> markings_;
  uint32_t texture_seed_;
};

}  // namespace stereomap::sim
