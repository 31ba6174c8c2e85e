#include "onboard/sim/scene.hpp"

#include <algorithm>
#include <cmath>
#include <random>

#include "onboard/sim/flight.hpp"

namespace stereomap::sim {

using common::Vec3;

namespace {

uint32_t hash3(int32_t x, int32_t y, int32_t z, uint32_t seed) {
  uint32_t h = seed * 0x9E3779B1u;
  h ^= static_cast<uint32_t>(x) * 0x85EBCA77u;
  h = (h << 13) | (h >> 19);
  h ^= static_cast<uint32_t>(y) * 0xC2B2AE3Du;
  h = (h << 13) | (h >> 19);
  h ^= static_cast<uint32_t>(z) * 0x27D4EB2Fu;
  // murmur3 finaliser
  h ^= h >> 16;
  h *= 0x85EBCA6Bu;
  h ^= h >> 13;
  h *= 0xC2B2AE35u;
  h ^= h >> 16;
  return h;
}

float lattice(int32_t x, int32_t y, int32_t z, uint32_t seed) {
  return static_cast<float>(hash3(x, y, z, seed) & 0xFFFFu) * (1.0f / 65535.0f);
}

float lerp(float a, float b, float t) { return a + (b - a) * t; }

// std::floor as an integer, without its library call (x86-64 has no rounding instruction
// before SSE4.1); the same value for every input in range.
int32_t floorInt(double v) {
  const auto i = static_cast<int32_t>(v);
  return i > v ? i - 1 : i;
}

// Distance in the xy plane from point (px, py) to the rectangle of `box`.
double footprintDistance(const SceneBox& box, double px, double py) {
  const double dx = std::max({box.min.x() - px, 0.0, px - box.max.x()});
  const double dy = std::max({box.min.y() - py, 0.0, py - box.max.y()});
  return std::hypot(dx, dy);
}

// Even-odd rule.
bool insidePolygon(const std::vector<Eigen::Vector2d>& polygon, double x, double y) {
  bool inside = false;
  for (size_t i = 0, j = polygon.size() - 1; i < polygon.size(); j = i++) {
    const Eigen::Vector2d& a = polygon[i];
    const Eigen::Vector2d& b = polygon[j];
    if ((a.y() > y) != (b.y() > y) && x < (b.x() - a.x()) * (y - a.y()) / (b.y() - a.y()) + a.x())
      inside = !inside;
  }
  return inside;
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

float SurfaceShader::valueNoise(const Vec3& p, uint32_t seed, LatticeCell& cell) {
  const int32_t x = floorInt(p.x()), y = floorInt(p.y()), z = floorInt(p.z());
  const double fx = x, fy = y, fz = z;
  const float tx = static_cast<float>(p.x() - fx), ty = static_cast<float>(p.y() - fy),
              tz = static_cast<float>(p.z() - fz);
  if (!cell.lower || x != cell.x || y != cell.y || z != cell.z || seed != cell.seed) {
    cell = {.x = x, .y = y, .z = z, .seed = seed, .lower = true};
    cell.corner = {lattice(x, y, z, seed), lattice(x + 1, y, z, seed), lattice(x, y + 1, z, seed),
                   lattice(x + 1, y + 1, z, seed)};
  }
  const std::array<float, 8>& c = cell.corner;
  const float lower = lerp(lerp(c[0], c[1], tx), lerp(c[2], c[3], tx), ty);
  // On a lattice plane (a deck's top at z = 0) the layer above has no weight: lerp(lower,
  // upper, 0) is `lower` to the bit, so skipping it changes nothing but the time.
  if (tz == 0) return lower;
  if (!cell.upper) {
    cell.corner[4] = lattice(x, y, z + 1, seed);
    cell.corner[5] = lattice(x + 1, y, z + 1, seed);
    cell.corner[6] = lattice(x, y + 1, z + 1, seed);
    cell.corner[7] = lattice(x + 1, y + 1, z + 1, seed);
    cell.upper = true;
  }
  return lerp(lower, lerp(lerp(c[4], c[5], tx), lerp(c[6], c[7], tx), ty), tz);
}

SurfaceShader::Shade SurfaceShader::shade(const Vec3& p, int box, double footprint_m) {
  const SceneBox& surface = scene_.boxes_[box];
  const uint32_t seed = scene_.texture_seed_ * 131u + static_cast<uint32_t>(box);
  // Two octaves: 6 cm detail for matching up close, 25 cm blobs for matching far away. Each
  // fades to its mean (0.5) between lattice spacings of two and one footprints (band-limiting,
  // as procedural textures are anti-aliased), and is not evaluated once gone.
  auto octave = [&](double spacing_m, uint32_t octave_seed, LatticeCell& cell) {
    double weight = 1.0;  // comparisons first: most points need no division
    if (footprint_m >= spacing_m) {
      weight = 0.0;
    } else if (2 * footprint_m > spacing_m) {
      weight = spacing_m / footprint_m - 1.0;
    }
    if (weight == 0) return 0.5f;
    const float value = valueNoise(p * (1.0 / spacing_m), octave_seed, cell);
    return weight == 1 ? value : 0.5f + static_cast<float>(weight) * (value - 0.5f);
  };
  const float fine = octave(0.06, seed, octaves_[0]);
  const float coarse = octave(0.25, seed ^ 0x5bd1e995u, octaves_[1]);
  float albedo = surface.albedo, shade = 1.0f;
  const bool on_top = p.z() >= surface.max.z() - 1e-9;
  for (size_t i = 0; i < scene_.markings_.size() && on_top; ++i) {
    const SceneMarking& marking = scene_.markings_[i];
    if (marking.box == box && scene_.marking_bounds_[i].contains(Eigen::Vector2d(p.x(), p.y())) &&
        insidePolygon(marking.polygon, p.x(), p.y())) {
      if (marking.shade) {
        shade *= marking.albedo;
      } else {
        albedo = marking.albedo;
      }
    }
  }
  albedo *= shade;
  const float value = albedo * (0.25f + 0.45f * fine + 0.55f * coarse);
  return {.grey = std::clamp(value * 255.0f, 0.0f, 255.0f), .albedo = albedo};
}

}  // namespace stereomap::sim
