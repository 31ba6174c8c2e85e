// Aligning maps with no hint (server/align): flights of one room started far apart, pairs cut
// from a real OctoMap map, and what must be refused (unrelated rooms, a corridor, a repeated
// pattern) or is an error (empty maps, one voxel, different resolutions).
#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <fstream>

#include "server/align/map_align.hpp"
#include "tests/support/align_pairs.hpp"

namespace stereomap {
namespace {

using common::Vec3;
using testing::poseError;
using testing::poseOf;

align::Alignment aligned(const fusion::OccupancyMap& a, const fusion::OccupancyMap& b) {
  auto result = align::alignMaps(a, b, {});
  EXPECT_TRUE(result) << (result ? "" : result.error().message);
  if (!result) return {};
  std::printf("%s (confidence %.2f, agreement %.2f, constraint %.3f, cell %.2f m, %zu matches)\n",
              align::alignLine("A", "B", *result).c_str(), result->confidence, result->agreement,
              result->constraint_ratio, result->working_cell_m, result->matches);
  return *result;
}

void expectTruth(const align::Alignment& found, const common::Rigid3& truth, double voxel) {
  ASSERT_TRUE(found.found) << found.reason;
  const auto error = poseError(found.T_a_b, truth);
  EXPECT_LE(error.translation_m, voxel);
  EXPECT_LE(error.rotation_deg, 0.5);
}

// Two flights of one room, each mapped in its own frame (its start): the second turned by
// up to 180 degrees and 20 m away; different paths, so the maps overlap only in part.
TEST(Align, FlightsOfOneRoomStartedFarApart) {
  const auto room = sim::Scene::makeRoom({.seed = 3});
  const double v = 0.1;
  // Off the voxel grid: a surface on a voxel face lands in the voxel on one side or the other.
  const common::Rigid3 T_a_world = poseOf(23, Vec3(0.537, -1.213, 0.031));
  const common::Rigid3 T_b_world = poseOf(180, Vec3(12.345, 15.731, 0.372));
  const auto a = testing::flyRoom(room, {}, 0, 30, T_a_world, v);
  const auto b = testing::flyRoom(room, {.radius_x = 2.6, .radius_y = 2.0, .height = 1.2}, 15, 45,
                                  T_b_world, v);
  expectTruth(aligned(*a, *b), T_a_world * T_b_world.inverse(), v);
}

// The same maps give the same answer: every random draw (RANSAC, FLANN's trees) is seeded.
TEST(Align, TheSameMapsGiveTheSameAnswer) {
  const auto room = sim::Scene::makeRoom({.seed = 5});
  const auto a = testing::flyRoom(room, {}, 0, 20, poseOf(31, Vec3(0.21, 0.43, 0.05)), 0.1);
  const auto b = testing::flyRoom(room, {.radius_x = 2.5}, 10, 30, poseOf(-97, Vec3(9, 4, 0)), 0.1);
  const auto first = align::alignMaps(*a, *b, {}), second = align::alignMaps(*a, *b, {});
  ASSERT_TRUE(first && second);
  EXPECT_EQ(first->found, second->found);
  EXPECT_EQ(first->T_a_b.translation, second->T_a_b.translation);
  EXPECT_EQ(first->T_a_b.rotation.coeffs(), second->T_a_b.rotation.coeffs());
  EXPECT_EQ(first->matches, second->matches);
}

std::unique_ptr<fusion::OccupancyMap> loadSample(const char* name) {
  const std::filesystem::path path =
      std::filesystem::path(STEREOMAP_DATA_DIR) / "octomap_samples" / name;
  std::ifstream in(path, std::ios::binary);
  if (!in) return nullptr;
  auto map = fusion::OccupancyMap::load(in);
  return map ? std::move(map).value() : nullptr;
}

TEST(Align, WindowsOfARealMap) {
  const auto campus = loadSample("fr_campus.bt");
  if (!campus) GTEST_SKIP() << "fr_campus.bt not found under " << STEREOMAP_DATA_DIR;
  for (const double share : {0.3, 0.6}) {
    SCOPED_TRACE(share);
    const auto T_b_world = poseOf(137, Vec3(-14.3, 8.71, 1.3), 1.5, -2);
    const auto pair = testing::windowPair(*campus, 60, share, T_b_world);
    std::printf("voxels %zu %zu\n", pair.a->occupiedCount(), pair.b->occupiedCount());
    expectTruth(aligned(*pair.a, *pair.b), pair.T_a_b, campus->resolution());
  }
}

TEST(Align, UnrelatedMapsAreRefused) {
  const double v = 0.1;
  const auto a = testing::flyRoom(sim::Scene::makeRoom({.seed = 3}), {}, 0, 30,
                                  poseOf(10, Vec3(0.3, 0.2, 0)), v);
  const auto b = testing::flyRoom(sim::Scene::makeRoom({.seed = 8, .length = 14, .width = 9}), {},
                                  0, 30, poseOf(-70, Vec3(4.1, 2.2, 0)), v);
  const auto found = aligned(*a, *b);
  EXPECT_FALSE(found.found);
}

TEST(Align, APlainCorridorIsRefused) {
  const double v = 0.1;
  const auto a = testing::corridorMap(0, 30, 0, poseOf(0, Vec3(0.03, 0.01, 0.02)), v);
  const auto b = testing::corridorMap(12, 42, 0, poseOf(40, Vec3(-3.1, 5.2, 0.02)), v);
  const auto found = aligned(*a, *b);
  EXPECT_FALSE(found.found);
}

TEST(Align, ARepeatedPatternIsRefused) {
  const double v = 0.1;
  const auto a = testing::corridorMap(0, 30, 3.0, poseOf(0, Vec3(0.03, 0.01, 0.02)), v);
  const auto b = testing::corridorMap(12, 42, 3.0, poseOf(40, Vec3(-3.1, 5.2, 0.02)), v);
  const auto found = aligned(*a, *b);
  EXPECT_FALSE(found.found);
}

TEST(Align, BadMapsAreClearErrors) {
  const auto room = testing::flyRoom(sim::Scene::makeRoom({.seed = 3}), {}, 0, 10,
                                     common::Rigid3::identity(), 0.1);
  fusion::OccupancyMap empty({.resolution = 0.1});
  const auto one = testing::mapOfPoints(0.1, {Vec3(1, 2, 3)}, {});
  const auto coarse = testing::flyRoom(sim::Scene::makeRoom({.seed = 3}), {}, 0, 10,
                                       common::Rigid3::identity(), 0.2);
  for (const fusion::OccupancyMap* other : {&empty, one.get(), coarse.get()}) {
    const auto result = align::alignMaps(*room, *other, {});
    ASSERT_FALSE(result);
    EXPECT_EQ(result.error().code, common::ErrorCode::kInvalidArgument);
    std::printf("%s\n", result.error().message.c_str());
  }
}

}  // namespace
}  // namespace stereomap
