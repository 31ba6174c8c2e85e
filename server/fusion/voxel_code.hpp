// Voxel indices and their Morton codes, the order in which the map lists voxels and cuts
// them into tiles: a voxel's code interleaves the bits of its OctoMap key (index + 32768 on
// each axis, 16 bits), x lowest. Voxels of one octree node (and so of one tile) have
// consecutive codes, and sorting by code lists them depth first.
//
//   const uint64_t code = voxelCode({x, y, z});
//   const VoxelIndex v = voxelOfCode(code);
#pragma once

#include <compare>
#include <cstdint>

namespace stereomap::fusion {

// A voxel at the map's finest resolution: its centre is ((x + 0.5) * r, (y + 0.5) * r, ...)
// in the map frame for resolution r.
struct VoxelIndex {
  int32_t x = 0, y = 0, z = 0;
  auto operator<=>(const VoxelIndex&) const = default;
};

constexpr unsigned kTreeDepth = 16;      // OctoMap's: the finest voxels are at depth 16
constexpr int32_t kKeyOffset = 1 << 15;  // key of index 0

// A voxel (depth 16) or a whole block above it (a pruned node of the tree: 2^(16 - depth)
// voxels per axis) whose class or value changed in an insertion.
struct VoxelChange {
  uint64_t code = 0;  // Morton code of the first voxel of the node
  uint8_t depth = kTreeDepth;
  uint8_t value = 0;  // occupancy probability after the change, round(255 P); 0: not occupied
  bool occupied = false;
};

namespace detail {
constexpr uint64_t spreadBits(uint64_t v) {  // 16 bits -> every third bit
  v &= 0xFFFF;
  v = (v | v << 32) & 0x1F00000000FFFFull;
  v = (v | v << 16) & 0x1F0000FF0000FFull;
  v = (v | v << 8) & 0x100F00F00F00F00Full;
  v = (v | v << 4) & 0x10C30C30C30C30C3ull;
  v = (v | v << 2) & 0x1249249249249249ull;
  return v;
}
constexpr uint64_t compactBits(uint64_t v) {  // every third bit -> 16 bits
  v &= 0x1249249249249249ull;
  v = (v ^ (v >> 2)) & 0x10C30C30C30C30C3ull;
  v = (v ^ (v >> 4)) & 0x100F00F00F00F00Full;
  v = (v ^ (v >> 8)) & 0x1F0000FF0000FFull;
  v = (v ^ (v >> 16)) & 0x1F00000000FFFFull;
  v = (v ^ (v >> 32)) & 0x1FFFFFull;
  return v;
}
}  // namespace detail

// Morton code of three 16-bit keys.
constexpr uint64_t mortonOfKeys(uint32_t kx, uint32_t ky, uint32_t kz) {
  return detail::spreadBits(kx) | detail::spreadBits(ky) << 1 | detail::spreadBits(kz) << 2;
}

constexpr uint64_t voxelCode(const VoxelIndex& v) {
  return mortonOfKeys(static_cast<uint32_t>(v.x + kKeyOffset),
                      static_cast<uint32_t>(v.y + kKeyOffset),
                      static_cast<uint32_t>(v.z + kKeyOffset));
}

constexpr VoxelIndex voxelOfCode(uint64_t code) {
  return {static_cast<int32_t>(detail::compactBits(code)) - kKeyOffset,
          static_cast<int32_t>(detail::compactBits(code >> 1)) - kKeyOffset,
          static_cast<int32_t>(detail::compactBits(code >> 2)) - kKeyOffset};
}

}  // namespace stereomap::fusion
