// Cross-process: stereomap-onboard flies the simulated room and streams over real DDS to a
// real stereomap-server; the server's map (map.bt over HTTP) is compared with the room's
// true geometry. Figures are reported in docs/BENCHMARKS.md.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "onboard/sim/sim_source.hpp"
#include "tests/support/map_score.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;
using common::Vec3;

constexpr int kFrames = 100;
constexpr double kResolution = 0.1;
constexpr double kMaxRange = 6.0;  // the onboard default

// Flies sim room 1 with a camera model on the odometry's poses, streams it to a server and
// scores the server's map.
MapScore flyAndScore(int domain, const std::string& camera, const std::string& vo = "fast") {
  ServerProcess server(domain, {"--resolution", std::to_string(kResolution)});
  ChildProcess onboard(onboardArgs(domain, "accuracy", kFrames,
                                   {"--rate", "0", "--seed", "1", "--camera", camera, "--vo", vo,
                                    // thinned to the server's voxels, as vehicles send
                                    "--map-resolution", std::to_string(kResolution)}),
                       server.logPath() + ".onboard");
  const auto code = onboard.waitExit(180s);
  EXPECT_TRUE(code.has_value()) << "onboard did not finish";
  EXPECT_EQ(code.value_or(-1), 0) << "onboard failed";

  EXPECT_TRUE(waitUntil(60s,
                        [&] {
                          const auto reply = server.get("/api/sessions/accuracy");
                          if (reply.status != 200) return false;
                          const auto status = nlohmann::json::parse(reply.body);
                          return status["frames"] == kFrames && status["fusion_backlog"] == 0;
                        }))
      << server.get("/api/sessions").body << "\n"
      << server.log();

  const auto map_reply = server.get("/api/sessions/accuracy/map.bt");
  EXPECT_EQ(map_reply.status, 200);
  if (map_reply.status != 200) return {};
  // The same room and flight as the onboard run (seed 1, 10 Hz simulated time).
  const sim::SimSource truth({.seed = 1, .rate_hz = 10.0, .max_frames = kFrames});
  const auto score = scoreMap(map_reply.body, kResolution, truth, kFrames, kMaxRange);
  std::printf(
      "map accuracy, %s camera: %zu occupied voxels, precision %.4f (surface in the voxel), "
      "%.4f (within one voxel); coverage %.4f of %zu seen surface voxels\n",
      camera.c_str(), score.occupied, score.precision, score.precision_1, score.coverage,
      score.seen);
  ::testing::Test::RecordProperty("precision", std::to_string(score.precision));
  ::testing::Test::RecordProperty("coverage", std::to_string(score.coverage));
  return score;
}

TEST(MapAccuracy, SimFlightMapMatchesTheRoomOverRealDds) {
  const auto score = flyAndScore(71, "clean");
  // The issue asks for precision >= 0.90 and coverage >= 0.50; measured 0.977 and 0.949
  // flying on the odometry (docs/BENCHMARKS.md; the run is deterministic; 0.923 before a
  // surface on a voxel face covered the voxels on both sides), so the bar sits just below.
  EXPECT_GE(score.precision, 0.97);
  EXPECT_GE(score.coverage, 0.94);
}

TEST(MapAccuracy, TypicalCameraNoiseStaysOutOfTheMap) {
  const auto score = flyAndScore(93, "typical");
  // Issue 16 asks for precision >= 0.95 and coverage >= 0.85 with the typical camera, on the
  // odometry's poses; measured 0.977 and 0.918 (0.975 / 0.914 with full rows). Before:
  // 0.910 / 0.907 without the depth step's noise handling (--noise-handling off), and 0.62 /
  // 0.50 while the odometry's stereo matches were biased by the cameras' gain mismatch.
  EXPECT_GE(score.precision, 0.97);
  EXPECT_GE(score.coverage, 0.90);
}

}  // namespace
}  // namespace stereomap::testing
