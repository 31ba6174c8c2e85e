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
    ServerProcess first(kDomain, {"--snapshot-every", "10"}, store);
    ASSERT_TRUE(waitUntil(60s, [&] { return (fused_before_kill = framesFused(first)) >= 30; }))
        << first.log();
    first.process().kill9();
  }
  ServerProcess second(kDomain, {"--snapshot-every", "10"}, store);
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
  // The restart after the kill started from a snapshot (every 10 frames), not from scratch.
  EXPECT_EQ(second.log().find("(0 from a snapshot)"), std::string::npos) << second.log();

  // Snapshot damaged, then gone: recovery falls back to replaying the whole journal.
  const auto session_dir = std::filesystem::path(store) / kSession;
  second.process().stop();
  for (const char* damage : {"truncate", "delete"}) {
    SCOPED_TRACE(damage);
    for (const auto& entry : std::filesystem::directory_iterator(session_dir)) {
      if (entry.path().extension() != ".ot") continue;
      if (std::string(damage) == "truncate") {
        std::filesystem::resize_file(entry.path(), std::filesystem::file_size(entry.path()) / 2);
      } else {
        std::filesystem::remove(entry.path());
      }
    }
    ServerProcess again(kDomain, {"--snapshot-every", "1000000"}, store);
    ASSERT_TRUE(waitUntil(60s, [&] { return framesFused(again) == fused; })) << again.log();
    const auto recovered = again.get("/api/sessions/" + kSession + "/map.bt");
    EXPECT_TRUE(recovered.body == expected.str());
    // The vehicle's ENDED event was journaled too: the session comes back as ended.
    EXPECT_EQ(nlohmann::json::parse(again.get("/api/sessions/" + kSession).body)["state"], "ended");
    EXPECT_NE(again.log().find("(0 from a snapshot)"), std::string::npos) << again.log();
    if (std::string(damage) == "truncate") {
      EXPECT_NE(again.log().find("unusable"), std::string::npos) << again.log();
    }
  }
  std::filesystem::remove_all(store);
  std::filesystem::remove(store + ".onboard.log");
}

}  // namespace
}  // namespace stereomap::testing
