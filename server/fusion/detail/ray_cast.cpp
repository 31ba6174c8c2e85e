#include "server/fusion/detail/ray_cast.hpp"

#include <immintrin.h>

#include <algorithm>
#include <cassert>
#include <cmath>
#include <limits>

#include "server/fusion/voxel_code.hpp"

namespace stereomap::fusion::detail {

using octomap::OcTreeKey;
using octomap::point3d;

namespace {

// Where one ray's walk starts: OctoMap's computeRayKeys up to its incremental phase, with the
// same float/double arithmetic so that the walk visits the same voxels. Voxels are linear
// indices into the box; a step along axis i adds move[i] (+-stride, or 0).
struct RayStart {
  double t_max[3], t_delta[3];
  int64_t index, end, move[3];
  float length;
};

// False when there is nothing to mark (an end outside the tree, or origin and end in one
// voxel).
bool startRay(const octomap::OcTree& tree, const point3d& origin, const point3d& end,
              const VoxelBox& box, RayStart& ray) {
  OcTreeKey key_origin, key_end;
  if (!tree.coordToKeyChecked(origin, key_origin) || !tree.coordToKeyChecked(end, key_end)) {
    return false;
  }
  if (key_origin == key_end) return false;
  point3d direction = end - origin;
  ray.length = static_cast<float>(direction.norm());
  // A ray whose length underflows float (an end 1e-38 m from an origin on a voxel border,
  // in another voxel) has no direction: its walk would never end. Found by fuzzing
  // (tests/fuzz/corpus/samples/ray-without-length), as a write past the box.
  if (!(ray.length > 0) || !std::isfinite(ray.length)) return false;
  direction /= ray.length;
  const double resolution = tree.getResolution();
  for (unsigned i = 0; i < 3; ++i) {
    const int step = direction(i) > 0.0 ? 1 : direction(i) < 0.0 ? -1 : 0;
    if (step != 0) {
      double border = tree.keyToCoord(key_origin[i]);
      border += static_cast<float>(step * resolution * 0.5);
      ray.t_max[i] = (border - origin(i)) / direction(i);
      ray.t_delta[i] = resolution / std::fabs(direction(i));
    } else {
      ray.t_max[i] = ray.t_delta[i] = std::numeric_limits<double>::max();
    }
    ray.move[i] = step * box.stride(i);
  }
  ray.index =
      box.index(key_origin[0] - box.min[0], key_origin[1] - box.min[1], key_origin[2] - box.min[2]);
  ray.end = box.index(key_end[0] - box.min[0], key_end[1] - box.min[1], key_end[2] - box.min[2]);
  return true;
}

// Hands out the rays [from, to) that have something to mark, marking each one's origin
// voxel as it starts. Each of `streams` walkers (lanes) takes its rays from its own share of
// the range while it lasts, then from the others': walkers with neighbouring rays would mark
// the same words at the same time, and a read-modify-write waiting on another to the same
// word was most of the vector kernel's time.
class RaySource {
 public:
  RaySource(const octomap::OcTree& tree, const point3d& origin, const std::vector<point3d>& ends,
            size_t from, size_t to, unsigned streams, const VoxelBox& box, uint64_t* bits)
      : tree_(tree), origin_(origin), ends_(ends), box_(box), bits_(bits) {
    for (unsigned k = 0; k < streams; ++k) {
      shares_.push_back({from + (to - from) * k / streams, from + (to - from) * (k + 1) / streams});
    }
  }
  bool next(unsigned stream, RayStart& ray) {
    for (size_t k = 0; k < shares_.size(); ++k) {
      Share& share = shares_[(stream + k) % shares_.size()];
      while (share.next < share.to) {
        if (startRay(tree_, origin_, ends_[share.next++], box_, ray)) {
          bits_[ray.index >> 6] |= uint64_t{1} << (ray.index & 63);
          return true;
        }
      }
    }
    return false;
  }

 private:
  struct Share {
    size_t next, to;
  };
  const octomap::OcTree& tree_;
  const point3d& origin_;
  const std::vector<point3d>& ends_;
  const VoxelBox& box_;
  uint64_t* bits_;
  std::vector<Share> shares_;
};

// Why a walk stays inside the box with its margin of one voxel (asserted in debug builds
// only, the walk being the hot loop; AddressSanitizer sees any write outside): a voxel is
// entered only while the ray's parameter is within its length, so every voxel walked touches
// the segment up to rounding; coordinates are floats over a tree of 2^16 voxels a side, so
// rounding is below 1/256 of a voxel, and a walk can end at most one voxel outside the
// segment's voxels. Inside the box, equal indices are equal keys: reaching the end index is
// reaching OctoMap's end key.

// One ray's walk, scalar.
class RayWalk {
 public:
  void start(const RayStart& ray, const VoxelBox& box) {
    t0_ = ray.t_max[0], t1_ = ray.t_max[1], t2_ = ray.t_max[2];
    d0_ = ray.t_delta[0], d1_ = ray.t_delta[1], d2_ = ray.t_delta[2];
    m0_ = ray.move[0], m1_ = ray.move[1], m2_ = ray.move[2];
    index_ = ray.index, end_ = ray.end;
    length_ = ray.length;
    limit_ = static_cast<uint64_t>(box.words()) * 64;
  }

  // One voxel further; false when the ray is done, else the voxel to mark is the current
  // one. The next axis is the smallest t_max, ties going to the later axis (as OctoMap),
  // chosen with selects instead of branches: the choice is unpredictable, and a mispredicted
  // branch per voxel was most of the cost.
  bool advance() {
    const bool x_first = t0_ < t1_;
    const bool z_next = !((x_first ? t0_ : t1_) < t2_);
    const bool x_next = x_first && !z_next;
    const bool y_next = !x_first && !z_next;
    index_ += x_next ? m0_ : y_next ? m1_ : m2_;
    t0_ += x_next ? d0_ : 0.0;
    t1_ += y_next ? d1_ : 0.0;
    t2_ += z_next ? d2_ : 0.0;
    if (index_ == end_) return false;
    return !(std::min(std::min(t0_, t1_), t2_) > length_);
  }
  void mark(uint64_t* words) const {
    assert(static_cast<uint64_t>(index_) < limit_);
    words[index_ >> 6] |= uint64_t{1} << (index_ & 63);
  }

 private:
  double t0_, t1_, t2_, d0_, d1_, d2_;
  int64_t m0_, m1_, m2_, index_, end_;
  uint64_t limit_;  // voxels in the box
  float length_;
};

// Two rays are walked in turns: each walk is one long chain of dependent steps, and two of
// them keep the core busier.
void castRaysScalar(RaySource& source, const VoxelBox& box, uint64_t* bits) {
  RayStart ray;
  RayWalk a, b;
  auto load = [&](RayWalk& walk) {
    if (!source.next(&walk == &a ? 0 : 1, ray)) return false;
    walk.start(ray, box);
    return true;
  };
  bool a_live = load(a), b_live = load(b);
  while (a_live && b_live) {
    if (a.advance()) {
      a.mark(bits);
    } else {
      a_live = load(a);
    }
    if (b.advance()) {
      b.mark(bits);
    } else {
      b_live = load(b);
    }
  }
  for (RayWalk* walk : {&a, &b}) {
    for (bool live = walk == &a ? a_live : b_live; live;) {
      if (walk->advance()) {
        walk->mark(bits);
      } else {
        live = load(*walk);
      }
    }
  }
}

// Four rays in the lanes of AVX2 registers, stepped together by the scalar walk's rule
// (lane for lane the same compares, selects and additions, in doubles, no fused
// multiply-add); a lane whose ray ends takes the next ray. Indices are 64-bit lanes so that
// the compare masks of the doubles select them directly. What a step changes (LaneState)
// stays in registers; what it only reads (LaneRays) is read from memory, for two groups'
// state and temporaries to fit AVX2's sixteen registers.
struct LaneState {
  __m256d t0, t1, t2;
  __m256i index;
};
struct LaneRays {
  __m256d d0, d1, d2, length;
  __m256i end, m0, m1, m2;
  unsigned idle = 0xF;  // lanes with no ray left to take
};

// One step of every lane; marks the voxels of the lanes whose ray goes on and returns the
// lanes whose ray ended (idle ones included).
__attribute__((target("avx2"), always_inline)) inline unsigned stepLanes(LaneState& s,
                                                                         const LaneRays& r,
                                                                         uint64_t* bits) {
  const __m256d x_first = _mm256_cmp_pd(s.t0, s.t1, _CMP_LT_OQ);
  const __m256d first = _mm256_blendv_pd(s.t1, s.t0, x_first);
  const __m256d z_next = _mm256_cmp_pd(first, s.t2, _CMP_NLT_UQ);
  const __m256d x_next = _mm256_andnot_pd(z_next, x_first);
  const __m256d y_next =
      _mm256_andnot_pd(_mm256_or_pd(z_next, x_first), _mm256_castsi256_pd(_mm256_set1_epi64x(-1)));
  s.t0 = _mm256_add_pd(s.t0, _mm256_and_pd(x_next, r.d0));
  s.t1 = _mm256_add_pd(s.t1, _mm256_and_pd(y_next, r.d1));
  s.t2 = _mm256_add_pd(s.t2, _mm256_and_pd(z_next, r.d2));
  // The move of the chosen axis: x's or y's, then z's where z is next.
  const __m256d xy_move =
      _mm256_blendv_pd(_mm256_castsi256_pd(r.m1), _mm256_castsi256_pd(r.m0), x_first);
  s.index = _mm256_add_epi64(
      s.index, _mm256_castpd_si256(_mm256_blendv_pd(xy_move, _mm256_castsi256_pd(r.m2), z_next)));
  const __m256d nearest = _mm256_min_pd(_mm256_min_pd(s.t0, s.t1), s.t2);
  const __m256i done =
      _mm256_or_si256(_mm256_cmpeq_epi64(s.index, r.end),
                      _mm256_castpd_si256(_mm256_cmp_pd(nearest, r.length, _CMP_GT_OQ)));
  // Word and bit of each lane's voxel; a finished lane ORs nothing into word 0.
  const __m256i word = _mm256_andnot_si256(done, _mm256_srli_epi64(s.index, 6));
  const __m256i mask = _mm256_andnot_si256(
      done,
      _mm256_sllv_epi64(_mm256_set1_epi64x(1), _mm256_and_si256(s.index, _mm256_set1_epi64x(63))));
  alignas(32) uint64_t words[4], masks[4];
  _mm256_store_si256(reinterpret_cast<__m256i*>(words), word);
  _mm256_store_si256(reinterpret_cast<__m256i*>(masks), mask);
  bits[words[0]] |= masks[0];
  bits[words[1]] |= masks[1];
  bits[words[2]] |= masks[2];
  bits[words[3]] |= masks[3];
  return static_cast<unsigned>(_mm256_movemask_pd(_mm256_castsi256_pd(done)));
}

__attribute__((target("avx2"))) void blendLane(__m256d& v, double value, __m256d select) {
  v = _mm256_blendv_pd(v, _mm256_set1_pd(value), select);
}
__attribute__((target("avx2"))) void blendLane(__m256i& v, int64_t value, __m256i select) {
  v = _mm256_blendv_epi8(v, _mm256_set1_epi64x(value), select);
}

// Gives each lane of `lanes` the next ray, or makes it idle: a ray of zeros does not move and
// is at its end, so it is finished at every step and marks nothing. Each register blends the
// ray's value into the lane (storing the registers and loading them back after a scalar
// store would stall on store forwarding).
__attribute__((target("avx2"), noinline)) void refillLanes(RaySource& source, unsigned group,
                                                           unsigned lanes, LaneState& s,
                                                           LaneRays& r) {
  RayStart ray;
  for (; lanes != 0; lanes &= lanes - 1) {
    const auto lane = static_cast<unsigned>(__builtin_ctz(lanes));
    if (source.next(4 * group + lane, ray)) {
      r.idle &= ~(1u << lane);
    } else {
      ray = RayStart{};
      r.idle |= 1u << lane;
    }
    const __m256i select = _mm256_cmpeq_epi64(_mm256_set_epi64x(3, 2, 1, 0),
                                              _mm256_set1_epi64x(static_cast<int64_t>(lane)));
    const __m256d select_pd = _mm256_castsi256_pd(select);
    blendLane(s.t0, ray.t_max[0], select_pd), blendLane(s.t1, ray.t_max[1], select_pd);
    blendLane(s.t2, ray.t_max[2], select_pd), blendLane(s.index, ray.index, select);
    blendLane(r.d0, ray.t_delta[0], select_pd), blendLane(r.d1, ray.t_delta[1], select_pd);
    blendLane(r.d2, ray.t_delta[2], select_pd), blendLane(r.length, ray.length, select_pd);
    blendLane(r.end, ray.end, select), blendLane(r.m0, ray.move[0], select);
    blendLane(r.m1, ray.move[1], select), blendLane(r.m2, ray.move[2], select);
  }
}

// Two groups of four lanes stepped in turns, as the scalar kernel walks two rays: eight
// dependency chains in flight. The loop's state is in locals whose address is never taken,
// so that it stays in registers.
__attribute__((target("avx2"))) void castRaysAvx2(RaySource& source, uint64_t* bits) {
  LaneRays ra{}, rb{};
  LaneState a{}, b{};
  {
    LaneState fill{};
    refillLanes(source, 0, 0xF, fill, ra);
    a = fill;
    refillLanes(source, 1, 0xF, fill, rb);
    b = fill;
  }
  while (ra.idle != 0xF || rb.idle != 0xF) {
    if (const unsigned ended = stepLanes(a, ra, bits) & ~ra.idle; ended != 0) {
      LaneState fill = a;
      refillLanes(source, 0, ended, fill, ra);
      a = fill;
    }
    if (const unsigned ended = stepLanes(b, rb, bits) & ~rb.idle; ended != 0) {
      LaneState fill = b;
      refillLanes(source, 1, ended, fill, rb);
      b = fill;
    }
  }
}

// Bit of a voxel in its brick's word: the Morton code of its 2-bit coordinates.
constexpr unsigned brickBit(unsigned dx, unsigned dy, unsigned dz) {
  return (dx & 1) | (dy & 1) << 1 | (dz & 1) << 2 | (dx & 2) << 2 | (dy & 2) << 3 | (dz & 2) << 4;
}

// The four bits of a z row's nibble (dz = 0..3) at their Morton places for dx = dy = 0.
constexpr std::array<uint64_t, 16> kRowBits = [] {
  std::array<uint64_t, 16> bits{};
  for (unsigned nibble = 0; nibble < 16; ++nibble) {
    for (unsigned dz = 0; dz < 4; ++dz) {
      if ((nibble >> dz) & 1) bits[nibble] |= uint64_t{1} << brickBit(0, 0, dz);
    }
  }
  return bits;
}();

}  // namespace

RayKernel bestRayKernel() {
  static const RayKernel kernel =
      __builtin_cpu_supports("avx2") ? RayKernel::kAvx2 : RayKernel::kScalar;
  return kernel;
}

void castRays(const octomap::OcTree& tree, const point3d& origin, const std::vector<point3d>& ends,
              size_t from, size_t to, const VoxelBox& box, uint64_t* bits, RayKernel kernel) {
  if (kernel == RayKernel::kAuto) kernel = bestRayKernel();
  RaySource source(tree, origin, ends, from, to, kernel == RayKernel::kAvx2 ? 8 : 2, box, bits);
  if (kernel == RayKernel::kAvx2) {
    castRaysAvx2(source, bits);
  } else {
    castRaysScalar(source, box, bits);
  }
}

VoxelBox VoxelBox::around(const std::array<int, 3>& lo, const std::array<int, 3>& hi) {
  constexpr std::array<int, 3> kMultiple{4, 4, 64};
  VoxelBox box;
  for (unsigned a = 0; a < 3; ++a) {
    box.min[a] = lo[a] & ~3;
    const int span = hi[a] - box.min[a] + 1;
    box.size[a] = (span + kMultiple[a] - 1) / kMultiple[a] * kMultiple[a];
  }
  return box;
}

void collectBricks(const VoxelBox& box, const std::vector<const uint64_t*>& free_sets,
                   const std::vector<const uint64_t*>& occupied_sets, int bx_begin, int bx_end,
                   std::vector<TouchedBrick>& bricks) {
  bricks.clear();
  const size_t row_words = static_cast<size_t>(box.size[2]) / 64;
  auto union_of = [](const std::vector<const uint64_t*>& sets, size_t w) {
    uint64_t bits = 0;
    for (const uint64_t* set : sets) bits |= set[w];
    return bits;
  };
  // Bricks along x and y, a word of z rows (16 bricks) at a time: first the union of the
  // 16 rows, whose nibbles say which of the 16 bricks were touched at all.
  for (int bx = bx_begin; bx < std::min(bx_end, box.size[0] / 4); ++bx) {
    for (int by = 0; by < box.size[1] / 4; ++by) {
      size_t rows[16];
      for (unsigned d = 0; d < 16; ++d) {
        const auto x = static_cast<size_t>(4 * bx + (d & 3)),
                   y = static_cast<size_t>(4 * by + (d >> 2));
        rows[d] = (x * box.size[1] + y) * row_words;
      }
      for (size_t w = 0; w < row_words; ++w) {
        uint64_t union_bits = 0;
        for (const size_t row : rows) {
          union_bits |= union_of(free_sets, row + w) | union_of(occupied_sets, row + w);
        }
        while (union_bits != 0) {
          const unsigned nibble = static_cast<unsigned>(__builtin_ctzll(union_bits)) / 4;
          union_bits &= ~(uint64_t{0xF} << (4 * nibble));
          TouchedBrick brick{};
          for (unsigned d = 0; d < 16; ++d) {
            const unsigned place = brickBit(d & 3, d >> 2, 0);
            const size_t word = rows[d] + w;
            const uint64_t occupied = union_of(occupied_sets, word);
            brick.any |= kRowBits[(union_of(free_sets, word) | occupied) >> (4 * nibble) & 0xF]
                         << place;
            brick.occupied |= kRowBits[occupied >> (4 * nibble) & 0xF] << place;
          }
          const int bz = static_cast<int>(16 * w + nibble);
          brick.code = mortonOfKeys(static_cast<uint32_t>(box.min[0] / 4 + bx),
                                    static_cast<uint32_t>(box.min[1] / 4 + by),
                                    static_cast<uint32_t>(box.min[2] / 4 + bz));
          bricks.push_back(brick);
        }
      }
    }
  }
}

}  // namespace stereomap::fusion::detail
