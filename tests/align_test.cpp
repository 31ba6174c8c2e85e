// Aligning maps with no hint (server/align): flights of one room started far apart, pairs cut
// from a real OctoMap map, and what must be refused (unrelated rooms, a corridor, a repeated
// pattern) or is an error (empty maps, one voxel, different resolutions).
#include <gtest/gtest.h>
#include <omp.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>

#include <open3d/pipelines/registration/Feature.h>

#include "server/align/fpfh.hpp"
#include "server/align/map_align.hpp"
#include "server/align/space_raster.hpp"
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
  const auto first = align::alignMaps(*a, *b, {});
  ASSERT_TRUE(first);
  EXPECT_TRUE(first->found) << first->reason;
  // Again, and on two threads: every parallel step sums in a fixed order.
  for (const unsigned threads : {1u, 2u}) {
    const auto second = align::alignMaps(*a, *b, {.threads = threads});
    ASSERT_TRUE(second);
    EXPECT_EQ(first->found, second->found);
    EXPECT_EQ(first->T_a_b.translation, second->T_a_b.translation);
    EXPECT_EQ(first->T_a_b.rotation.coeffs(), second->T_a_b.rotation.coeffs());
    EXPECT_EQ(first->matches, second->matches);
    EXPECT_EQ(first->overlap, second->overlap);
    EXPECT_EQ(first->rmse_m, second->rmse_m);
  }
}

// The rasters answer exactly what a search of every occupied cell and the octree answer: at
// points on and off the map, near its cells' centres and on their faces, inside and outside
// the cached box.
TEST(Align, RastersAnswerAsTheMapDoes) {
  const auto room = sim::Scene::makeRoom({.seed = 4});
  const auto map = testing::flyRoom(room, {}, 0, 20, poseOf(17, Vec3(0.3, -0.2, 0.04)), 0.1);
  const common::Box3 bounds = map->occupiedBounds();
  std::mt19937 random(7);
  const auto pointsAround = [&](double margin) {
    std::vector<Vec3> points;
    for (int i = 0; i < 20000; ++i) {
      Vec3 p;
      for (int axis = 0; axis < 3; ++axis) {
        std::uniform_real_distribution<double> along(bounds.min[axis] - margin,
                                                     bounds.max[axis] + margin);
        p[axis] = along(random);
      }
      points.push_back(p);
    }
    return points;
  };
  for (const unsigned depth : {15u, 16u}) {
    SCOPED_TRACE(depth);
    const double edge = map->cellSize(depth);
    const int32_t offset = fusion::kKeyOffset >> (fusion::kTreeDepth - depth);
    std::vector<uint64_t> codes;
    std::vector<Vec3> centres;
    for (const auto& c : map->occupiedCells(depth)) {
      codes.push_back(fusion::mortonOfKeys(c.x + offset, c.y + offset, c.z + offset));
      centres.push_back(Vec3(c.x + 0.5, c.y + 0.5, c.z + 0.5) * edge);
    }
    const align::CellRaster cells(codes, depth, edge);
    size_t near = 0;
    for (const Vec3& p : pointsAround(1.0)) {
      double nearest = -1;
      for (const Vec3& c : centres) {
        const double d2 = (c - p).squaredNorm();
        if (d2 <= 2.25 * edge * edge && (nearest < 0 || d2 < nearest)) nearest = d2;
      }
      ASSERT_EQ(cells.nearest2(p, 1.5 * edge), nearest) << p.transpose();
      ASSERT_EQ(cells.near(p, 1.5 * edge), nearest >= 0);
      near += nearest >= 0;
    }
    EXPECT_GT(near, 400u);  // the points test both answers
  }
  const align::ClassRaster space(*map, 0.5);
  size_t counted[3] = {0, 0, 0};
  for (const Vec3& p : pointsAround(3.0)) {
    ASSERT_EQ(space.at(p), map->query(p)) << p.transpose();
    ++counted[static_cast<int>(map->query(p))];
  }
  EXPECT_GT(counted[static_cast<int>(fusion::Occupancy::kFree)], 400u);
  EXPECT_GT(counted[static_cast<int>(fusion::Occupancy::kOccupied)], 10u);
}

// Our FPFH (one neighbour search a point) gives Open3D's features, on a map's cells with their
// normals, at one thread and at two.
TEST(Align, FeaturesAreOpen3dsFpfh) {
  const auto room = sim::Scene::makeRoom({.seed = 6});
  const auto map = testing::flyRoom(room, {}, 0, 20, poseOf(-40, Vec3(0.1, 0.2, 0.03)), 0.1);
  const double edge = map->cellSize(15);
  open3d::geometry::PointCloud cloud;
  for (const auto& c : map->occupiedCells(15)) {
    cloud.points_.push_back(Vec3(c.x + 0.5, c.y + 0.5, c.z + 0.5) * edge);
  }
  cloud.EstimateNormals(open3d::geometry::KDTreeSearchParamHybrid(2.5 * edge, 30));
  const open3d::geometry::KDTreeFlann tree(cloud);
  const auto theirs = open3d::pipelines::registration::ComputeFPFHFeature(
      cloud, open3d::geometry::KDTreeSearchParamHybrid(5.0 * edge, 50));
  for (const int threads : {1, 2}) {
    omp_set_num_threads(threads);
    const align::FpfhFeatures ours = align::fpfhFeatures(cloud, tree, 5.0 * edge, 50);
    ASSERT_EQ(ours.cols(), theirs->data_.cols());
    EXPECT_LT((ours - theirs->data_).cwiseAbs().maxCoeff(), 1e-9);
    EXPECT_GT(ours.cwiseAbs().sum(), 1000.0);  // not all zero
  }
  omp_set_num_threads(1);
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

// Half a second of a flight in room 2 (seen whole: floor, walls, boxes) against a flight of
// room 12, a room from the same generator: floors and walls fit, the boxes do not. Without the
// gates on what stands off the large planes it is placed, wrongly (agreement 0.958, every other
// gate passed); with them, the coarse level's pose is refused, and the finer level's search
// finds the rivals that make it ambiguous.
TEST(Align, AStretchOfOneRoomIsNotPlacedInASimilarRoom) {
  const double v = 0.1;
  const auto room = sim::Scene::makeRoom({.seed = 2});
  const auto other = sim::Scene::makeRoom({.seed = 12, .length = 13.0, .width = 10.0});
  const auto a = testing::flyRoom(other, {}, 0, 30, poseOf(50.7, Vec3(0.73, -0.2, 0.04)), v);
  const auto b = testing::flyRoom(room, {.radius_x = 2.2, .radius_y = 1.8, .height = 1.1}, 6, 6.5,
                                  poseOf(-122, Vec3(6.6, 1.7, 0.17)), v);
  const auto found = aligned(*a, *b);
  EXPECT_FALSE(found.found);
  EXPECT_LT(found.structure_agreement, align::AlignOptions{}.min_structure_agreement)
      << found.reason;
  align::AlignOptions without;
  without.min_structure_agreement = 0;
  without.min_structure_cells = 0;
  const auto placed = align::alignMaps(*a, *b, without);
  ASSERT_TRUE(placed);
  EXPECT_TRUE(placed->found) << "the gate is not what refuses it: " << placed->reason;
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
