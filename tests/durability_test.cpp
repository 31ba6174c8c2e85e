// Durability holes found from outside (issue 13), tried with real processes over real DDS:
// a full disk (a small tmpfs), then freed space and restarts; a server started on a full
// disk; a flipped byte in the middle of a journal; and a server killed for a few seconds
// while its vehicle flies on (poses and the end of the flight must not be lost).
// Figures (sent / acknowledged / recovered) are printed for docs/BENCHMARKS.md.
#include <gtest/gtest.h>
#include <sys/mount.h>
#include <nlohmann/json.hpp>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <thread>

#include "proto/journal/journal.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;
using nlohmann::json;
namespace fs = std::filesystem;

json status(const ServerProcess& server, const std::string& id) {
  const auto reply = server.get("/api/sessions/" + id);
  return reply.status == 200 ? json::parse(reply.body) : json();
}

int count(const json& status, const char* key) {
  return status.is_object() && status[key].is_number() ? status[key].get<int>() : -1;
}

// Waits until a session's numbers stop changing and fusion is idle.
json settled(const ServerProcess& server, const std::string& id) {
  json last, now;
  waitUntil(
      60s,
      [&] {
        last = now;
        now = status(server, id);
        return now.is_object() && now == last && now["fusion_backlog"] == 0;
      },
      1s);
  return now;
}

// A series' value from Prometheus text (its own line, not the HELP line naming it).
double metric(const std::string& metrics, const std::string& series) {
  const size_t at = metrics.find("\n" + series + " ");
  return at == std::string::npos ? -1.0 : std::atof(metrics.c_str() + at + series.size() + 2);
}

// Fills the file system holding `path` with a file until it refuses (ENOSPC).
void fill(const fs::path& path) {
  std::FILE* file = std::fopen(path.c_str(), "wb");
  ASSERT_NE(file, nullptr);
  const std::string block(4096, 'x');
  while (std::fwrite(block.data(), 1, block.size(), file) == block.size() &&
         std::fflush(file) == 0) {
  }
  std::fclose(file);
}

// Every file under `dir` with its size, for failure messages.
std::string listing(const fs::path& dir) {
  std::string text = "files under " + dir.string() + ":\n";
  for (const auto& entry : fs::recursive_directory_iterator(dir)) {
    std::error_code ec;
    text += "  " + entry.path().string() + " " +
            std::to_string(entry.is_regular_file(ec) ? entry.file_size(ec) : 0) + "\n";
  }
  return text;
}

// A tmpfs of `megabytes` mounted on a new directory, unmounted at the end; empty path (and
// a reason) when this machine cannot mount one (not root, no permission in a container).
class SmallDisk {
 public:
  explicit SmallDisk(int megabytes) : dir_(makeTempDir("stereomap-small-disk")) {
    const std::string options = "size=" + std::to_string(megabytes) + "m";
    if (::mount("tmpfs", dir_.c_str(), "tmpfs", 0, options.c_str()) == 0) {
      mounted_ = true;
    } else {
      reason_ = std::string("cannot mount a tmpfs (") + std::strerror(errno) + "); run as root";
    }
  }
  ~SmallDisk() {
    if (mounted_) ::umount2(dir_.c_str(), MNT_DETACH);
    std::error_code ec;
    fs::remove_all(dir_, ec);
  }
  bool mounted() const { return mounted_; }
  const std::string& reason() const { return reason_; }
  const fs::path& dir() const { return dir_; }

 private:
  fs::path dir_;
  bool mounted_ = false;
  std::string reason_;
};

// Issue 13, items 4 and 5.
TEST(Durability, AFullDiskLosesNoAcknowledgedFrameAndIsReportedUntilSpaceIsFreed) {
  // 3 MB for the store until the ballast is freed, then room for the rest of the flight.
  SmallDisk disk(8);
  if (!disk.mounted()) GTEST_SKIP() << disk.reason();
  const fs::path ballast = disk.dir() / "ballast";
  std::ofstream(ballast, std::ios::binary) << std::string(5 << 20, 'b');
  const std::string store = (disk.dir() / "store").string();
  const std::string session = "full";
  constexpr int kFrames = 80;
  constexpr int kDomain = 77;

  json before_restart;
  {
    ServerProcess server(kDomain, {"--snapshot-every", "1000"}, store);
    ChildProcess onboard(onboardArgs(kDomain, session, kFrames, {"--rate", "10"}),
                         disk.dir().string() + ".onboard.log");
    // The disk fills: samples are refused, and the server says so everywhere.
    ASSERT_TRUE(waitUntil(60s, [&] { return !status(server, session)["store_error"].is_null(); }))
        << server.log();
    const auto health = server.get("/healthz");
    EXPECT_EQ(health.status, 503);
    EXPECT_NE(health.body.find("No space left on device"), std::string::npos) << health.body;
    const std::string metrics = server.get("/metrics").body;
    EXPECT_EQ(metric(metrics, "stereomap_store_healthy"), 0.0) << metrics;
    EXPECT_GT(metric(metrics, "stereomap_store_write_errors_total{topic=\"CloudFrame\"}"), 0.0);
    EXPECT_NE(server.log().find("store degraded: "), std::string::npos) << server.log();
    EXPECT_NE(server.log().find("No space left on device"), std::string::npos);
    const int acknowledged_when_full = count(status(server, session), "frames_received");
    std::this_thread::sleep_for(2s);  // still full: nothing more is taken

    // Space freed: the next write succeeds and everything is healthy again.
    fs::remove(ballast);
    ASSERT_TRUE(waitUntil(30s, [&] { return server.get("/healthz").status == 200; }))
        << server.log();
    ASSERT_EQ(onboard.waitExit(120s).value_or(-1), 0);
    EXPECT_NE(server.log().find("store writable again"), std::string::npos) << server.log();
    before_restart = settled(server, session);
    EXPECT_TRUE(before_restart["store_error"].is_null()) << before_restart.dump();
    EXPECT_GT(count(before_restart, "frames_received"), acknowledged_when_full)
        << "no frame was taken after space was freed";
    EXPECT_GT(count(before_restart, "samples_refused"), 0);
    std::printf(
        "full disk: %d frames sent, %d acknowledged before the disk filled up, %d in all, "
        "%d samples refused while full\n",
        kFrames, acknowledged_when_full, count(before_restart, "frames_received"),
        count(before_restart, "samples_refused"));
    server.process().kill9();
  }
  // Every acknowledged frame is in the journal, whole, and comes back.
  auto journal = proto::journal::readJournal(fs::path(store) / session / "journal.smj");
  ASSERT_TRUE(journal.ok());
  EXPECT_TRUE(journal->problem.empty()) << journal->problem;
  {
    ServerProcess again(kDomain, {}, store);
    const auto recovered = settled(again, session);
    EXPECT_EQ(count(recovered, "frames"), count(before_restart, "frames_received")) << again.log();
    std::printf("full disk: %d frames recovered after the restart\n", count(recovered, "frames"));
    again.process().stop();
  }

  // Item 5: started on a full disk, the server serves what it has, read-only, and says so.
  const fs::path room = disk.dir() / "room";  // what the operator frees below
  std::ofstream(room, std::ios::binary) << std::string(1 << 20, 'r');
  fill(ballast);
  {
    ServerProcess full(kDomain, {}, store, /*require_healthy=*/false);
    const auto health = full.get("/healthz");
    EXPECT_EQ(health.status, 503) << health.body;
    EXPECT_NE(health.body.find("degraded"), std::string::npos) << health.body;
    EXPECT_EQ(count(settled(full, session), "frames"), count(before_restart, "frames_received"));
    EXPECT_EQ(full.get("/api/sessions/" + session + "/map.bt").status, 200);
    EXPECT_EQ(metric(full.get("/metrics").body, "stereomap_store_healthy"), 0.0);
    fs::remove(ballast);
    fs::remove(room);
    EXPECT_TRUE(waitUntil(30s, [&] { return full.get("/healthz").status == 200; }))
        << full.log() << listing(disk.dir());
  }
  fs::remove(disk.dir().string() + ".onboard.log");
}

// Issue 17: a store on a read-only file system at start is a clear error and exit 1 (it
// was reported as "in use by another stereomap-server", the lock being unopenable).
TEST(Durability, AReadOnlyStoreAtStartIsAClearErrorAndExitOne) {
  SmallDisk disk(1);
  if (!disk.mounted()) GTEST_SKIP() << disk.reason();
  fs::create_directories(disk.dir() / "store");
  ASSERT_EQ(::mount(nullptr, disk.dir().c_str(), nullptr, MS_REMOUNT | MS_RDONLY, nullptr), 0)
      << std::strerror(errno);
  for (const char* store : {"store", "new-store"}) {
    const auto run =
        runTool({std::string(STEREOMAP_BIN_DIR) + "/stereomap-server", "--store",
                 (disk.dir() / store).string(), "--http", "127.0.0.1:0", "--domain", "78"},
                std::chrono::seconds(30));
    EXPECT_EQ(run.exit_code, 1) << run.output;
    EXPECT_NE(run.output.find("Read-only file system"), std::string::npos) << run.output;
    EXPECT_EQ(run.output.find("in use by another"), std::string::npos) << run.output;
  }
}

// The byte ranges of a format 2 journal's records (header 24 bytes: marker, length at +4).
std::vector<std::pair<size_t, size_t>> recordRanges(const std::string& bytes) {
  std::vector<std::pair<size_t, size_t>> ranges;
  for (size_t at = 8; at + 24 <= bytes.size();) {
    uint32_t length;
    std::memcpy(&length, &bytes[at + 4], 4);
    ranges.emplace_back(at, at + 24 + length);
    at += 24 + length;
  }
  return ranges;
}

ToolRun storeTool(const std::string& root, std::vector<std::string> args) {
  args.insert(args.begin(), {std::string(STEREOMAP_BIN_DIR) + "/stereomap-store", "--store", root});
  return runTool(args);
}

// Issue 13, item 6.
TEST(Durability, AFlippedByteInTheJournalCostsOnlyItsRecord) {
  constexpr int kDomain = 78;
  constexpr int kFrames = 120;
  const std::string session = "flip";
  const std::string store = makeTempDir("stereomap-flip-store");
  {
    ServerProcess server(kDomain, {"--snapshot-every", "50"}, store);
    ChildProcess onboard(onboardArgs(kDomain, session, kFrames, {"--rate", "20"}),
                         store + ".onboard.log");
    ASSERT_EQ(onboard.waitExit(120s).value_or(-1), 0);
    ASSERT_TRUE(waitUntil(60s, [&] { return count(status(server, session), "frames") == kFrames; }))
        << server.log();
  }
  const fs::path path = fs::path(store) / session / "journal.smj";
  std::string bytes;
  {
    std::ifstream in(path, std::ios::binary);
    bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  const auto ranges = recordRanges(bytes);
  auto intact = proto::journal::readJournal(path);
  ASSERT_TRUE(intact.ok());
  // A cloud record in the middle, which the newest snapshot covers.
  size_t victim = 0, clouds = 0;
  for (size_t i = 0; i < intact->records.size(); ++i) {
    if (std::holds_alternative<proto::CloudFrameMsg>(intact->records[i]) &&
        ++clouds == kFrames / 2) {
      victim = i;
    }
  }
  const uint64_t victim_number = intact->numbers[victim];
  bytes[(ranges[victim].first + ranges[victim].second) / 2] ^= 0x01;
  std::ofstream(path, std::ios::binary | std::ios::trunc) << bytes;

  const std::string lost = "record " + std::to_string(victim_number) + " lost";
  {
    ServerProcess server(kDomain, {"--snapshot-every", "50"}, store);
    const auto recovered = settled(server, session);
    EXPECT_EQ(count(recovered, "frames"), kFrames - 1) << server.log();
    EXPECT_NE(server.log().find(lost), std::string::npos) << server.log();
    EXPECT_EQ(server.log().find("(0 from a snapshot)"), std::string::npos) << server.log();
    std::printf("flipped byte: %d frames journaled, %d recovered (%s, newest snapshot used)\n",
                kFrames, count(recovered, "frames"), lost.c_str());
    // check names the record beside a running server; repair needs the store to itself.
    auto check = storeTool(store, {"check"});
    EXPECT_EQ(check.exit_code, 1) << check.output;
    EXPECT_NE(check.output.find(lost), std::string::npos) << check.output;
    EXPECT_NE(storeTool(store, {"repair", session}).exit_code, 0);
  }
  auto repair = storeTool(store, {"repair", session});
  EXPECT_EQ(repair.exit_code, 0) << repair.output;
  EXPECT_NE(repair.output.find("damaged original is kept"), std::string::npos) << repair.output;
  auto check = storeTool(store, {"check"});
  EXPECT_EQ(check.exit_code, 0) << check.output;
  bool kept_aside = false;
  for (const auto& entry : fs::directory_iterator(fs::path(store) / session)) {
    kept_aside |= entry.path().filename().string().rfind("journal.smj.damaged-", 0) == 0;
  }
  EXPECT_TRUE(kept_aside);
  {
    ServerProcess server(kDomain, {}, store);
    EXPECT_EQ(count(settled(server, session), "frames"), kFrames - 1) << server.log();
  }
  fs::remove_all(store);
  fs::remove(store + ".onboard.log");
}

std::vector<std::string> lines(const std::string& text) {
  std::vector<std::string> out;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) {
    if (!line.empty() && line[0] != '#') out.push_back(line);
  }
  return out;
}

// Issue 13, item 7.
TEST(Durability, PosesAndTheEndOfAFlightSurviveAShortServerOutage) {
  constexpr int kDomain = 80;
  const std::string store = makeTempDir("stereomap-outage-store");
  const std::string trajectory = store + ".vehicle.tum";
  {
    ChildProcess onboard(
        onboardArgs(kDomain, "outage", 120, {"--rate", "20", "--trajectory-out", trajectory}),
        store + ".onboard.log");
    {
      ServerProcess first(kDomain, {}, store);
      ASSERT_TRUE(waitUntil(60s, [&] { return count(status(first, "outage"), "poses") >= 30; }));
      first.process().kill9();
    }
    std::this_thread::sleep_for(3s);
    ServerProcess second(kDomain, {}, store);
    ASSERT_EQ(onboard.waitExit(120s).value_or(-1), 0);
    const auto final_status = settled(second, "outage");
    EXPECT_EQ(final_status["state"], "ended");
    EXPECT_EQ(final_status["ended_by"], "vehicle");
    std::ifstream in(trajectory);
    const std::string sent((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    const auto served = second.get("/api/sessions/outage/trajectory.tum");
    const auto sent_lines = lines(sent), served_lines = lines(served.body);
    EXPECT_EQ(served_lines.size(), sent_lines.size());
    std::printf("outage of 3 s: %zu poses sent, %zu in the session\n", sent_lines.size(),
                served_lines.size());
    // The same stamps (the TUM writers print positions differently).
    for (size_t i = 0; i < std::min(sent_lines.size(), served_lines.size()); ++i) {
      EXPECT_NEAR(std::stod(sent_lines[i]), std::stod(served_lines[i]), 1e-6) << "pose " << i;
    }
  }
  // The vehicle ends its flight while the server is down: the session ends all the same. Its
  // 5 s flight outlasts the first server by seconds: a sanitised server fused its 5th frame
  // only after the 2 s flight this had was over, and journaled the end it was not to see.
  {
    ChildProcess onboard(onboardArgs(kDomain, "unseen-end", 100, {"--rate", "20"}),
                         store + ".onboard.log");
    {
      ServerProcess first(kDomain, {}, store);
      ASSERT_TRUE(
          waitUntil(60s, [&] { return count(status(first, "unseen-end"), "frames") >= 5; }));
      first.process().kill9();
    }
    ASSERT_EQ(onboard.waitExit(120s).value_or(-1), 0);
    ServerProcess second(kDomain, {"--vehicle-timeout", "3"}, store);
    EXPECT_EQ(status(second, "unseen-end")["state"], "live");
    EXPECT_TRUE(waitUntil(20s, [&] { return status(second, "unseen-end")["state"] == "ended"; }))
        << second.log();
    EXPECT_EQ(status(second, "unseen-end")["ended_by"], "silence");
  }
  fs::remove_all(store);
  fs::remove(trajectory);
  fs::remove(store + ".onboard.log");
}

}  // namespace
}  // namespace stereomap::testing
