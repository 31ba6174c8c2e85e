#include "server/fusion/detail/ray_cast.hpp"

#include <gtest/gtest.h>

#include <random>
#include <set>

#include "server/fusion/voxel_code.hpp"

namespace stereomap::fusion::detail {
namespace {

using octomap::OcTreeKey;
using octomap::point3d;

// The keys OctoMap's computeRayKeys gives for each ray (origin voxel included), and the ones
// a kernel marks in the box around them.
std::set<uint64_t> octomapKeys(const octomap::OcTree& tree, const point3d& origin,
                               const std::vector<point3d>& ends) {
  std::set<uint64_t> keys;
  octomap::KeyRay ray;
  for (const auto& end : ends) {
    if (!tree.computeRayKeys(origin, end, ray)) continue;
    for (const OcTreeKey& key : ray) keys.insert(mortonOfKeys(key[0], key[1], key[2]));
  }
  return keys;
}

std::set<uint64_t> kernelKeys(const octomap::OcTree& tree, const point3d& origin,
                              const std::vector<point3d>& ends, RayKernel kernel) {
  OcTreeKey key;
  std::array<int, 3> lo{0xFFFF, 0xFFFF, 0xFFFF}, hi{0, 0, 0};
  std::vector<point3d> corners = ends;
  corners.push_back(origin);
  for (const auto& p : corners) {
    if (!tree.coordToKeyChecked(p, key)) continue;
    for (int a = 0; a < 3; ++a) {
      lo[a] = std::min<int>(lo[a], std::max(key[a] - 1, 0));
      hi[a] = std::max<int>(hi[a], std::min(key[a] + 1, 0xFFFF));
    }
  }
  const VoxelBox box = VoxelBox::around(lo, hi);
  std::vector<uint64_t> bits(box.words(), 0);
  castRays(tree, origin, ends, 0, ends.size(), box, bits.data(), kernel);
  std::set<uint64_t> keys;
  for (int x = 0; x < box.size[0]; ++x) {
    for (int y = 0; y < box.size[1]; ++y) {
      for (int z = 0; z < box.size[2]; ++z) {
        const int64_t i = box.index(x, y, z);
        if ((bits[i >> 6] >> (i & 63)) & 1) {
          keys.insert(mortonOfKeys(box.min[0] + x, box.min[1] + y, box.min[2] + z));
        }
      }
    }
  }
  return keys;
}

// Rays that are hard to walk alike: from voxel borders and corners, along the axes and the
// diagonals (ties between axes at every step), nearly parallel to an axis, very short, and
// in every direction; several resolutions.
std::vector<point3d> awkwardEnds(const point3d& origin, double resolution, std::mt19937& rng) {
  std::vector<point3d> ends;
  std::uniform_real_distribution<float> unit(-1, 1);
  const float r = static_cast<float>(resolution);
  for (int dx = -1; dx <= 1; ++dx) {
    for (int dy = -1; dy <= 1; ++dy) {
      for (int dz = -1; dz <= 1; ++dz) {
        for (const float length : {0.5f * r, 3.0f * r, 40.0f * r}) {
          ends.push_back(origin + point3d(dx, dy, dz) * length);
          ends.push_back(origin + point3d(dx + 1e-4f * unit(rng), dy, dz) * length);
        }
      }
    }
  }
  for (int i = 0; i < 3000; ++i) {
    const point3d direction(unit(rng), unit(rng), unit(rng));
    ends.push_back(origin + direction * (r * 60.0f * (0.01f + (unit(rng) + 1) / 2)));
  }
  return ends;
}

TEST(RayCast, BothKernelsMarkExactlyOctomapsRayKeys) {
  std::mt19937 rng(11);
  for (const double resolution : {0.05, 0.1, 0.2, 0.37}) {
    octomap::OcTree tree(resolution);
    const float r = static_cast<float>(resolution);
    // A voxel centre, a voxel border, a corner of eight voxels, and anywhere.
    for (const point3d& origin :
         {point3d(0.5f * r, 0.5f * r, 0.5f * r), point3d(3 * r, 0.5f * r, -0.5f * r),
          point3d(-2 * r, 7 * r, 4 * r), point3d(1.234f, -5.678f, 2.345f)}) {
      const auto ends = awkwardEnds(origin, resolution, rng);
      const auto expected = octomapKeys(tree, origin, ends);
      ASSERT_GT(expected.size(), 1000u);
      EXPECT_EQ(kernelKeys(tree, origin, ends, RayKernel::kScalar), expected)
          << "resolution " << resolution;
      if (bestRayKernel() == RayKernel::kAvx2) {
        EXPECT_EQ(kernelKeys(tree, origin, ends, RayKernel::kAvx2), expected)
            << "resolution " << resolution;
      }
    }
  }
  if (bestRayKernel() != RayKernel::kAvx2) GTEST_SKIP() << "no AVX2 here: scalar kernel only";
}

// Fewer rays than lanes, and none at all: idle lanes mark nothing.
TEST(RayCast, FewRaysLeaveTheOtherLanesIdle) {
  octomap::OcTree tree(0.1);
  const point3d origin(0.05f, 0.05f, 0.05f);
  for (size_t count : {0, 1, 3, 9}) {
    std::vector<point3d> ends;
    for (size_t i = 0; i < count; ++i)
      ends.push_back(origin + point3d(1.0f + 0.3f * i, 0.2f, -0.4f));
    for (const RayKernel kernel : {RayKernel::kScalar, bestRayKernel()}) {
      EXPECT_EQ(kernelKeys(tree, origin, ends, kernel), octomapKeys(tree, origin, ends));
    }
  }
}

// The bricks list every touched voxel once, at its Morton place, occupied where marked so.
TEST(RayCast, BricksHoldTheMarkedVoxelsInMortonOrder) {
  const VoxelBox box = VoxelBox::around({100, 200, 300}, {117, 209, 371});
  EXPECT_EQ(box.size[0] % 4, 0);
  EXPECT_EQ(box.size[2] % 64, 0);
  std::vector<uint64_t> free_bits(box.words(), 0), more_free(box.words(), 0),
      occupied(box.words(), 0);
  std::mt19937 rng(3);
  std::set<uint64_t> any, hit;
  for (int i = 0; i < 500; ++i) {
    const int x = 100 + static_cast<int>(rng() % 18), y = 200 + static_cast<int>(rng() % 10),
              z = 300 + static_cast<int>(rng() % 72);
    const uint64_t code = mortonOfKeys(x, y, z);
    auto& set = i % 3 == 0 ? occupied : i % 3 == 1 ? free_bits : more_free;
    markVoxel(set.data(), box, x - box.min[0], y - box.min[1], z - box.min[2]);
    any.insert(code);
    if (i % 3 == 0) hit.insert(code);
  }
  // In two shares, as two threads take it.
  std::vector<TouchedBrick> bricks, second;
  collectBricks(box, {free_bits.data(), more_free.data()}, {occupied.data()}, 0, 2, bricks);
  collectBricks(box, {free_bits.data(), more_free.data()}, {occupied.data()}, 2, 1000, second);
  bricks.insert(bricks.end(), second.begin(), second.end());
  std::set<uint64_t> got_any, got_hit;
  for (const auto& brick : bricks) {
    EXPECT_NE(brick.any, 0u);
    EXPECT_EQ(brick.occupied & ~brick.any, 0u);
    for (unsigned bit = 0; bit < 64; ++bit) {
      if ((brick.any >> bit) & 1) got_any.insert(brick.code << 6 | bit);
      if ((brick.occupied >> bit) & 1) got_hit.insert(brick.code << 6 | bit);
    }
  }
  EXPECT_EQ(got_any, any);
  EXPECT_EQ(got_hit, hit);
}

}  // namespace
}  // namespace stereomap::fusion::detail
