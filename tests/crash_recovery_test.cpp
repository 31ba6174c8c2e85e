// Cross-process crash test (issue 5): a simulated flight streams to stereomap-server, the
// server is killed with SIGKILL mid-stream and restarted on the same store. Every frame it
// had journaled must be in the recovered map, the stream must continue, and the final map
// must be byte-for-byte the map built from the journal's frames without a crash.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <filesystem>
#include <sstream>

#include "proto/cloud_codec.hpp"
#include "server/fusion/occupancy_map.hpp"
#include "server/store/journal.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;

constexpr int kDomain = 74;
constexpr int kFrames = 100;
const std::string kSession = "crash";

int framesFused(const ServerProcess& server) {
  const auto reply = server.get("/api/sessions/" + kSession);
  if (reply.status != 200) return -1;
  return nlohmann::json::parse(reply.body)["frames"].get<int>();
}

TEST(CrashRecovery, KilledServerLosesNothingItJournaled) {
  const std::string store = makeTempDir("stereomap-crash-store");
  int fused_before_kill = 0;
  ChildProcess onboard(onboardArgs(kDomain, kSession, kFrames, {"--rate", "20"}),
                       store + ".onboard.log");
  {
    ServerProcess first(kDomain, {}, store);
    ASSERT_TRUE(waitUntil(60s, [&] { return (fused_before_kill = framesFused(first)) >= 30; }))
        << first.log();
    first.process().kill9();
  }
  ServerProcess second(kDomain, {}, store);
  ASSERT_TRUE(onboard.waitExit(120s).value_or(-1) == 0) << "onboard did not finish";
  int previous = -2, fused = -1;
  ASSERT_TRUE(waitUntil(
      60s,
      [&] {
        previous = fused;
        fused = framesFused(second);
        const auto status = nlohmann::json::parse(second.get("/api/sessions/" + kSession).body);
        return fused == previous && status["fusion_backlog"] == 0;
      },
      1s))
      << second.log();

  auto journal = store::readJournal(std::filesystem::path(store) / kSession / "journal.smj");
  ASSERT_TRUE(journal.ok()) << journal.error().message;
  std::vector<proto::CloudFrameMsg> frames;
  for (const auto& record : journal->records) {
    if (const auto* frame = std::get_if<proto::CloudFrameMsg>(&record)) frames.push_back(*frame);
  }
  std::printf(
      "crash test: %d frames fused before the kill, %zu journaled in all, %d fused at "
      "the end\n",
      fused_before_kill, frames.size(), fused);
  EXPECT_EQ(static_cast<size_t>(fused), frames.size());
  EXPECT_GT(frames.size(), static_cast<size_t>(fused_before_kill));  // the stream went on
  for (size_t i = 1; i < frames.size(); ++i) {
    ASSERT_GT(frames[i].seq, frames[i - 1].seq) << "a frame was journaled twice";
  }

  fusion::OccupancyMap reference({.resolution = 0.1});
  for (const auto& frame : frames) {
    auto cloud = proto::decodeCloud(frame.payload);
    ASSERT_TRUE(cloud.ok());
    const common::Quat q(frame.sensor_orientation[3], frame.sensor_orientation[0],
                         frame.sensor_orientation[1], frame.sensor_orientation[2]);
    const common::Vec3 t(frame.sensor_position[0], frame.sensor_position[1],
                         frame.sensor_position[2]);
    reference.insertCloud(*cloud, {q.normalized(), t}, frame.max_range);
  }
  std::ostringstream expected;
  ASSERT_TRUE(reference.writeBinary(expected));
  const auto served = second.get("/api/sessions/" + kSession + "/map.bt");
  ASSERT_EQ(served.status, 200);
  EXPECT_EQ(served.body.size(), expected.str().size());
  EXPECT_TRUE(served.body == expected.str()) << "the recovered map differs from the reference";
  std::filesystem::remove_all(store);
  std::filesystem::remove(store + ".onboard.log");
}

}  // namespace
}  // namespace stereomap::testing
