// What a Scene's surfaces look like: a procedural solid texture (two octaves of value noise,
// band-limited to a pixel's footprint) under the paint of its markings. The renderer's inner
// loop, so the path every ray takes is inline here.
//
//   SurfaceShader shader(scene);               // one per thread
//   float grey = shader.shade(p, hit.box, footprint_m).grey;
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <cstring>
#include <vector>

#include "onboard/sim/detail/lanes.hpp"
#include "onboard/sim/scene.hpp"

namespace stereomap::sim {

namespace detail {

// A lattice point's hash: of one point (uint32_t) or of four in lanes (U4), the same bits.
template <class U>
inline U hash3(U x, U y, U z, U seed) {
  U h = seed * 0x9E3779B1u;
  h ^= x * 0x85EBCA77u;
  h = (h << 13) | (h >> 19);
  h ^= y * 0xC2B2AE3Du;
  h = (h << 13) | (h >> 19);
  h ^= z * 0x27D4EB2Fu;
  // murmur3 finaliser
  h ^= h >> 16;
  h *= 0x85EBCA6Bu;
  h ^= h >> 13;
  h *= 0xC2B2AE35u;
  h ^= h >> 16;
  return h;
}

// The noise's value at a lattice point, in [0, 1].
inline float lattice(int32_t x, int32_t y, int32_t z, uint32_t seed) {
  return static_cast<float>(hash3(static_cast<uint32_t>(x), static_cast<uint32_t>(y),
                                  static_cast<uint32_t>(z), seed) &
                            0xFFFFu) *
         (1.0f / 65535.0f);
}
// The same in lanes.
inline F4 lattice4(U4 x, U4 y, U4 z, U4 seed) {
  return toFloat(reinterpret_cast<I4>(hash3(x, y, z, seed) & 0xFFFFu)) * (1.0f / 65535.0f);
}

inline float lerp(float a, float b, float t) { return a + (b - a) * t; }

// std::floor as an integer, without its library call (x86-64 has no rounding instruction
// before SSE4.1); the same value for every input in range.
inline int32_t floorInt(double v) {
  const auto i = static_cast<int32_t>(v);
  return i > v ? i - 1 : i;
}

}  // namespace detail

// Shades surface points of a Scene, keeping the texture's lattice values of the cells it last
// used: consecutive pixels of a row mostly fall in the same cells and then need no hashing.
// Not thread-safe: one per thread (it is small).
class SurfaceShader {
 public:
  explicit SurfaceShader(const Scene& scene);

  struct Shade {
    float grey = 0;  // 0..255, not rounded
    // The albedo there: the box's, or its paint's, times any shadow on it. It changes only at
    // a marking's edge, which is what anti-aliasing looks for.
    float albedo = 0;
  };
  // Box `box`'s surface at `p`. `footprint_m`: the pixel's size on the surface; each octave of
  // the texture fades to its mean as its lattice spacing shrinks from two footprints to one, so
  // that detail finer than the pixels does not alias into noise (0: the exact texture).
  Shade shade(const common::Vec3& p, int box, double footprint_m = 0) {
    const SceneBox& surface = scene_.boxes_[box];
    const uint32_t seed = scene_.texture_seed_ * 131u + static_cast<uint32_t>(box);
    // Two octaves: 6 cm detail for matching up close, 25 cm blobs for matching far away.
    const float fine = octave(0.06, p, footprint_m, seed, octaves_[0]);
    const float coarse = octave(0.25, p, footprint_m, seed ^ 0x5bd1e995u, octaves_[1]);
    float albedo = surface.albedo, shade = 1.0f;
    if (paint_bounds_[box].contains(Eigen::Vector2d(p.x(), p.y())) &&
        p.z() >= surface.max.z() - 1e-9) {
      paint(box, p, albedo, shade);
    }
    albedo *= shade;
    const float value = albedo * (0.25f + 0.45f * fine + 0.55f * coarse);
    return {.grey = std::clamp(value * 255.0f, 0.0f, 255.0f), .albedo = albedo};
  }

  // Four points at once (the renderer's first pass), in floats: shade() of each within the
  // rounding of a float (the texture within a hundredth of a grey level; the albedo exact).
  // Lanes whose `box` is negative are left as they are in `grey` and `albedo`; the others' come
  // in `albedo` as their box's. `top`: the lanes on their box's top face (where paint may be).
  STEREOMAP_LANES_CLONES void shade4(detail::F4 x, detail::F4 y, detail::F4 z, detail::I4 box,
                                     detail::I4 top, detail::F4 footprint_m, detail::F4& grey,
                                     detail::F4& albedo) {
    using namespace detail;
    const I4 hit = box >= 0;
    const uint32_t seed = scene_.texture_seed_ * 131u;  // plus the box, as in shade()
    const F4 fine = octave4(0.06f, x, y, z, footprint_m, seed, 0, box, hit);
    const F4 coarse = octave4(0.25f, x, y, z, footprint_m, seed, 0x5bd1e995u, box, hit);
    if (any(top)) {
      alignas(16) std::array<float, 4> painted;
      std::memcpy(painted.data(), &albedo, sizeof(albedo));
      for (int l = 0; l < 4; ++l) {
        if (top[l] == 0 || !paint_bounds_[box[l]].contains(Eigen::Vector2d(x[l], y[l]))) continue;
        float shade = 1.0f;
        paint(box[l], common::Vec3(x[l], y[l], z[l]), painted[l], shade);
        painted[l] *= shade;
      }
      std::memcpy(&albedo, painted.data(), sizeof(albedo));
    }
    const F4 value = albedo * (0.25f + 0.45f * fine + 0.55f * coarse);
    grey = select(hit, detail::min(detail::max(value * 255.0f, splat(0.0f)), splat(255.0f)), grey);
  }

 private:
  // The value noise's lattice values around one cell: the layer at z (corners 0-3) and the
  // layer at z + 1 (corners 4-7), each filled when a point first needs it.
  struct alignas(64) LatticeCell {  // a cache line each
    int32_t x = 0, y = 0, z = 0;
    uint32_t seed = 0;
    std::array<bool, 2> filled{};  // the layers at z and z + 1
    std::array<float, 8> corner{};
  };
  // The cells an octave used last, direct-mapped: a row of pixels steps through cells that the
  // rows above it used too, so most cells need no hashing (4 lattice values each).
  class LatticeCells {
   public:
    LatticeCells() = default;
    LatticeCells(const LatticeCells&) = delete;  // last_ may point at its own none_
    LatticeCells& operator=(const LatticeCells&) = delete;
    // The cell (x, y, z) of `seed`, its values kept if it was used last or is still held,
    // else emptied for them. The table is made on the first cell asked for: a shader whose
    // points all go through shade4() never needs it.
    LatticeCell& at(int32_t x, int32_t y, int32_t z, uint32_t seed) {
      if (last_->x == x && last_->y == y && last_->z == z && last_->seed == seed) return *last_;
      if (cells_.empty()) cells_.resize(kSize);
      const uint32_t slot =
          (static_cast<uint32_t>(x) * 0x9E3779B1u ^ static_cast<uint32_t>(y) * 0x85EBCA77u ^
           static_cast<uint32_t>(z) * 0xC2B2AE3Du ^ seed) >>
          (32 - kBits);
      last_ = &cells_[slot];
      if (last_->x != x || last_->y != y || last_->z != z || last_->seed != seed) {
        *last_ = {.x = x, .y = y, .z = z, .seed = seed};
      }
      return *last_;
    }

   private:
    static constexpr int kBits = 10;
    static constexpr size_t kSize = size_t{1} << kBits;
    std::vector<LatticeCell> cells_;
    LatticeCell none_;  // matches (0, 0, 0, seed 0) with nothing filled, as an empty slot does
    LatticeCell* last_ = &none_;
  };

  // One octave (lattice spacing in metres) at `p`: it fades to its mean (0.5) between lattice
  // spacings of two and one footprints (band-limiting, as procedural textures are anti-aliased),
  // and is not evaluated once gone.
  static float octave(double spacing_m, const common::Vec3& p, double footprint_m, uint32_t seed,
                      LatticeCells& cells) {
    double weight = 1.0;  // comparisons first: most points need no division
    if (footprint_m >= spacing_m) {
      weight = 0.0;
    } else if (2 * footprint_m > spacing_m) {
      weight = spacing_m / footprint_m - 1.0;
    }
    if (weight == 0) return 0.5f;
    const double scale = 1.0 / spacing_m;
    const float value = valueNoise(p.x() * scale, p.y() * scale, p.z() * scale, seed, cells);
    return weight == 1 ? value : 0.5f + static_cast<float>(weight) * (value - 0.5f);
  }

  // Trilinear value noise in [0, 1] with unit lattice spacing at (x, y, z), with the lattice
  // values of `cells` (an octave's).
  static float valueNoise(double x, double y, double z, uint32_t seed, LatticeCells& cells) {
    using detail::lerp;
    const int32_t ix = detail::floorInt(x), iy = detail::floorInt(y), iz = detail::floorInt(z);
    const float tx = static_cast<float>(x - ix), ty = static_cast<float>(y - iy),
                tz = static_cast<float>(z - iz);
    LatticeCell& cell = cells.at(ix, iy, iz, seed);
    fillLayer(cell, 0);
    const std::array<float, 8>& c = cell.corner;
    const float lower = lerp(lerp(c[0], c[1], tx), lerp(c[2], c[3], tx), ty);
    // On a lattice plane (a deck's top at z = 0) the layer above has no weight: lerp(lower,
    // upper, 0) is `lower` to the bit, so skipping it changes nothing but the time.
    if (tz == 0) return lower;
    fillLayer(cell, 1);
    return lerp(lower, lerp(lerp(c[4], c[5], tx), lerp(c[6], c[7], tx), ty), tz);
  }
  // A cell's lattice values on layer 0 (its z: corners 0-3) or 1 (z + 1: corners 4-7), hashed
  // when first needed.
  static void fillLayer(LatticeCell& cell, int layer) {
    if (cell.filled[layer]) return;
    using detail::lattice;
    const int32_t x = cell.x, y = cell.y, z = cell.z + layer;
    float* corner = &cell.corner[4 * layer];
    corner[0] = lattice(x, y, z, cell.seed);
    corner[1] = lattice(x + 1, y, z, cell.seed);
    corner[2] = lattice(x, y + 1, z, cell.seed);
    corner[3] = lattice(x + 1, y + 1, z, cell.seed);
    cell.filled[layer] = true;
  }

  // octave() on four lanes in floats; `active`: the lanes to evaluate.
  // A lane's seed is (seed + its box) ^ seed_xor, as shade()'s.
  static detail::F4 octave4(float spacing_m, detail::F4 x, detail::F4 y, detail::F4 z,
                            detail::F4 footprint_m, uint32_t seed, uint32_t seed_xor,
                            detail::I4 box, detail::I4 active) {
    using namespace detail;
    const F4 spacing = splat(spacing_m);
    const F4 weight =
        select(footprint_m >= spacing, splat(0.0f),
               select(2.0f * footprint_m > spacing, spacing / footprint_m - 1.0f, splat(1.0f)));
    active &= weight != 0.0f;
    if (!any(active)) return splat(0.5f);
    const U4 seeds = (seed + reinterpret_cast<U4>(box)) ^ seed_xor;
    const float scale = static_cast<float>(1.0 / spacing_m);
    const F4 value = valueNoise4(x * scale, y * scale, z * scale, seeds, active);
    return select(weight == 1.0f, value, 0.5f + weight * (value - 0.5f));
  }

  // valueNoise() on four lanes in floats; a lane not `active` gives 0.5.
  static detail::F4 valueNoise4(detail::F4 x, detail::F4 y, detail::F4 z, detail::U4 seed,
                                detail::I4 active) {
    using namespace detail;
    const I4 ix = floorInt(x), iy = floorInt(y), iz = floorInt(z);
    const F4 tx = x - toFloat(ix), ty = y - toFloat(iy), tz = z - toFloat(iz);
    // The lattice values hashed in lanes, each lane its own cell's corner: without branches,
    // faster than looking the cells up (whose misses a row's lanes cannot predict).
    const U4 x0 = reinterpret_cast<U4>(ix), y0 = reinterpret_cast<U4>(iy),
             z0 = reinterpret_cast<U4>(iz);
    const F4 lower =
        lerp4(lerp4(lattice4(x0, y0, z0, seed), lattice4(x0 + 1, y0, z0, seed), tx),
              lerp4(lattice4(x0, y0 + 1, z0, seed), lattice4(x0 + 1, y0 + 1, z0, seed), tx), ty);
    // On a lattice plane (a deck's top) the layer above has no weight, as in valueNoise().
    const I4 flat = tz == 0.0f;
    F4 value = lower;
    if (!all(flat | ~active)) {
      const U4 z1 = z0 + 1;
      const F4 upper =
          lerp4(lerp4(lattice4(x0, y0, z1, seed), lattice4(x0 + 1, y0, z1, seed), tx),
                lerp4(lattice4(x0, y0 + 1, z1, seed), lattice4(x0 + 1, y0 + 1, z1, seed), tx), ty);
      value = select(flat, lower, lerp4(lower, upper, tz));
    }
    return select(active, value, splat(0.5f));
  }
  static detail::F4 lerp4(detail::F4 a, detail::F4 b, detail::F4 t) { return a + (b - a) * t; }

  // The markings' paint at `p` on box `box`'s top face: sets `albedo` where one is painted and
  // multiplies `shade` by each shadow over it.
  void paint(int box, const common::Vec3& p, float& albedo, float& shade) const;

  const Scene& scene_;
  std::vector<Eigen::AlignedBox2d> paint_bounds_;  // per box: around all its markings' paint
  std::array<LatticeCells, 2> octaves_;            // fine, coarse
};

}  // namespace stereomap::sim
