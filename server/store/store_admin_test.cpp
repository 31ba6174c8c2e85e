// Session management over a real store directory (real files, real SQLite, real journals):
// close, open read-only, per-session resolution, delete and merge, and the store lock.
#include "server/store/store_admin.hpp"

#include <gtest/gtest.h>
#include <sys/resource.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <csignal>
#include <fstream>
#include <thread>

#include "server/core/exports.hpp"
#include "testing/journal_format_one.hpp"
#include "testing/synthetic.hpp"

namespace stereomap::store {
namespace {

namespace fs = std::filesystem;
using common::ErrorCode;

// A server's store side, as stereomap-server wires it (without DDS).
struct Server {
  Server(const fs::path& root, double resolution, size_t max_sessions = 256)
      : journals(root, resolution) {
    core::MapServerOptions options;
    options.resolution = resolution;
    options.max_sessions = max_sessions;
    options.log = &journals;
    options.snapshots = &journals;
    options.archive = &journals;
    options.snapshot_every = 4;
    map = std::make_unique<core::MapServer>(options);
    auto created = StoreAdmin::create(root, *map, &journals, {.default_resolution = resolution});
    EXPECT_TRUE(created.ok()) << created.error().message;
    admin = std::move(created).value();
  }
  SessionJournals journals;
  std::unique_ptr<core::MapServer> map;
  std::unique_ptr<StoreAdmin> admin;  // last: unlocks first
};

proto::CloudFrameMsg wallFrame(const std::string& session, uint64_t seq, double y_offset = 0,
                               const std::string& vehicle = "v1") {
  auto cloud = testing::planeCloud(2.05 + 0.1 * seq, 0.6, 0.05);
  auto frame = testing::planeFrame(vehicle, session, seq, cloud);
  frame.stamp_ns = 1'000'000'000 + static_cast<int64_t>(seq) * 100'000'000;
  frame.sensor_position = {0, y_offset, 0};
  return frame;
}

proto::PoseMsg pose(const std::string& session, uint64_t seq, const std::string& vehicle = "v1") {
  proto::PoseMsg p;
  p.vehicle_id = vehicle;
  p.session_id = session;
  p.seq = seq;
  p.stamp_ns = 1'000'000'000 + static_cast<int64_t>(seq) * 100'000'000;
  p.position = {0.1 * seq, 0, 1};
  return p;
}

proto::SessionEventMsg ended(const std::string& session, const std::string& vehicle = "v1") {
  proto::SessionEventMsg e;
  e.vehicle_id = vehicle;
  e.session_id = session;
  e.stamp_ns = 9'000'000'000;
  e.kind = proto::SessionEventKind::kEnded;
  return e;
}

// The poses of frames [0, frames) moved by `dy` in y, as a vehicle's pose graph would send.
proto::PoseCorrectionMsg correction(const std::string& session, int frames, double dy) {
  proto::PoseCorrectionMsg c;
  c.vehicle_id = "v1";
  c.session_id = session;
  c.seq = 1;
  c.stamp_ns = pose(session, frames).stamp_ns;
  for (int i = 0; i < frames; ++i) {
    const auto sent = pose(session, i);
    c.keyframes.push_back(
        {sent.stamp_ns, {sent.position[0], sent.position[1] + dy, sent.position[2]}, {0, 0, 0, 1}});
  }
  return c;
}

void fly(core::MapServer& map, const std::string& session, int frames, double y_offset = 0,
         int first = 0) {
  for (int i = first; i < first + frames; ++i) {
    ASSERT_TRUE(map.ingest(wallFrame(session, i, y_offset)));
    ASSERT_TRUE(map.ingest(pose(session, i)));
  }
  map.find(session)->waitUntilIdle();
}

class StoreAdminTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string name = "stereomap-admin-";
    name += std::to_string(::getpid());
    name += ::testing::UnitTest::GetInstance()->current_test_info()->name();
    root_ = fs::temp_directory_path() / name;
    fs::remove_all(root_);
  }
  void TearDown() override { fs::remove_all(root_); }
  fs::path root_;
};

TEST_F(StoreAdminTest, ClosedSessionReopensReadOnlyWithItsMapAndTrajectory) {
  std::vector<fusion::VoxelIndex> voxels;
  {
    Server server(root_, 0.1);
    fly(*server.map, "f1", 6);
    voxels = server.map->find("f1")->occupiedVoxels();
    ASSERT_FALSE(voxels.empty());
    ASSERT_TRUE(server.admin->close("f1").ok());
    EXPECT_EQ(server.map->find("f1"), nullptr);
    EXPECT_TRUE(fs::exists(root_ / "f1" / "closed"));
    EXPECT_EQ(server.admin->close("f1").error().code, ErrorCode::kConflict);
    EXPECT_FALSE(server.map->ingest(wallFrame("f1", 7)));  // closed: refused, counted
    EXPECT_NE(server.map->metricsText().find("reason=\"session_closed\""), std::string::npos);
    const auto closed = server.admin->closedSessions();
    ASSERT_EQ(closed.size(), 1u);
    EXPECT_EQ(closed[0].frames_fused, 6u);
    EXPECT_EQ(closed[0].occupied_voxels, voxels.size());
  }
  Server restarted(root_, 0.2);  // another default resolution: the session keeps its own
  EXPECT_TRUE(restarted.admin->recoverAll().empty());  // closed sessions are not loaded
  EXPECT_FALSE(restarted.map->ingest(wallFrame("f1", 8)));
  EXPECT_EQ(restarted.admin->open("nope").error().code, ErrorCode::kNotFound);
  ASSERT_TRUE(restarted.admin->open("f1").ok());
  const auto session = restarted.map->find("f1");
  ASSERT_NE(session, nullptr);
  const auto status = session->status();
  EXPECT_TRUE(status.read_only);
  EXPECT_DOUBLE_EQ(status.resolution, 0.1);
  EXPECT_EQ(status.poses, 6u);
  EXPECT_EQ(session->occupiedVoxels(), voxels);
  EXPECT_FALSE(restarted.map->ingest(wallFrame("f1", 9)));  // read-only
  EXPECT_NE(restarted.map->metricsText().find("reason=\"read_only\""), std::string::npos);
  EXPECT_EQ(restarted.admin->open("f1").error().code, ErrorCode::kConflict);
  EXPECT_TRUE(restarted.admin->closedSessions().empty());
}

TEST_F(StoreAdminTest, RecoveryUsesEachSessionsOwnResolution) {
  std::vector<fusion::VoxelIndex> voxels;
  {
    Server server(root_, 0.05);
    fly(*server.map, "fine", 5);  // 5 frames, snapshot every 4: snapshot + 1 replayed
    voxels = server.map->find("fine")->occupiedVoxels();
  }
  Server restarted(root_, 0.2);
  const auto recovered = restarted.admin->recoverAll();
  ASSERT_EQ(recovered.size(), 1u);
  // The snapshot due after frame 4 is taken by its writer thread, after frame 4 or 5.
  EXPECT_GE(recovered[0].snapshot_frames, 4u);
  const auto session = restarted.map->find("fine");
  ASSERT_NE(session, nullptr);
  EXPECT_DOUBLE_EQ(session->status().resolution, 0.05);
  EXPECT_FALSE(session->status().read_only);
  EXPECT_EQ(session->occupiedVoxels(), voxels);
}

// Recovery opens each live session's journal for appending from its own reading: a torn
// tail is cut then, not at the first sample (which would read the whole journal again on an
// ingest thread); the next sample appends after the last whole record.
TEST_F(StoreAdminTest, RecoveryOpensTheJournalItRead) {
  uint64_t whole_bytes = 0;
  {
    Server server(root_, 0.1);
    fly(*server.map, "torn", 3);
    whole_bytes = fs::file_size(root_ / "torn" / kJournalName);
  }
  {
    std::ofstream tail(root_ / "torn" / kJournalName, std::ios::binary | std::ios::app);
    tail << "SMRC";  // a record whose write was cut short
  }
  Server restarted(root_, 0.1);
  const auto recovered = restarted.admin->recoverAll();
  ASSERT_EQ(recovered.size(), 1u);
  EXPECT_GT(recovered[0].seconds, 0.0);
  EXPECT_EQ(fs::file_size(root_ / "torn" / kJournalName), whole_bytes);  // cut at recovery
  ASSERT_TRUE(restarted.map->ingest(wallFrame("torn", 3)));
  auto read = readJournal(root_ / "torn" / kJournalName);
  ASSERT_TRUE(read.ok());
  EXPECT_TRUE(read->problem.empty()) << read->problem;
  EXPECT_EQ(read->numbers.back(), read->last_number);
}

// Review of issue 17: a format 1 journal (a store written before issue 13) is upgraded
// before it is replayed. Replaying it brings snapshots due, labelled with record numbers;
// the upgrade, run after, read those labels as frame counts and moved each snapshot to a
// later record than it holds: the frames between were lost from the map at the next start.
TEST_F(StoreAdminTest, AFormatOneJournalIsUpgradedBeforeItIsReplayed) {
  std::vector<fusion::VoxelIndex> voxels;
  {
    Server server(root_, 0.1);
    fly(*server.map, "old", 10);  // frames are records 1, 3, ..., 19
    voxels = server.map->find("old")->occupiedVoxels();
  }
  const fs::path dir = root_ / "old";
  for (const auto& [label, snapshot] : snapshotsIn(dir)) fs::remove(snapshot);
  const std::string v1 = testing::formatOneOf(dir / kJournalName);
  std::ofstream(dir / kJournalName, std::ios::binary | std::ios::trunc) << v1;
  ASSERT_EQ(readJournal(dir / kJournalName)->version, 1);
  {  // a store opened only for reading (stereomap-store show) reads it and writes nothing
    core::MapServer map({.resolution = 0.1});
    auto reader = StoreAdmin::create(root_, map, nullptr, {.writable = false});
    ASSERT_TRUE(reader.ok()) << reader.error().message;
    ASSERT_TRUE((*reader)->open("old").ok());
    EXPECT_EQ(map.find("old")->occupiedVoxels(), voxels);
    EXPECT_EQ(readJournal(dir / kJournalName)->version, 1);
  }
  {  // the upgrade cannot be written: served as it is, without snapshots, and said so
    Server server(root_, 0.1);
    std::signal(SIGXFSZ, SIG_IGN);
    rlimit saved{};
    ASSERT_EQ(::getrlimit(RLIMIT_FSIZE, &saved), 0);
    rlimit limited = saved;
    limited.rlim_cur = fs::file_size(dir / kJournalName) / 2;
    ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &limited), 0);
    const auto recovered = server.admin->recoverAll();
    ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &saved), 0);
    std::signal(SIGXFSZ, SIG_DFL);
    ASSERT_EQ(recovered.size(), 1u);
    EXPECT_NE(recovered[0].problem.find("cannot be upgraded"), std::string::npos)
        << recovered[0].problem;
    EXPECT_EQ(recovered[0].frames, 10u);
    EXPECT_EQ(server.map->find("old")->occupiedVoxels(), voxels);
    EXPECT_EQ(server.map->find("old")->status().snapshots, 0u);
  }
  EXPECT_TRUE(snapshotsIn(dir).empty());
  ASSERT_EQ(readJournal(dir / kJournalName)->version, 1);
  {
    Server upgraded(root_, 0.1);  // snapshot every 4 frames: due twice while replaying
    const auto recovered = upgraded.admin->recoverAll();
    ASSERT_EQ(recovered.size(), 1u);
    EXPECT_TRUE(recovered[0].problem.empty()) << recovered[0].problem;
    EXPECT_EQ(recovered[0].frames, 10u);
    EXPECT_EQ(upgraded.map->find("old")->occupiedVoxels(), voxels);
  }
  const auto journal = readJournal(dir / kJournalName);
  ASSERT_TRUE(journal.ok());
  EXPECT_EQ(journal->version, 2);
  const auto snapshots = snapshotsIn(dir);
  ASSERT_FALSE(snapshots.empty());
  for (const auto& [label, snapshot] : snapshots) {
    EXPECT_EQ(label % 2, 1u) << snapshot;  // a frame's record number
    EXPECT_GE(label, 7u) << snapshot;      // at least the 4th frame's
  }
  Server restarted(root_, 0.1);  // from the snapshot: the same map
  const auto recovered = restarted.admin->recoverAll();
  ASSERT_EQ(recovered.size(), 1u);
  EXPECT_GE(recovered[0].snapshot_frames, 4u);
  EXPECT_EQ(restarted.map->find("old")->occupiedVoxels(), voxels);
}

TEST_F(StoreAdminTest, OnlyOneWriterPerStore) {
  Server server(root_, 0.1);
  core::MapServer other({});
  SessionJournals journals(root_, 0.1);
  auto second = StoreAdmin::create(root_, other, &journals, {});
  ASSERT_FALSE(second.ok());
  EXPECT_EQ(second.error().code, ErrorCode::kConflict);
  EXPECT_NE(second.error().message.find("in use"), std::string::npos);
  auto reader = StoreAdmin::create(root_, other, nullptr, {.writable = false});
  ASSERT_TRUE(reader.ok());  // reading beside a server is fine...
  EXPECT_EQ((*reader)->remove("x").error().code, ErrorCode::kInvalidArgument);  // ...writing not
}

TEST_F(StoreAdminTest, DeleteRefusesLiveSessionsAndRemovesEverything) {
  Server server(root_, 0.1);
  fly(*server.map, "gone", 3);
  server.admin->checkpoint(true);
  EXPECT_EQ(server.admin->remove("gone").error().code, ErrorCode::kConflict);  // live
  ASSERT_TRUE(server.map->ingest(ended("gone")));
  ASSERT_TRUE(server.admin->remove("gone").ok());
  EXPECT_FALSE(fs::exists(root_ / "gone"));
  EXPECT_EQ(server.map->find("gone"), nullptr);
  EXPECT_EQ(server.admin->remove("gone").error().code, ErrorCode::kNotFound);
  auto catalog = Catalog::openReadOnly(root_);
  ASSERT_TRUE(catalog.ok());
  EXPECT_TRUE((*catalog)->list()->empty());
  // The id is free again: a new flight may use it.
  EXPECT_TRUE(server.map->ingest(wallFrame("gone", 0)));
}

// Two vehicles in one session: the first one's end does not end the session while the other
// flies (an operator could delete it under the second vehicle); the last one's does, and the
// catalog keeps it so.
TEST_F(StoreAdminTest, ASessionEndsWhenItsLastVehicleEnds) {
  {
    Server server(root_, 0.1);
    for (const char* vehicle : {"v1", "v2"}) {
      auto started = ended("pair", vehicle);
      started.stamp_ns = 500'000'000;
      started.kind = proto::SessionEventKind::kStarted;
      ASSERT_TRUE(server.map->ingest(started));
    }
    fly(*server.map, "pair", 3);
    ASSERT_TRUE(server.map->ingest(ended("pair", "v1")));
    EXPECT_FALSE(server.map->find("pair")->status().ended);
    const auto removed = server.admin->remove("pair");
    ASSERT_FALSE(removed.ok());
    EXPECT_EQ(removed.error().code, ErrorCode::kConflict);  // v2 flies
    ASSERT_TRUE(server.map->ingest(ended("pair", "v2")));
    const auto status = server.map->find("pair")->status();
    EXPECT_TRUE(status.ended);
    EXPECT_EQ(status.ended_by, "vehicle");
    server.admin->checkpoint(true);
  }
  auto catalog = Catalog::openReadOnly(root_);
  ASSERT_TRUE(catalog.ok());
  const auto rows = (*catalog)->list();
  ASSERT_TRUE(rows.ok());
  ASSERT_EQ(rows->size(), 1u);
  EXPECT_EQ(rows->front().state, "ended");
}

// A vehicle in its own frame that ended and flies again: its session is live, and stays so
// through a restart (recovery takes own-frame starts before the frames, but counts each in
// its place among the ends).
TEST_F(StoreAdminTest, AVehicleThatFliesAgainKeepsItsSessionLiveThroughARestart) {
  {
    Server server(root_, 0.1);
    // Its first run (stream 1) starts and ends; its second (stream 2) starts.
    auto started = ended("again", "v1");
    started.kind = proto::SessionEventKind::kStarted;
    started.frame = proto::VehicleFrame::kOwn;
    started.stream = 1;
    started.stamp_ns = 500'000'000;
    ASSERT_TRUE(server.map->ingest(started));
    fly(*server.map, "again", 3);
    auto end = ended("again", "v1");
    end.stream = 1;
    end.seq = 10;
    ASSERT_TRUE(server.map->ingest(end));
    EXPECT_TRUE(server.map->find("again")->status().ended);
    started.stream = 2;
    started.stamp_ns = 9'500'000'000;
    ASSERT_TRUE(server.map->ingest(started));
    EXPECT_FALSE(server.map->find("again")->status().ended);
    server.admin->checkpoint(true);
  }
  Server again(root_, 0.1);
  again.admin->recoverAll();
  ASSERT_NE(again.map->find("again"), nullptr);
  EXPECT_FALSE(again.map->find("again")->status().ended);
  const auto removed = again.admin->remove("again");
  ASSERT_FALSE(removed.ok());
  EXPECT_EQ(removed.error().code, ErrorCode::kConflict);  // it flies
}

// The time slider: a session as it was at a moment, fused from its journal; the loaded
// session is untouched.
TEST_F(StoreAdminTest, ReplayShowsTheSessionAsItWasThen) {
  Server server(root_, 0.1);
  fly(*server.map, "r", 6);
  const int64_t third_frame = wallFrame("r", 2).stamp_ns;
  auto then = server.admin->replay("r", third_frame);
  ASSERT_TRUE(then.ok()) << then.error().message;
  EXPECT_EQ((*then)->status().frames_fused, 3u);
  EXPECT_EQ((*then)->trajectory(0).size(), 3u);  // poses stamped up to then
  EXPECT_EQ(server.map->find("r")->status().frames_fused, 6u);

  // Exactly the map of those three frames alone.
  core::MapServer alone({.resolution = 0.1});
  fly(alone, "r", 3);
  EXPECT_EQ((*then)->occupiedVoxels(), alone.find("r")->occupiedVoxels());
  EXPECT_LT((*then)->occupiedVoxels().size(), server.map->find("r")->occupiedVoxels().size());

  EXPECT_EQ(server.admin->replay("nope", third_frame).error().code, ErrorCode::kNotFound);
  EXPECT_EQ(server.admin->replay("../r", third_frame).error().code, ErrorCode::kNotFound);
  EXPECT_EQ((*server.admin->replay("r", 0))->status().frames_fused, 0u);  // before the flight
}

TEST_F(StoreAdminTest, MergeJoinsTwoFlightsMovedByTheTransform) {
  Server server(root_, 0.1);
  fly(*server.map, "a", 4);
  fly(*server.map, "b", 4);  // the same vehicle and stamps: a second flight of v1
  ASSERT_TRUE(server.admin->close("b").ok());
  const auto a = server.map->find("a")->status();
  const auto b = server.admin->closedSessions().at(0);

  auto request = core::MergeRequest::pair("a", "b", "ab");
  request.sources[1].T_into_source.translation = {0, 5, 0};
  ASSERT_TRUE(server.admin->merge(request).ok());
  const auto merged = server.map->find("ab");
  ASSERT_NE(merged, nullptr);
  const auto status = merged->status();
  EXPECT_TRUE(status.read_only);
  EXPECT_EQ(status.frames_fused, 8u);
  EXPECT_EQ(status.poses, 8u);
  EXPECT_EQ(status.vehicles, (std::vector<std::string>{"v1", "v1-b"}));
  EXPECT_NEAR(status.bounds.max.y() - a.bounds.max.y(), 5.0, 0.11);
  const auto tum = core::trajectoryTum(*merged, "v1-b");
  EXPECT_NE(tum.find(" 5.000000 1.000000 "), std::string::npos) << tum;  // moved +5 m in y
  // The same map as fusing both flights directly, the second 5 m to the side.
  for (int i = 0; i < 4; ++i) ASSERT_TRUE(server.map->ingest(wallFrame("direct", i)));
  for (int i = 0; i < 4; ++i) ASSERT_TRUE(server.map->ingest(wallFrame("direct", i, 5.0, "w")));
  server.map->find("direct")->waitUntilIdle();
  EXPECT_EQ(merged->occupiedVoxels(), server.map->find("direct")->occupiedVoxels());
  EXPECT_GT(status.occupied_voxels, b.occupied_voxels);

  EXPECT_EQ(server.admin->merge(request).error().code, ErrorCode::kConflict);  // exists
  EXPECT_EQ(server.admin->merge(core::MergeRequest::pair("a", "zz", "c")).error().code,
            ErrorCode::kNotFound);
  EXPECT_EQ(server.admin->merge(core::MergeRequest::pair("a", "a", "c")).error().code,
            ErrorCode::kInvalidArgument);
  EXPECT_EQ(server.admin->merge(core::MergeRequest::pair("a", "b", "../x")).error().code,
            ErrorCode::kInvalidArgument);
}

// Listings (REST, every viewer's "sessions") are answered from memory, not by reading every
// closed session's session.json on the network thread: a file changed behind the server's
// back does not change them; close, merge and delete do.
TEST_F(StoreAdminTest, ClosedSessionsAreListedFromMemory) {
  Server server(root_, 0.1);
  fly(*server.map, "a", 3);
  fly(*server.map, "b", 2);
  ASSERT_TRUE(server.admin->close("a").ok());
  ASSERT_TRUE(server.admin->close("b").ok());
  fs::remove(root_ / "a" / "session.json");
  auto listed = server.admin->closedSessions();
  ASSERT_EQ(listed.size(), 2u);
  EXPECT_EQ(listed[0].id, "a");
  EXPECT_EQ(listed[0].frames_fused, 3u);
  EXPECT_TRUE(listed[0].closed);
  ASSERT_TRUE(server.admin->remove("b").ok());
  ASSERT_TRUE(server.admin->open("a").ok());  // loaded: listed with the loaded ones
  EXPECT_TRUE(server.admin->closedSessions().empty());
}

// The server's periodic checkpoint (every 5 s on its main thread, which also ends silent
// sessions) does not wait while a merge replays journals: it returns at once, and the round
// after the merge saves.
TEST_F(StoreAdminTest, ACheckpointDoesNotWaitBehindAMerge) {
  Server server(root_, 0.1);
  fly(*server.map, "a", 300);
  fly(*server.map, "b", 300);
  ASSERT_TRUE(server.admin->close("a").ok());
  ASSERT_TRUE(server.admin->close("b").ok());
  std::atomic<bool> merged{false};
  std::thread merge([&] {
    EXPECT_TRUE(server.admin->merge(core::MergeRequest::pair("a", "b", "ab")).ok());
    merged = true;
  });
  auto staging = [&] {
    for (const auto& entry : fs::directory_iterator(root_)) {
      if (entry.path().filename().string().rfind(".merge-", 0) == 0) return true;
    }
    return false;
  };
  while (!staging() && !merged) std::this_thread::yield();
  const bool under_way = !merged;  // (it takes seconds: the window to miss it is tiny)
  const auto start = std::chrono::steady_clock::now();
  server.admin->checkpoint(/*all=*/false);
  const auto waited = std::chrono::steady_clock::now() - start;
  merge.join();
  if (!under_way) GTEST_SKIP() << "the merge ended before the checkpoint could begin";
  EXPECT_LT(waited, std::chrono::milliseconds(100));
}

// A merged session is born closed. When it cannot be opened (here: the session limit), it
// must stay closed all the same: a vehicle naming it would otherwise start a live session
// appending to the merged journal.
TEST_F(StoreAdminTest, AMergedSessionThatCannotBeOpenedStaysClosed) {
  Server server(root_, 0.1, /*max_sessions=*/1);
  fly(*server.map, "a", 2);
  ASSERT_TRUE(server.admin->close("a").ok());
  fly(*server.map, "b", 2);
  const auto merged = server.admin->merge(core::MergeRequest::pair("a", "b", "ab"));
  ASSERT_FALSE(merged.ok());
  EXPECT_EQ(merged.error().code, ErrorCode::kUnavailable) << merged.error().message;
  ASSERT_TRUE(server.admin->close("b").ok());  // room for a session again
  EXPECT_FALSE(server.map->ingest(wallFrame("ab", 9)));
  EXPECT_EQ(server.map->find("ab"), nullptr);
  const auto journal = readJournal(root_ / "ab" / "journal.smj");
  ASSERT_TRUE(journal.ok());
  EXPECT_EQ(journal->records.size(), 8u);  // both flights' frames and poses, nothing more
}

// A vehicle's pose graph moves poses it sent: the map is fused again from the journal with
// them, later frames are fused corrected, and a restart recovers the corrected map: never
// from a snapshot older than the correction, from a newer one when there is one.
TEST_F(StoreAdminTest, APoseCorrectionFusesTheMapAgainAndSurvivesRestarts) {
  std::vector<fusion::VoxelIndex> right;
  {
    Server server(root_, 0.1);
    fly(*server.map, "truth", 14);
    right = server.map->find("truth")->occupiedVoxels();
  }
  std::vector<fusion::VoxelIndex> corrected;
  {
    Server server(root_, 0.1);
    fly(*server.map, "c", 6, /*y_offset=*/0.5);  // every frame 0.5 m off in y
    const auto session = server.map->find("c");
    const auto wrong = session->occupiedVoxels();
    ASSERT_TRUE(server.map->ingest(correction("c", 6, -0.5)));
    session->waitUntilIdle();
    const auto status = session->status();
    EXPECT_EQ(status.corrections, 1u);
    EXPECT_EQ(status.refusions, 1u);
    EXPECT_FALSE(status.refusing);
    corrected = session->occupiedVoxels();
    EXPECT_NE(corrected, wrong);
    EXPECT_EQ(session->trajectory(0).at(3).T_map_body.translation.y(), -0.5);
    // Six frames fused where they belong: a prefix of the truth's map, not the wrong one's.
    Server check(root_ / "check", 0.1);
    fly(*check.map, "t6", 6);
    EXPECT_EQ(corrected, check.map->find("t6")->occupiedVoxels());
  }
  {
    Server restarted(root_, 0.1);
    const auto recovered = restarted.admin->recoverAll();
    const auto c =
        std::find_if(recovered.begin(), recovered.end(), [](const auto& r) { return r.id == "c"; });
    ASSERT_NE(c, recovered.end());
    EXPECT_EQ(c->snapshot_frames, 0u);  // snapshot-4 holds the frames where they were
    EXPECT_EQ(restarted.map->find("c")->occupiedVoxels(), corrected);
    // More frames, sent with the old error: corrected as they come; snapshots again.
    fly(*restarted.map, "c", 8, /*y_offset=*/0.5, /*first=*/6);
    EXPECT_EQ(restarted.map->find("c")->occupiedVoxels(), right);
    EXPECT_GT(restarted.map->find("c")->status().snapshots, 0u);
  }
  Server again(root_, 0.1);
  const auto recovered = again.admin->recoverAll();
  const auto c =
      std::find_if(recovered.begin(), recovered.end(), [](const auto& r) { return r.id == "c"; });
  ASSERT_NE(c, recovered.end());
  EXPECT_GT(c->snapshot_frames, 0u);  // newer than the correction: used
  EXPECT_EQ(again.map->find("c")->occupiedVoxels(), right);
  EXPECT_EQ(again.map->find("c")->trajectory(0).back().T_map_body.translation.y(), -0.5);
}

}  // namespace
}  // namespace stereomap::store
