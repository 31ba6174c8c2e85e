// Cross-process: stereomap-onboard flies the simulated room and streams over real DDS to a
// real stereomap-server; the server's map (map.bt over HTTP) is compared with the room's
// true geometry. Figures are reported in docs/BENCHMARKS.md.
#include <gtest/gtest.h>
#include <octomap/OcTree.h>
#include <nlohmann/json.hpp>

#include <set>
#include <sstream>

#include "onboard/sim/sim_source.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;
using common::Vec3;

constexpr int kDomain = 71;
constexpr int kFrames = 100;
constexpr double kResolution = 0.1;
constexpr double kMaxRange = 6.0;  // the onboard default

using Key = std::tuple<int, int, int>;

Key keyOf(const Vec3& p) {
  return {static_cast<int>(std::floor(p.x() / kResolution)),
          static_cast<int>(std::floor(p.y() / kResolution)),
          static_cast<int>(std::floor(p.z() / kResolution))};
}

TEST(MapAccuracy, SimFlightMapMatchesTheRoomOverRealDds) {
  ServerProcess server(kDomain, {"--resolution", std::to_string(kResolution)});
  ChildProcess onboard(onboardArgs(kDomain, "accuracy", kFrames, {"--rate", "0", "--seed", "1"}),
                       server.logPath() + ".onboard");
  const auto code = onboard.waitExit(180s);
  ASSERT_TRUE(code.has_value()) << "onboard did not finish";
  ASSERT_EQ(*code, 0) << "onboard failed";

  ASSERT_TRUE(waitUntil(60s,
                        [&] {
                          const auto reply = server.get("/api/sessions/accuracy");
                          if (reply.status != 200) return false;
                          const auto status = nlohmann::json::parse(reply.body);
                          return status["frames"] == kFrames && status["fusion_backlog"] == 0;
                        }))
      << server.get("/api/sessions").body << "\n"
      << server.log();

  const auto map_reply = server.get("/api/sessions/accuracy/map.bt");
  ASSERT_EQ(map_reply.status, 200);
  std::istringstream bt(map_reply.body);
  octomap::OcTree map(kResolution);
  ASSERT_TRUE(map.readBinary(bt));

  std::set<Key> occupied;
  for (auto it = map.begin_leafs(); it != map.end_leafs(); ++it) {
    if (!map.isNodeOccupied(*it)) continue;
    // A pruned leaf stands for all the finest voxels inside it.
    const int span = 1 << (16 - it.getDepth());
    const Vec3 corner = Vec3(it.getX(), it.getY(), it.getZ()) - Vec3::Constant(it.getSize() / 2);
    for (int dx = 0; dx < span; ++dx) {
      for (int dy = 0; dy < span; ++dy) {
        for (int dz = 0; dz < span; ++dz) {
          occupied.insert(keyOf(corner + (Vec3(dx, dy, dz) + Vec3::Constant(0.5)) * kResolution));
        }
      }
    }
  }

  // The same room and flight as the onboard run (seed 1, 10 Hz simulated time).
  sim::SimSource truth({.seed = 1, .rate_hz = 10.0, .max_frames = kFrames});
  const auto& scene = truth.scene();

  // Precision: an occupied voxel is right when a true surface passes through it.
  const double half_diagonal = kResolution * std::sqrt(3.0) / 2.0;
  size_t correct = 0, within_one_voxel = 0;
  for (const auto& [x, y, z] : occupied) {
    const Vec3 centre((x + 0.5) * kResolution, (y + 0.5) * kResolution, (z + 0.5) * kResolution);
    const double distance = scene.distanceToSurface(centre);
    correct += distance <= half_diagonal;
    within_one_voxel += distance <= half_diagonal + kResolution;
  }

  // Coverage: voxels of the true surfaces the left camera saw within range.
  const sim::Renderer renderer(scene, truth.camera());
  std::set<Key> seen;
  for (int i = 0; i < kFrames; ++i) {
    const auto T_map_camera = truth.flight().T_map_camera(i / 10.0);
    const cv::Mat depth = renderer.renderDepth(T_map_camera);
    for (int v = 0; v < depth.rows; v += 2) {
      for (int u = 0; u < depth.cols; u += 2) {
        const float z = depth.at<float>(v, u);
        if (z <= 0 || z > kMaxRange) continue;
        seen.insert(keyOf(T_map_camera * (truth.camera().rayThrough(u, v) * z)));
      }
    }
  }
  size_t covered = 0;
  for (const auto& key : seen) covered += occupied.count(key);

  const double precision = static_cast<double>(correct) / occupied.size();
  const double precision_1 = static_cast<double>(within_one_voxel) / occupied.size();
  const double coverage = static_cast<double>(covered) / seen.size();
  std::printf(
      "map accuracy: %zu occupied voxels, precision %.4f (surface in the voxel), "
      "%.4f (within one voxel); coverage %.4f of %zu seen surface voxels\n",
      occupied.size(), precision, precision_1, coverage, seen.size());
  RecordProperty("precision", std::to_string(precision));
  RecordProperty("coverage", std::to_string(coverage));
  // The issue asks for precision >= 0.90 and coverage >= 0.50; measured 0.977 and 0.923
  // flying on the odometry (docs/BENCHMARKS.md; the run is deterministic), so the bar sits
  // just below those.
  EXPECT_GE(precision, 0.97);
  EXPECT_GE(coverage, 0.90);
}

}  // namespace
}  // namespace stereomap::testing
