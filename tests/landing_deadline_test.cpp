// The landing's final approach on time (issue 54): stereomap-onboard descends the last 5 m onto
// the simulated deck at 10 Hz with its landing watch on (--skip-late off: every frame taken),
// publishing to a real stereomap-server. There the pad grows past the image: the watch's line
// fits, contours and edge refinement grew with it (a frame took 182 ms, 88 ms behind its slot
// on this machine; 28-38 frames late on another), so every frame must fit its period and none
// may be late. Runs alone (SERIAL): it measures time.
#include <gtest/gtest.h>

#include "tests/support/server_fixture.hpp"
#include "tests/support/stream_count.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;

constexpr int kDomain = 93;

TEST(LandingDeadline, EveryFrameOfTheFinalApproachFitsItsPeriod) {
  ServerProcess server(kDomain);
  // From 52 s into the 60 s descent: 5.3 m from the pad to touchdown, 81 frames.
  const std::string log = server.logPath() + ".onboard";
  ChildProcess onboard({std::string(STEREOMAP_BIN_DIR) + "/stereomap-onboard", "--source",
                        "sim:deck", "--landing", "default", "--skip-late", "off", "--start", "52",
                        "--rate", "10", "--session", "approach", "--spool", "memory",
                        "--dds-config", STEREOMAP_DDS_CONFIG, "--domain", std::to_string(kDomain)},
                       log);
  const auto code = onboard.waitExit(120s);
  const std::string text = readText(log);
  ASSERT_TRUE(code.has_value() && *code == 0) << text;
  const double frames = numberIn(text, R"(done: (\d+) frames)");
  const double late = numberIn(text, R"((\d+) late,)");
  const double slowest = numberIn(text, R"(slowest ([0-9.]+) ms)");
  const double behind = numberIn(text, R"(at most ([0-9.]+) ms behind)");
  const double tracked = numberIn(text, R"(landing pad: tracked in (\d+) of)");
  ASSERT_EQ(frames, 81) << text;
  // The watch still does its work: the pad is tracked until it outgrows the image (56-57 of
  // the 81 frames, measured).
  EXPECT_GE(tracked, 50) << text;
  EXPECT_EQ(late, 0) << text;
  EXPECT_LT(slowest, 100.0) << "a frame slower than the 10 Hz period\n" << text;
  EXPECT_LT(behind, 100.0) << text;
  std::printf("final approach: %.0f frames, slowest %.1f ms, at most %.0f ms behind, %.0f late\n",
              frames, slowest, behind, late);
  EXPECT_EQ(server.process().stop(), 0);
}

}  // namespace
}  // namespace stereomap::testing
