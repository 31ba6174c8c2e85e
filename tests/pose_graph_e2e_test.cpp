// Cross-process (issue 18): stereomap-onboard flies the simulated room's loop with its pose
// graph on, over real DDS to a real stereomap-server: the vehicle's corrections reach the
// server, which fuses the session again with them. The same flight without the graph is the
// baseline: the server's trajectory and map of both are compared with the truth, with image
// noise (the trajectory) and without (the map: with noise its errors are the stereo's, whatever
// the poses). Figures in docs/BENCHMARKS.md ("Pose graph in the product").
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <unistd.h>
#include <cstdio>
#include <fstream>

#include "common/trajectory.hpp"
#include "onboard/eval/metrics.hpp"
#include "onboard/posegraph/g2o.hpp"
#include "onboard/sim/sim_source.hpp"
#include "tests/support/map_score.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;
using nlohmann::json;

// One domain per test: ctest runs the two side by side.
constexpr int kNoisyDomain = 87, kCleanDomain = 89;
constexpr int kFrames = 600;  // one loop of 40 s and half another: the loop closes
constexpr double kResolution = 0.05;
constexpr double kMaxRange = 6.0;  // the onboard default

struct Flown {
  json status;
  double ate_m = 0;
  double unaligned_m = 0;   // the same without alignment: where the map puts things
  double rotation_deg = 0;  // unaligned attitude error (rms)
  MapScore map;
};

// `noise`: the images' noise, grey levels (blur 1 px either way).
Flown fly(ServerProcess& server, int domain, const std::string& session, bool pose_graph,
          int noise) {
  Flown flown;
  const std::string truth_path = server.logPath() + "." + session + ".truth.tum";
  std::vector<std::string> extra = {
      "--rate",       "0", "--seed",      "1",       "--image-noise", std::to_string(noise),
      "--image-blur", "1", "--truth-out", truth_path};
  if (pose_graph) extra.push_back("--pose-graph");
  ChildProcess onboard(onboardArgs(domain, session, kFrames, extra),
                       server.logPath() + "." + session + ".onboard");
  const auto code = onboard.waitExit(300s);
  EXPECT_TRUE(code.has_value() && *code == 0) << "onboard failed";
  // Every frame fused and every correction fused in.
  const bool settled = waitUntil(180s, [&] {
    const auto reply = server.get("/api/sessions/" + session);
    if (reply.status != 200) return false;
    flown.status = json::parse(reply.body);
    return flown.status["frames"] == kFrames && flown.status["fusion_backlog"] == 0 &&
           flown.status["refusing"] == false;
  });
  EXPECT_TRUE(settled) << flown.status.dump() << "\n" << server.log();

  const auto tum = server.get("/api/sessions/" + session + "/trajectory.tum");
  const std::string estimate_path = server.logPath() + "." + session + ".server.tum";
  std::ofstream(estimate_path) << tum.body;
  const auto truth = common::readTrajectory(truth_path);
  const auto estimate = common::readTrajectory(estimate_path);
  EXPECT_TRUE(truth.ok() && estimate.ok());
  if (truth.ok() && estimate.ok()) {
    flown.ate_m = eval::absoluteError(*truth, *estimate, eval::Alignment::kSe3).translation.rmse;
    const auto unaligned = eval::absoluteError(*truth, *estimate, eval::Alignment::kNone);
    flown.unaligned_m = unaligned.translation.rmse;
    flown.rotation_deg = unaligned.rotation.rmse;
  }
  const sim::SimSource room({.seed = 1, .rate_hz = 10.0, .max_frames = kFrames});
  flown.map = scoreMap(server.get("/api/sessions/" + session + "/map.bt").body, kResolution, room,
                       kFrames, kMaxRange);
  return flown;
}

void report(const char* what, const Flown& odometry, const Flown& graph) {
  std::printf(
      "pose graph over DDS, %s, %d frames at %.2f m: %d corrections, %d re-fusions; server "
      "trajectory ATE %.4f m (odometry) -> %.4f m (unaligned %.4f -> %.4f, attitude %.3f -> "
      "%.3f deg); map precision %.4f -> %.4f, within one voxel %.4f -> %.4f, coverage %.4f -> "
      "%.4f\n",
      what, kFrames, kResolution, graph.status["corrections"].get<int>(),
      graph.status["refusions"].get<int>(), odometry.ate_m, graph.ate_m, odometry.unaligned_m,
      graph.unaligned_m, odometry.rotation_deg, graph.rotation_deg, odometry.map.precision,
      graph.map.precision, odometry.map.precision_1, graph.map.precision_1, odometry.map.coverage,
      graph.map.coverage);
  EXPECT_EQ(odometry.status["corrections"], 0);
  EXPECT_GE(graph.status["corrections"].get<int>(), 1);
  EXPECT_GE(graph.status["refusions"].get<int>(), 1);
  EXPECT_TRUE(graph.status["refusion_error"].is_null());
}

// Image noise sigma 2: the trajectory.
TEST(PoseGraphEndToEnd, CorrectionsReachTheServerAndTheTrajectoryImproves) {
  ServerProcess server(kNoisyDomain, {"--resolution", std::to_string(kResolution)});
  const Flown odometry = fly(server, kNoisyDomain, "odometry", /*pose_graph=*/false, /*noise=*/2);
  const Flown graph = fly(server, kNoisyDomain, "graph", /*pose_graph=*/true, /*noise=*/2);
  report("noise sigma 2", odometry, graph);
  RecordProperty("ate_odometry_m", std::to_string(odometry.ate_m));
  RecordProperty("ate_graph_m", std::to_string(graph.ate_m));
  // The goal for the trajectory: at most half the odometry's ATE (measured 0.34x:
  // 16.1 -> 5.5 mm; the run is deterministic but for thread timing).
  EXPECT_LE(graph.ate_m, 0.5 * odometry.ate_m);
  EXPECT_LT(graph.unaligned_m, odometry.unaligned_m);
}

// Clean images: the map. Measured precision 0.764 -> 0.868 (ground-truth poses: 0.943),
// coverage 0.935 -> 0.946; asserted at about half the gain. (Coverage read 0.748 -> 0.820 while
// a wall on a voxel face counted for one side only, by floating-point rounding: a misaligned
// map that occupied the other side was missing it; seen_voxels.hpp.)
TEST(PoseGraphEndToEnd, OnCleanImagesTheCorrectedMapIsMorePrecise) {
  ServerProcess server(kCleanDomain, {"--resolution", std::to_string(kResolution)});
  const Flown odometry =
      fly(server, kCleanDomain, "clean-odometry", /*pose_graph=*/false, /*noise=*/0);
  const Flown graph = fly(server, kCleanDomain, "clean-graph", /*pose_graph=*/true, /*noise=*/0);
  report("clean images", odometry, graph);
  RecordProperty("precision_odometry", std::to_string(odometry.map.precision));
  RecordProperty("precision_graph", std::to_string(graph.map.precision));
  EXPECT_GE(graph.map.precision, odometry.map.precision + 0.05);
  EXPECT_GE(graph.map.coverage, odometry.map.coverage + 0.005);
  EXPECT_LE(graph.ate_m, 0.5 * odometry.ate_m);
}

// Issue 41: the vehicle's keyframe graph of the three-loop flight (image noise sigma 2) written
// as g2o and solved again by stereomap-posegraph from its own chordal start: the vehicle's
// poses. Measured: 92 keyframes, 143 edges; at most 0.84 mm and 0.20 mrad apart (the file's
// error is the vehicle's to first order, and it has no robust loss). Asserted at 2.5 times that.
TEST(PoseGraphEndToEnd, TheVehiclesGraphSolvedAgainIsTheVehiclesSolution) {
  const std::string base = ::testing::TempDir() + "stereomap-graph-out-" + std::to_string(getpid());
  const std::string written = base + ".g2o", solved = base + ".solved.g2o";
  ChildProcess onboard(
      {std::string(STEREOMAP_BIN_DIR) + "/stereomap-onboard", "--source", "sim", "--no-publish",
       "--frames", "1200", "--rate", "0", "--seed", "1", "--image-noise", "2", "--image-blur", "1",
       "--pose-graph", "--graph-out", written},
      base + ".onboard.log");
  const auto flown = onboard.waitExit(300s);
  ASSERT_TRUE(flown.has_value() && *flown == 0);
  ChildProcess posegraph(
      {std::string(STEREOMAP_BIN_DIR) + "/stereomap-posegraph", written, "--out", solved},
      base + ".posegraph.log");
  const auto code = posegraph.waitExit(60s);
  ASSERT_TRUE(code.has_value() && *code == 0);
  const auto vehicle = posegraph::readG2o(written);
  const auto again = posegraph::readG2o(solved);
  ASSERT_TRUE(vehicle.ok()) << vehicle.error().message;
  ASSERT_TRUE(again.ok()) << again.error().message;
  ASSERT_EQ(vehicle->vertices.size(), again->vertices.size());
  // Three loops: keyframes, the odometry between them, and loop edges beyond it.
  EXPECT_GE(vehicle->vertices.size(), 60u);
  EXPECT_GE(vehicle->edges.size(), vehicle->vertices.size() + 20);
  EXPECT_EQ(vehicle->fixed, std::vector<int64_t>{0});
  double position_m = 0, attitude_rad = 0;
  for (size_t v = 0; v < vehicle->vertices.size(); ++v) {
    const auto& a = vehicle->vertices[v].T_world_vertex;
    const auto& b = again->vertices[v].T_world_vertex;
    position_m = std::max(position_m, (a.translation - b.translation).norm());
    attitude_rad = std::max(attitude_rad, a.rotation.angularDistance(b.rotation));
  }
  std::printf(
      "the vehicle's graph (%zu keyframes, %zu edges) solved again: at most %.3f mm, "
      "%.3f mrad from the vehicle's solve\n",
      vehicle->vertices.size(), vehicle->edges.size(), 1000 * position_m, 1000 * attitude_rad);
  EXPECT_LT(position_m, 0.002);
  EXPECT_LT(attitude_rad, 0.0005);
  for (const auto& path : {written, solved, base + ".onboard.log", base + ".posegraph.log"}) {
    std::remove(path.c_str());
  }
}

}  // namespace
}  // namespace stereomap::testing
