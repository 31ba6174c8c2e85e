// Aligning maps with no hint (server/align): flights of one room started far apart, pairs cut
// from a real OctoMap map, and what must be refused (unrelated rooms, a corridor, a repeated
// pattern) or is an error (empty maps, one voxel, different resolutions).
#include <gtest/gtest.h>
#include <omp.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>

#include <open3d/geometry/KDTreeFlann.h>
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
    const align::CellRaster from_centres(centres, edge);
    size_t near = 0;
    for (const Vec3& p : pointsAround(1.0)) {
      double nearest = -1, nearest_2 = -1;  // within 1.5 and 2 edges
      for (const Vec3& c : centres) {
        const double d2 = (c - p).squaredNorm();
        if (d2 <= 2.25 * edge * edge && (nearest < 0 || d2 < nearest)) nearest = d2;
        if (d2 <= 4 * edge * edge && (nearest_2 < 0 || d2 < nearest_2)) nearest_2 = d2;
      }
      ASSERT_EQ(cells.nearest2(p, 1.5 * edge), nearest) << p.transpose();
      ASSERT_EQ(cells.near(p, 1.5 * edge), nearest >= 0);
      double found2 = -1;
      const int found = from_centres.nearest(p, 2.0 * edge, &found2);
      ASSERT_EQ(found2, nearest_2) << p.transpose();
      if (found >= 0) {
        ASSERT_EQ((centres[found] - p).squaredNorm(), nearest_2);
      }
      near += nearest >= 0;
    }
    EXPECT_GT(near, 400u);  // the points test both answers
    // Each cell's 30 nearest within 2.5 edges: itself first, nearest first, and the same
    // distances as a search of every cell (which of equally distant cells is left to each).
    const align::NeighbourRows rows = cells.around(2.5, 30);
    for (size_t i = 0; i < centres.size(); i += 7) {
      std::vector<double> all;
      for (const Vec3& c : centres) {
        const double d2 = (c - centres[i]).squaredNorm();
        if (d2 <= 6.25 * edge * edge) all.push_back(d2);
      }
      std::sort(all.begin(), all.end());
      all.resize(std::min<size_t>(all.size(), 30));
      ASSERT_EQ(rows.count[i], static_cast<int>(all.size()));
      ASSERT_EQ(rows.indices(i)[0], static_cast<int>(i));
      for (int m = 0; m < rows.count[i]; ++m) {
        const double d2 = (centres[rows.indices(i)[m]] - centres[i]).squaredNorm();
        ASSERT_NEAR(d2, all[m], 1e-9 * edge * edge);
        ASSERT_NEAR(rows.distances2(i)[m], all[m], 1e-9 * edge * edge);
      }
    }
  }
  const align::ClassRaster space(*map, map->occupiedBounds(), 0.5);
  size_t counted[3] = {0, 0, 0};
  for (const Vec3& p : pointsAround(3.0)) {
    ASSERT_EQ(space.at(p), map->query(p)) << p.transpose();
    ++counted[static_cast<int>(map->query(p))];
  }
  EXPECT_GT(counted[static_cast<int>(fusion::Occupancy::kFree)], 400u);
  EXPECT_GT(counted[static_cast<int>(fusion::Occupancy::kOccupied)], 10u);
}

// Cells far apart are hashed (their box is beyond kMaxDenseCells) and answer as a dense raster
// does; a key far outside the cells' box, which would wrap the hash's 21-bit fields onto a
// cell's, finds none.
TEST(Align, AHashedRasterAnswersAsADenseOne) {
  const double edge = 0.1;
  std::vector<Vec3> block;  // 4 x 3 x 4 cells
  for (int i = 0; i < 48; ++i)
    block.push_back(Vec3(i % 4 + 0.5, i / 4 % 3 + 0.5, i / 12 + 0.5) * edge);
  std::vector<Vec3> apart = block;
  apart.push_back(Vec3(400.5, 400.5, 400.5) * edge);
  const align::CellRaster dense(block, edge), hashed(apart, edge);
  std::mt19937 random(3);
  std::uniform_real_distribution<double> along(-0.3, 0.7);
  for (int i = 0; i < 2000; ++i) {
    const Vec3 p(along(random), along(random), along(random));
    double d_dense = -1, d_hashed = -1;
    ASSERT_EQ(dense.nearest(p, 2.0 * edge, &d_dense), hashed.nearest(p, 2.0 * edge, &d_hashed));
    ASSERT_EQ(d_dense, d_hashed);
  }
  const align::NeighbourRows rows_dense = dense.around(2.5, 30);
  const align::NeighbourRows rows_hashed = hashed.around(2.5, 30);
  for (size_t i = 0; i < block.size(); ++i) {
    ASSERT_EQ(rows_dense.count[i], rows_hashed.count[i]);
    ASSERT_TRUE(std::equal(rows_dense.indices(i), rows_dense.indices(i) + rows_dense.count[i],
                           rows_hashed.indices(i)));
  }
  // Key (2^21, -1, 0) hashes as key (0, 0, 0) would, were it not checked against the box.
  const Vec3 wrapped((2097152 + 0.5) * edge, -0.5 * edge, 0.5 * edge);
  EXPECT_EQ(hashed.nearest(wrapped, 2.0 * edge), -1);
  EXPECT_FALSE(hashed.near(wrapped, 1.5 * edge));
}

// Our FPFH, given the neighbours Open3D's search finds, gives Open3D's features, on a map's
// cells with their normals, at one thread and at two; and the lattice's walk finds those
// neighbours' distances.
TEST(Align, FeaturesAreOpen3dsFpfh) {
  const auto room = sim::Scene::makeRoom({.seed = 6});
  const auto map = testing::flyRoom(room, {}, 0, 20, poseOf(-40, Vec3(0.1, 0.2, 0.03)), 0.1);
  const double edge = map->cellSize(15);
  open3d::geometry::PointCloud cloud;
  for (const auto& c : map->occupiedCells(15)) {
    cloud.points_.push_back(Vec3(c.x + 0.5, c.y + 0.5, c.z + 0.5) * edge);
  }
  cloud.EstimateNormals(open3d::geometry::KDTreeSearchParamHybrid(2.5 * edge, 30));
  const auto theirs = open3d::pipelines::registration::ComputeFPFHFeature(
      cloud, open3d::geometry::KDTreeSearchParamHybrid(5.0 * edge, 50));
  // The neighbours Open3D's search finds (the lattice's walk may order ties otherwise).
  const open3d::geometry::KDTreeFlann tree(cloud);
  align::NeighbourRows rows;
  rows.width = 50;
  rows.index.resize(cloud.points_.size() * 50);
  rows.distance2.resize(rows.index.size());
  for (size_t i = 0; i < cloud.points_.size(); ++i) {
    std::vector<int> found;
    std::vector<double> found2;
    const int k = tree.SearchHybrid(cloud.points_[i], 5.0 * edge, 50, found, found2);
    rows.count.push_back(k);
    std::copy_n(found.begin(), k, rows.index.begin() + i * 50);
    std::copy_n(found2.begin(), k, rows.distance2.begin() + i * 50);
  }
  for (const int threads : {1, 2}) {
    omp_set_num_threads(threads);
    const align::FpfhFeatures ours = align::fpfhFeatures(cloud, rows);
    ASSERT_EQ(ours.cols(), theirs->data_.cols());
    EXPECT_LT((ours - theirs->data_).cwiseAbs().maxCoeff(), 1e-9);
    EXPECT_GT(ours.cwiseAbs().sum(), 1000.0);  // not all zero
  }
  omp_set_num_threads(1);
  // The lattice's walk finds as many neighbours at the same distances, but for cells exactly at
  // the radius, which it takes and Open3D's search leaves out (or not: its cut is in float).
  const double r2 = 25.0 * edge * edge;
  const align::NeighbourRows lattice = align::CellRaster(cloud.points_, edge).around(5.0, 50);
  size_t full = 0;
  for (size_t i = 0; i < cloud.points_.size(); ++i) {
    const int both = std::min(lattice.count[i], rows.count[i]);
    for (int m = 0; m < both; ++m) {
      ASSERT_NEAR(lattice.distances2(i)[m], rows.distances2(i)[m], 1e-9 * r2) << i;
    }
    for (int m = both; m < lattice.count[i]; ++m) {
      ASSERT_NEAR(lattice.distances2(i)[m], r2, 1e-9 * r2) << i;
    }
    ASSERT_GE(lattice.count[i], rows.count[i]) << i;
    full += rows.count[i] == 50;
  }
  EXPECT_GT(full, 100u);  // the cap of 50 is met, not only the radius
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
