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

constexpr int kDomain = 71;
constexpr int kFrames = 100;
constexpr double kResolution = 0.1;
constexpr double kMaxRange = 6.0;  // the onboard default

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
  // The same room and flight as the onboard run (seed 1, 10 Hz simulated time).
  const sim::SimSource truth({.seed = 1, .rate_hz = 10.0, .max_frames = kFrames});
  const auto score = scoreMap(map_reply.body, kResolution, truth, kFrames, kMaxRange);
  const double precision = score.precision, coverage = score.coverage;
  std::printf(
      "map accuracy: %zu occupied voxels, precision %.4f (surface in the voxel), "
      "%.4f (within one voxel); coverage %.4f of %zu seen surface voxels\n",
      score.occupied, precision, score.precision_1, coverage, score.seen);
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
