#include "server/fusion/occupancy_map.hpp"

#include <gtest/gtest.h>
#include <octomap/OcTree.h>

#include <random>
#include <set>
#include <sstream>

#include "testing/data.hpp"
#include "testing/synthetic.hpp"
#include "testing/tum.hpp"

namespace stereomap::fusion {
namespace {

using common::Vec3;

// A 2 m x 2 m wall of points at x = 3 (map frame), seen from the origin, 2 cm apart.
common::PointCloud wall(double x) { return testing::planeCloud(x, 1.0, 0.02); }

TEST(OccupancyMap, WallIsOccupiedAndTheSpaceBeforeItFree) {
  OccupancyMap map({.resolution = 0.1});
  map.insertCloud(wall(3.05), common::Rigid3::identity(), 10.0);
  EXPECT_EQ(map.query(Vec3(3.05, 0.05, 0.05)), Occupancy::kOccupied);
  EXPECT_EQ(map.query(Vec3(1.5, 0.05, 0.05)), Occupancy::kFree);
  EXPECT_EQ(map.query(Vec3(5.0, 0.05, 0.05)), Occupancy::kUnknown);

  const auto voxels = map.occupiedVoxels();
  EXPECT_EQ(voxels.size(), map.occupiedCount());
  ASSERT_GT(voxels.size(), 300u);  // 20 x 20 voxels of wall, less edge effects
  EXPECT_TRUE(std::is_sorted(voxels.begin(), voxels.end()));
  for (const auto& v : voxels) {
    EXPECT_EQ(v.x, 30);  // 3.0 <= x < 3.1
    EXPECT_NEAR(map.voxelCentre(v).x(), 3.05, 1e-9);
  }
  const auto bounds = map.occupiedBounds();
  EXPECT_NEAR(bounds.min.x(), 3.0, 1e-6);
  EXPECT_NEAR(bounds.max.x(), 3.1, 1e-6);
}

TEST(OccupancyMap, SensorPoseTransformsTheCloud) {
  OccupancyMap map({.resolution = 0.1});
  // Sensor at (0, 0, 1) yawed by 90°: its x axis is the map's y.
  const common::Rigid3 T_map_sensor{common::Quat(Eigen::AngleAxisd(M_PI / 2, Vec3::UnitZ())),
                                    Vec3(0, 0, 1)};
  map.insertCloud(wall(3.05), T_map_sensor, 10.0);
  EXPECT_EQ(map.query(Vec3(0.05, 3.05, 1.05)), Occupancy::kOccupied);
  EXPECT_EQ(map.query(Vec3(3.05, 0.05, 1.05)), Occupancy::kUnknown);
}

TEST(OccupancyMap, RaysBeyondMaxRangeOnlyClearFreeSpace) {
  OccupancyMap map({.resolution = 0.1});
  map.insertCloud(wall(8.05), common::Rigid3::identity(), 5.0);
  EXPECT_EQ(map.occupiedCount(), 0u);
  EXPECT_EQ(map.query(Vec3(4.0, 0.05, 0.05)), Occupancy::kFree);
  EXPECT_TRUE(map.occupiedBounds().empty());
}

// Found by fuzzing the server's samples (tests/fuzz): values a validated frame may carry
// but OctoMap's key arithmetic cannot take. Before the fix, the first walked rays past their
// buffer (forever), the others were undefined behaviour (a float cast to int out of range).
TEST(OccupancyMap, ValuesAtTheLimitsOfFloatInsertNothingWrong) {
  OccupancyMap map({.resolution = 0.1});
  common::PointCloud cloud;
  // An origin of -0 on a voxel border and an end 1e-38 m beside it, in the next voxel: the
  // ray's float length is 0. Then a point far beyond float's square root (its norm is inf).
  cloud.points = {{-1.77e-38f, 1.1e-42f, 0}, {-1.6e29f, 0, 0}, {3.05f, 0.05f, 0.05f}};
  map.insertCloud(cloud, {common::Quat::Identity(), Vec3(-9e-280, 0, 0)}, 20.0);
  EXPECT_EQ(map.occupiedCount(), 2u);  // the first point's voxel and the third's
  EXPECT_EQ(map.query(Vec3(-0.05, 0.05, 0.05)), Occupancy::kOccupied);
  EXPECT_EQ(map.query(Vec3(3.05, 0.05, 0.05)), Occupancy::kOccupied);
  EXPECT_EQ(map.query(Vec3(-10.05, 0.05, 0.05)), Occupancy::kFree);  // the far point's ray
  // A sensor beyond the map's 2^16 voxels (3.3 km here), or beyond int's range: nothing.
  MapChanges changes;
  for (const double x : {4000.0, 1e12, -1e300}) {
    map.insertCloud(wall(3.05), {common::Quat::Identity(), Vec3(x, 0, 0)}, 20.0, &changes);
    EXPECT_TRUE(changes.complete);
    EXPECT_TRUE(changes.voxels.empty());
  }
  EXPECT_EQ(map.occupiedCount(), 2u);
  EXPECT_EQ(map.query(Vec3(1e12, 0, 0)), Occupancy::kUnknown);
}

TEST(OccupancyMap, BinaryExportLoadsInOctoMapWithTheSameOccupiedVoxels) {
  OccupancyMap map({.resolution = 0.05});
  map.insertCloud(wall(2.0), common::Rigid3::identity(), 10.0);
  std::stringstream bt;
  ASSERT_TRUE(map.writeBinary(bt));
  octomap::OcTree loaded(0.1);
  ASSERT_TRUE(loaded.readBinary(bt));
  EXPECT_DOUBLE_EQ(loaded.getResolution(), 0.05);
  size_t occupied = 0;
  for (auto it = loaded.begin_leafs(); it != loaded.end_leafs(); ++it) {
    if (loaded.isNodeOccupied(*it)) {
      const size_t span = size_t{1} << (16 - it.getDepth());
      occupied += span * span * span;
    }
  }
  EXPECT_EQ(occupied, map.occupiedCount());
  EXPECT_EQ(map.occupiedVoxels().size(), map.occupiedCount());  // export did not prune ours
}

}  // namespace
}  // namespace stereomap::fusion

namespace stereomap::fusion {
namespace {

// A synthetic frame: rays over a 65x50 degree view along the sensor's +x, ending on a wavy
// surface 2-10 m away, some beyond max_range.
common::PointCloud frustumCloud(int cols, int rows, uint32_t seed) {
  common::PointCloud cloud;
  const double h = 65.0 * M_PI / 180, v = 50.0 * M_PI / 180;
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < cols; ++c) {
      const double az = (c / (cols - 1.0) - 0.5) * h, el = (r / (rows - 1.0) - 0.5) * v;
      const double range = 6.0 + 3.5 * std::sin(3 * az + seed) * std::cos(2 * el) +
                           0.5 * std::sin(17 * az * el + seed);
      const Vec3 dir(std::cos(el) * std::cos(az), std::cos(el) * std::sin(az), std::sin(el));
      cloud.points.push_back((dir * range).cast<float>());
    }
  }
  return cloud;
}

double agreementAfter(const std::vector<std::pair<common::PointCloud, common::Rigid3>>& frames,
                      double resolution, double max_range) {
  OccupancyMap fast({.resolution = resolution});
  OccupancyMap stock({.resolution = resolution, .insertion = OccupancyMap::Insertion::kOctomap});
  for (const auto& [cloud, pose] : frames) {
    fast.insertCloud(cloud, pose, max_range);
    stock.insertCloud(cloud, pose, max_range);
  }
  const auto agreement = compareClassification(fast, stock);
  std::printf("agreement %.5f over %llu voxels\n", agreement.fraction(),
              static_cast<unsigned long long>(agreement.voxels));
  EXPECT_GT(agreement.voxels, 10000u);
  EXPECT_EQ(fast.occupiedCount() > 0, true);
  return agreement.fraction();
}

TEST(FastInsertion, AgreesWithOctomapOnSyntheticFrames) {
  std::vector<std::pair<common::PointCloud, common::Rigid3>> frames;
  for (uint32_t i = 0; i < 4; ++i) {
    frames.emplace_back(frustumCloud(100, 80, i),
                        common::Rigid3{common::Quat(Eigen::AngleAxisd(0.3 * i, Vec3::UnitZ())),
                                       Vec3(0.2 * i, -0.1 * i, 0.05 * i)});
  }
  EXPECT_GE(agreementAfter(frames, 0.05, 8.0), 0.995);
  EXPECT_GE(agreementAfter(frames, 0.1, -1.0), 0.995);
}

TEST(FastInsertion, AgreesWithOctomapOnRealTumDepth) {
  const auto dir = testing::kDataDir / "tum_rgbd_fr1";
  STEREOMAP_SKIP_WITHOUT(dir);
  std::vector<std::pair<common::PointCloud, common::Rigid3>> frames;
  for (auto& f : testing::tumDepthFrames(dir.string(), 6)) {
    frames.emplace_back(std::move(f.cloud), f.T_map_camera);
  }
  ASSERT_EQ(frames.size(), 6u);
  EXPECT_GE(agreementAfter(frames, 0.05, 3.0), 0.995);  // some rays longer than 3 m
}

// A ray that ends where two voxel borders cross can pass beside its end voxel and take one
// step past it (OctoMap compares the voxel's exit with the ray's length in floating point, and
// so do we). Walls on all six sides, their edges on borders that are also the edges of the
// box the rays are cast in (multiples of 4 voxels), put such steps outside that box: the fast
// path must mark them as OctoMap does, never outside its buffers (it wrote before its buffer,
// found by AddressSanitizer in tiles_test).
TEST(FastInsertion, RaysThatStepPastTheirEndAgreeWithOctomapAtTheEdgesOfTheirBox) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> jitter(-0.04, 0.04);
  const common::Rigid3 pose{common::Quat::Identity(), Vec3(-60, 0, 0)};  // on voxel borders
  OccupancyMap fast({.resolution = 0.1});
  OccupancyMap stock({.resolution = 0.1, .insertion = OccupancyMap::Insertion::kOctomap});
  for (const double distance : {8.0}) {
    for (int axis = 0; axis < 3; ++axis) {
      for (const double sign : {-1.0, 1.0}) {
        common::PointCloud wall;  // one wall a cloud: its edges are the box's
        for (double u = -8; u <= 8; u += 0.1) {
          for (double v = -8; v <= 8; v += 0.1) {
            Vec3 p;
            p[axis] = sign * (distance + jitter(rng));
            p[(axis + 1) % 3] = u;
            p[(axis + 2) % 3] = v;
            wall.points.push_back(p.cast<float>());
          }
        }
        fast.insertCloud(wall, pose, 30.0);
        stock.insertCloud(wall, pose, 30.0);
      }
    }
  }
  EXPECT_EQ(compareClassification(fast, stock).fraction(), 1.0);
}

// Space seen again and again saturates at the clamping bounds and is pruned into blocks; OctoMap
// leaves a clamped block alone when an update cannot move it, and so must the fast path (it
// skips such blocks instead of expanding and pruning them back each frame): the same tree,
// log-odds and all, after frames that saturate free and occupied space.
TEST(FastInsertion, ClampedSpaceSeenAgainGivesOctomapsTreeExactly) {
  OccupancyMap fast({.resolution = 0.1});
  OccupancyMap stock({.resolution = 0.1, .insertion = OccupancyMap::Insertion::kOctomap});
  for (uint32_t i = 0; i < 16; ++i) {
    const common::Rigid3 pose{common::Quat(Eigen::AngleAxisd(0.02 * (i % 4), Vec3::UnitZ())),
                              Vec3(0.03 * (i % 3), 0.0, 0.02 * (i % 2))};
    const auto cloud = frustumCloud(60, 45, i % 2);
    fast.insertCloud(cloud, pose, 8.0);
    stock.insertCloud(cloud, pose, 8.0);
  }
  std::ostringstream fast_bytes, stock_bytes;
  ASSERT_TRUE(fast.writeFull(fast_bytes));
  ASSERT_TRUE(stock.writeFull(stock_bytes));
  EXPECT_GT(fast.occupiedCount(), 1000u);
  EXPECT_TRUE(fast_bytes.str() == stock_bytes.str());
}

TEST(FastInsertion, ComparisonCanTellMapsApart) {
  OccupancyMap a({.resolution = 0.1}), b({.resolution = 0.1});
  a.insertCloud(wall(3.05), common::Rigid3::identity(), 10);
  b.insertCloud(wall(4.05), common::Rigid3::identity(), 10);
  EXPECT_LT(compareClassification(a, b).fraction(), 0.95);
  EXPECT_DOUBLE_EQ(compareClassification(a, a).fraction(), 1.0);
}

}  // namespace
}  // namespace stereomap::fusion

namespace stereomap::fusion {
namespace {

TEST(OccupancyMap, CoarseCellsAreOccupiedWhenAnyVoxelIs) {
  OccupancyMap map({.resolution = 0.1});
  map.insertCloud(wall(3.05), common::Rigid3::identity(), 10.0);
  const auto fine = map.occupiedVoxels();
  const auto coarse = map.occupiedCells(15);  // 0.2 m cells
  EXPECT_DOUBLE_EQ(map.cellSize(15), 0.2);
  EXPECT_DOUBLE_EQ(map.cellSize(16), 0.1);
  EXPECT_EQ(map.occupiedCells(16), fine);
  // Every fine voxel lies in a coarse cell, and every coarse cell holds a fine voxel.
  std::set<std::tuple<int, int, int>> from_fine;
  for (const auto& v : fine) {
    from_fine.insert({v.x >> 1, v.y >> 1, v.z >> 1});  // floor division by 2
  }
  ASSERT_EQ(coarse.size(), from_fine.size());
  for (const auto& c : coarse) EXPECT_TRUE(from_fine.count({c.x, c.y, c.z}));
  EXPECT_LT(coarse.size(), fine.size());
}

TEST(OccupancyMap, BoxQueryReturnsOnlyVoxelsInside) {
  OccupancyMap map({.resolution = 0.1});
  map.insertCloud(wall(3.05), common::Rigid3::identity(), 10.0);
  common::Box3 box;
  box.extend(Vec3(2.9, 0.0, 0.0));
  box.extend(Vec3(3.2, 0.5, 0.5));
  const auto inside = map.occupiedVoxelsIn(box);
  ASSERT_FALSE(inside.empty());
  size_t expected = 0;
  for (const auto& v : map.occupiedVoxels()) expected += box.contains(map.voxelCentre(v));
  EXPECT_EQ(inside.size(), expected);
  for (const auto& v : inside) EXPECT_TRUE(box.contains(map.voxelCentre(v)));
}

TEST(OccupancyMap, PaperPresetLeavesUncertainVoxelsUnknown) {
  // Three hits then one miss on a voxel: log-odds 3 * 0.847 - 2.197 = 0.344, P = 0.585 with
  // the paper's model (miss 0.1): between 0.4 and 0.6, unknown. OctoMap's model (miss 0.4)
  // gives P = 0.894: occupied.
  const auto paper = OccupancyMap::Options::paperPreset(0.1);
  EXPECT_DOUBLE_EQ(paper.prob_miss, 0.1);
  EXPECT_DOUBLE_EQ(paper.occupancy_threshold, 0.6);
  EXPECT_DOUBLE_EQ(paper.free_threshold, 0.4);
  const Vec3 voxel(3.05, 0.05, 0.05);
  common::PointCloud behind;
  behind.points.emplace_back(5.05f, 0.05f, 0.05f);  // its ray crosses the voxel
  for (const auto& options : {paper, OccupancyMap::Options::octomapPreset(0.1)}) {
    OccupancyMap map(options);
    for (int i = 0; i < 3; ++i) map.insertCloud(wall(3.05), common::Rigid3::identity(), 10.0);
    map.insertCloud(behind, common::Rigid3::identity(), 10.0);
    EXPECT_EQ(map.query(voxel),
              options.prob_miss == 0.1 ? Occupancy::kUnknown : Occupancy::kOccupied);
    EXPECT_EQ(map.query(Vec3(1.55, 0.05, 0.05)), Occupancy::kFree);
  }
}

TEST(OccupancyMap, FullExportKeepsLogOdds) {
  OccupancyMap map({.resolution = 0.1});
  map.insertCloud(wall(3.05), common::Rigid3::identity(), 10.0);
  std::stringstream ot;
  ASSERT_TRUE(map.writeFull(ot));
  std::unique_ptr<octomap::AbstractOcTree> read(octomap::AbstractOcTree::read(ot));
  auto* tree = dynamic_cast<octomap::OcTree*>(read.get());
  ASSERT_NE(tree, nullptr);
  const auto* node = tree->search(3.05, 0.05, 0.05);
  ASSERT_NE(node, nullptr);
  EXPECT_NEAR(node->getOccupancy(), 0.7, 1e-6);  // one hit, as inserted
}

}  // namespace
}  // namespace stereomap::fusion

namespace stereomap::fusion {
namespace {

std::string bytesOf(const OccupancyMap& map, bool full) {
  std::ostringstream out;
  full ? map.writeFull(out) : map.writeBinary(out);
  return out.str();
}

TEST(OccupancyMapLoad, ReadsOctoMapSampleMapsAsOctoMapDoes) {
  const auto geb079 = testing::kDataDir / "octomap_samples" / "geb079.bt";
  STEREOMAP_SKIP_WITHOUT(geb079);
  std::ifstream in(geb079, std::ios::binary);
  auto map = OccupancyMap::load(in);
  ASSERT_TRUE(map) << map.error().message;
  EXPECT_DOUBLE_EQ((*map)->resolution(), 0.08);
  EXPECT_EQ((*map)->occupiedCount(), 185673u);  // the data set's README (expanded leaves)
  octomap::OcTree reference(geb079.string());
  size_t occupied = 0;
  for (auto it = reference.begin_leafs(), end = reference.end_leafs(); it != end; ++it) {
    if (reference.isNodeOccupied(*it)) occupied += size_t{1} << 3 * (16 - it.getDepth());
  }
  EXPECT_EQ(occupied, 185673u);
}

TEST(OccupancyMapLoad, RoundTripsItsOwnBinaryAndFullFiles) {
  OccupancyMap map({.resolution = 0.05});
  map.insertCloud(testing::planeCloud(2.0, 1.0, 0.02), common::Rigid3::identity(), 10.0);
  for (const bool full : {false, true}) {
    std::istringstream in(bytesOf(map, full));
    auto loaded = OccupancyMap::load(in);
    ASSERT_TRUE(loaded) << loaded.error().message;
    EXPECT_EQ((*loaded)->occupiedVoxels(), map.occupiedVoxels());
    EXPECT_DOUBLE_EQ((*loaded)->resolution(), 0.05);
  }
  OccupancyMap empty({.resolution = 0.1});
  std::istringstream in(bytesOf(empty, true));
  auto loaded = OccupancyMap::load(in);
  ASSERT_TRUE(loaded) << loaded.error().message;
  EXPECT_EQ((*loaded)->occupiedCount(), 0u);
}

TEST(OccupancyMapLoad, RefusesTruncatedDamagedAndHostileFiles) {
  OccupancyMap map({.resolution = 0.1});
  map.insertCloud(testing::planeCloud(2.0, 1.0, 0.05), common::Rigid3::identity(), 10.0);
  for (const bool full : {false, true}) {
    const std::string good = bytesOf(map, full);
    const size_t data = good.find("data\n") + 5;
    for (size_t size = 0; size < good.size(); size += (size < data + 64 ? 1 : 97)) {
      std::istringstream in(good.substr(0, size));
      EXPECT_FALSE(OccupancyMap::load(in)) << "truncated to " << size;
    }
    std::istringstream longer(good + "x");
    EXPECT_FALSE(OccupancyMap::load(longer));
  }
  // Every node claiming children, far deeper than 16 levels (OctoMap itself would recurse on).
  const std::string header = "# Octomap OcTree binary file\nid OcTree\nsize 99\nres 0.1\ndata\n";
  std::istringstream deep(header + std::string(4096, '\xff'));
  auto refused = OccupancyMap::load(deep);
  ASSERT_FALSE(refused);
  EXPECT_NE(refused.error().message.find("16 levels"), std::string::npos);
  for (const char* bad : {"", "hello\n", "# Octomap OcTree binary file\nid ColorOcTree\nsize 1\n",
                          "# Octomap OcTree file\nid OcTree\nsize 1\nres -1\ndata\n"}) {
    std::istringstream in(bad);
    EXPECT_FALSE(OccupancyMap::load(in)) << bad;
  }
}

}  // namespace
}  // namespace stereomap::fusion
