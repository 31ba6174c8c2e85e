// Cross-process crash test (issue 5): a simulated flight streams to stereomap-server, the
// server is killed with SIGKILL mid-stream and restarted on the same store. Every frame it
// had journaled must be in the recovered map, the stream must continue, and the final map
// must be byte-for-byte the map built from the journal's frames without a crash. And a kill
// in the middle of a snapshot write (issue 21): recovery uses the previous snapshot.
#include <gtest/gtest.h>

#include <poll.h>
#include <sys/inotify.h>
#include <unistd.h>
#include <nlohmann/json.hpp>
#include <set>

#include <filesystem>
#include <sstream>

#include "proto/cloud_codec.hpp"
#include "proto/journal/journal.hpp"
#include "proto/pose_fields.hpp"
#include "server/fusion/occupancy_map.hpp"
#include "server/store/session_journals.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;

constexpr int kDomain = 74;
constexpr int kFrames = 100;
const std::string kSession = "crash";

// The session's cloud frames as its journal holds them.
std::vector<proto::CloudFrameMsg> journaledFrames(const std::string& store) {
  auto journal =
      proto::journal::readJournal(std::filesystem::path(store) / kSession / "journal.smj");
  EXPECT_TRUE(journal.ok()) << journal.error().message;
  std::vector<proto::CloudFrameMsg> frames;
  if (!journal.ok()) return frames;
  for (const auto& record : journal->records) {
    if (const auto* frame = std::get_if<proto::CloudFrameMsg>(&record)) frames.push_back(*frame);
  }
  return frames;
}

// The OctoMap binary (.bt) of the map those frames make without any crash.
std::string referenceMapBinary(const std::vector<proto::CloudFrameMsg>& frames) {
  fusion::OccupancyMap reference({.resolution = 0.1});
  for (const auto& frame : frames) {
    auto cloud = proto::decodeCloud(frame.payload, proto::payloadInfo(frame));
    EXPECT_TRUE(cloud.ok());
    if (!cloud.ok()) continue;
    reference.insertCloud(*cloud,
                          proto::rigidFromFields(frame.sensor_position, frame.sensor_orientation),
                          frame.max_range);
  }
  std::ostringstream bt;
  EXPECT_TRUE(reference.writeBinary(bt));
  return bt.str();
}

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

  const auto frames = journaledFrames(store);
  std::printf(
      "crash test: %d frames fused before the kill, %zu journaled in all, %d fused at "
      "the end\n",
      fused_before_kill, frames.size(), fused);
  EXPECT_EQ(static_cast<size_t>(fused), frames.size());
  EXPECT_GT(frames.size(), static_cast<size_t>(fused_before_kill));  // the stream went on
  // Each once; not necessarily in seq order: the vehicle sends again, after newer live
  // frames, what the killed server never acknowledged (its spool, issue 38).
  std::set<uint64_t> seqs;
  for (const auto& frame : frames) {
    ASSERT_TRUE(seqs.insert(frame.seq).second) << "frame " << frame.seq << " journaled twice";
  }
  const std::string expected = referenceMapBinary(frames);
  const auto served = second.get("/api/sessions/" + kSession + "/map.bt");
  ASSERT_EQ(served.status, 200);
  EXPECT_EQ(served.body.size(), expected.size());
  EXPECT_TRUE(served.body == expected) << "the recovered map differs from the reference";
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
    EXPECT_TRUE(recovered.body == expected);
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

// Issue 21: kill -9 while a snapshot is being written (its temporary file exists, the rename
// has not happened): the restart uses the previous snapshot, removes the temporary, and the
// map equals the one built from every journaled frame.
TEST(CrashRecovery, AKillInTheMiddleOfASnapshotWriteUsesThePreviousSnapshot) {
  constexpr int kSnapshotDomain = 85;
  const std::string store = makeTempDir("stereomap-snapshot-crash-store");
  const auto dir = std::filesystem::path(store) / kSession;
  ChildProcess onboard(onboardArgs(kSnapshotDomain, kSession, 2 * kFrames, {"--rate", "20"}),
                       store + ".onboard.log");
  std::string killed_while;
  for (int attempt = 0; attempt < 5 && killed_while.empty(); ++attempt) {
    ServerProcess server(kSnapshotDomain, {"--snapshot-every", "5"}, store);
    // A snapshot to fall back on, then a watch for the next one's temporary file.
    ASSERT_TRUE(waitUntil(60s, [&] {
      return std::filesystem::exists(dir) && !store::snapshotsIn(dir).empty();
    })) << server.log();
    const int watch = ::inotify_init1(IN_CLOEXEC);
    ASSERT_GE(watch, 0);
    ASSERT_GE(::inotify_add_watch(watch, dir.c_str(), IN_CREATE), 0);
    bool seen = false;
    const auto deadline = std::chrono::steady_clock::now() + scaledTimeout(30s);
    while (!seen && std::chrono::steady_clock::now() < deadline) {
      pollfd p{watch, POLLIN, 0};
      if (::poll(&p, 1, 100) <= 0) continue;
      alignas(inotify_event) char buffer[4096];
      const ssize_t n = ::read(watch, buffer, sizeof(buffer));
      for (ssize_t at = 0; at < n;) {
        const auto* event = reinterpret_cast<const inotify_event*>(buffer + at);
        const std::string name = event->len > 0 ? event->name : "";
        if (name.rfind("snapshot-", 0) == 0 && name.find(".tmp-") != std::string::npos) seen = true;
        at += static_cast<ssize_t>(sizeof(inotify_event) + event->len);
      }
    }
    if (seen) server.process().kill9();
    ::close(watch);
    ASSERT_TRUE(seen) << "no snapshot was written within 30 s\n" << server.log();
    for (const auto& entry : std::filesystem::directory_iterator(dir)) {
      if (entry.path().filename().string().find(".tmp-") != std::string::npos) {
        killed_while = entry.path().filename().string();
      }
    }
    // Else the write finished before the kill landed: try again on the next snapshot.
  }
  ASSERT_FALSE(killed_while.empty()) << "the kill never landed inside a snapshot write";
  const uint64_t fallback = store::snapshotsIn(dir).front().first;

  ServerProcess restarted(kSnapshotDomain, {"--snapshot-every", "1000000"}, store);
  ASSERT_TRUE(onboard.waitExit(120s).value_or(-1) == 0) << "onboard did not finish";
  // Every journaled frame fused, and nothing more arriving.
  std::vector<proto::CloudFrameMsg> frames;
  int previous = -1;
  ASSERT_TRUE(waitUntil(
      60s,
      [&] {
        frames = journaledFrames(store);
        const int fused = framesFused(restarted);
        const bool settled = fused == static_cast<int>(frames.size()) && fused == previous;
        previous = fused;
        return settled;
      },
      1s))
      << restarted.log();
  std::printf("snapshot crash test: killed while %s existed; restarted from snapshot %llu\n",
              killed_while.c_str(), static_cast<unsigned long long>(fallback));
  EXPECT_NE(restarted.log().find("removed " + killed_while), std::string::npos) << restarted.log();
  EXPECT_FALSE(std::filesystem::exists(dir / killed_while));
  EXPECT_EQ(restarted.log().find("(0 from a snapshot)"), std::string::npos) << restarted.log();
  EXPECT_TRUE(restarted.get("/api/sessions/" + kSession + "/map.bt").body ==
              referenceMapBinary(frames))
      << "the recovered map differs from the map of every journaled frame";
  std::filesystem::remove_all(store);
  std::filesystem::remove(store + ".onboard.log");
}

}  // namespace
}  // namespace stereomap::testing
