// Ray casting of the fast insertion path (internal to server/fusion): the voxels OctoMap's
// computeRayKeys visits for each ray, marked in a dense bitset over the cloud's box, and the
// touched voxels listed brick by brick in Morton order for the tree update.
//
// Two kernels walk the same rays with the same arithmetic (OctoMap's: float ends and lengths,
// double parameters accumulated step by step) and mark the same bits: a scalar one, and one
// that walks eight rays at once in AVX2 lanes, chosen at run time when the CPU has AVX2. A
// walk tracks one linear index into the box (a step along an axis adds that axis's stride),
// so each step is a handful of operations whatever the axis.
#pragma once

#include <octomap/OcTree.h>

#include <array>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace stereomap::fusion::detail {

// The voxels an update can touch: a box of keys whose corner is a multiple of 4 on each axis
// and whose sides are multiples of 4 (x, y) and of 64 (z), one bit per voxel, z fastest:
// voxel (rx, ry, rz) relative to the corner is bit `index` = (rx * size[1] + ry) * size[2] + rz,
// in word index / 64. A word holds 64 voxels of one z row, sixteen 4-voxel steps of bricks.
struct VoxelBox {
  std::array<int, 3> min{};   // first key of the box
  std::array<int, 3> size{};  // voxels along each axis
  // The box over keys [lo, hi] on each axis (inside the tree's 2^16 keys).
  static VoxelBox around(const std::array<int, 3>& lo, const std::array<int, 3>& hi);
  size_t words() const { return static_cast<size_t>(size[0]) * size[1] * size[2] / 64; }
  int64_t stride(unsigned axis) const {
    return axis == 2 ? 1 : axis == 1 ? size[2] : static_cast<int64_t>(size[1]) * size[2];
  }
  int64_t index(int rx, int ry, int rz) const {  // keys relative to the box
    return (static_cast<int64_t>(rx) * size[1] + ry) * size[2] + rz;
  }
};

inline void markVoxel(uint64_t* words, const VoxelBox& box, int rx, int ry, int rz) {
  const int64_t index = box.index(rx, ry, rz);
  words[index >> 6] |= uint64_t{1} << (index & 63);
}

// A 4x4x4 brick of touched voxels: `any` (free or occupied) and `occupied`, one bit per
// voxel in Morton order (bit = Morton code of its 2-bit coordinates).
struct TouchedBrick {
  uint64_t code;  // Morton code of the brick (of its keys / 4)
  uint64_t any, occupied;
};

// The bricks with a marked voxel in any of `free_sets` or `occupied_sets`, in box order, of
// the box's bricks bx_begin <= x / 4 < bx_end (a share of the work for one thread).
void collectBricks(const VoxelBox& box, const std::vector<const uint64_t*>& free_sets,
                   const std::vector<const uint64_t*>& occupied_sets, int bx_begin, int bx_end,
                   std::vector<TouchedBrick>& bricks);

enum class RayKernel { kAuto, kScalar, kAvx2 };

// The kernel kAuto picks on this CPU.
RayKernel bestRayKernel();

// Marks in `bits` (box.words() words) the voxels of the rays origin -> ends[from..to), each
// as OctoMap's computeRayKeys walks it, origin voxel included, end voxel excluded.
void castRays(const octomap::OcTree& tree, const octomap::point3d& origin,
              const std::vector<octomap::point3d>& ends, size_t from, size_t to,
              const VoxelBox& box, uint64_t* bits, RayKernel kernel = RayKernel::kAuto);

}  // namespace stereomap::fusion::detail
