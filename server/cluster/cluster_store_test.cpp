#include "server/cluster/cluster_store.hpp"

#include <gtest/gtest.h>

#include <limits>

#include "server/cluster/cluster_fixture.hpp"
#include "server/core/session_json.hpp"

namespace stereomap::cluster {
namespace {

using namespace std::chrono_literals;
using ClusterStoreTest = PostgresTest;

struct Cluster {
  std::unique_ptr<ClusterDb> db;
  std::unique_ptr<ClusterJournal> journal;
  std::unique_ptr<ClusterStore> store;
};

Cluster openCluster(const std::string& url) {
  Cluster c;
  auto db = ClusterDb::open({.url = url, .server_id = "a", .http = "127.0.0.1:1", .lease = 4000ms});
  EXPECT_TRUE(db) << (db ? "" : db.error().message);
  if (db) c.db = std::move(*db);
  auto journal = ClusterJournal::open(url);
  EXPECT_TRUE(journal) << (journal ? "" : journal.error().message);
  if (!journal) return c;
  c.journal = std::move(*journal);
  auto store = ClusterStore::open(url, *c.journal);
  EXPECT_TRUE(store) << (store ? "" : store.error().message);
  if (store) c.store = std::move(*store);
  return c;
}

// Session `session` placed on this server, adopted and written by its journal.
Ownership serving(Cluster& c, const std::string& session) {
  auto placed = c.db->placeSession(session, 0.1);
  EXPECT_TRUE(placed) << (placed ? "" : placed.error().message);
  auto adopted = c.db->adopt(*placed);
  EXPECT_TRUE(adopted);
  c.journal->adopt(session, adopted->epoch, 0);
  return *adopted;
}

// A session flown by `vehicle`: `poses` poses (x = 1, 2, ... m, one a second), then ended and
// out of memory with a summary.
Ownership fly(Cluster& c, const std::string& session, const std::string& vehicle, int poses) {
  const auto adopted = serving(c, session);
  for (int i = 1; i <= poses; ++i) {
    EXPECT_TRUE(c.journal->append(poseOf(session, vehicle, static_cast<uint64_t>(i))));
  }
  c.journal->drop(session);
  core::SessionStatus status;
  status.id = session;
  status.poses = static_cast<size_t>(poses);
  EXPECT_TRUE(c.db->release(adopted, ClusterDb::Leaving::kEnded, core::sessionJson(status)));
  return adopted;
}

std::vector<proto::PoseMsg> posesOf(Cluster& c, const std::string& session) {
  std::vector<proto::PoseMsg> out;
  EXPECT_TRUE(
      c.journal->forEachRecord(session, [&](proto::journal::JournalRecord&& record, uint64_t) {
        if (auto* pose = std::get_if<proto::PoseMsg>(&record)) out.push_back(*pose);
      }));
  return out;
}

TEST_F(ClusterStoreTest, AnEndedSessionIsListedOutOfMemoryAndServedAgainAtAHigherEpoch) {
  auto c = openCluster(url());
  const auto flown = fly(c, "s", "v", 3);
  auto owner = c.db->ownerOf("s");
  ASSERT_TRUE(owner);
  EXPECT_FALSE(owner->has_value()) << "an ended session has no owner";
  EXPECT_FALSE(c.db->poll()->orphans) << "an ended session waits for no server";
  auto left = c.db->outOfMemory();
  ASSERT_TRUE(left);
  ASSERT_EQ(left->size(), 1u);
  const auto status = (*left)[0].status();
  EXPECT_EQ(status.poses, 3u) << "its summary is kept for listings";
  EXPECT_TRUE(status.ended);
  EXPECT_FALSE(status.closed);

  // Its vehicle announces it again: served again, every earlier write fenced.
  auto revived = c.db->placeSession("s", 0.1);
  ASSERT_TRUE(revived) << revived.error().message;
  EXPECT_EQ(revived->owner, "a");
  EXPECT_GT(revived->epoch, flown.epoch);
  EXPECT_TRUE(c.db->outOfMemory()->empty());
  auto row = c.store->session("s");
  ASSERT_TRUE(row);
  EXPECT_EQ(row->state, "live");

  // Closed by an operator: never revived by a vehicle, and closed once.
  ASSERT_TRUE(c.store->close("s"));
  auto refused = c.db->placeSession("s", 0.1);
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error().code, common::ErrorCode::kConflict);
  auto again = c.store->close("s");
  ASSERT_FALSE(again);
  EXPECT_EQ(again.error().code, common::ErrorCode::kConflict);
  EXPECT_EQ(c.store->close("nothing").error().code, common::ErrorCode::kNotFound);
  EXPECT_EQ(c.store->close("../x").error().code, common::ErrorCode::kInvalidArgument);
}

TEST_F(ClusterStoreTest, AClosedOwnersWritesAreFenced) {
  auto c = openCluster(url());
  serving(c, "s");
  ASSERT_TRUE(c.journal->append(poseOf("s", "v", 1)));
  ASSERT_TRUE(c.store->close("s"));  // from another server, or the tool
  auto late = c.journal->append(poseOf("s", "v", 2));
  ASSERT_FALSE(late) << "the owner's writes after the close are refused";
  EXPECT_EQ(posesOf(c, "s").size(), 1u);
  EXPECT_TRUE(c.db->owned()->empty());
}

// A site: three sessions in one transaction, each moved by its own transform, and what made it
// (its origin) kept for its listings and for the server that loads it.
TEST_F(ClusterStoreTest, ASiteMergesSessionsEachByItsTransformAndKeepsItsOrigin) {
  auto c = openCluster(url());
  fly(c, "mon", "v", 2);
  fly(c, "tue", "v", 2);
  fly(c, "wed", "v", 2);
  core::MergeRequest request;
  request.sources = {{"mon", common::Rigid3::identity()},
                     {"tue", {common::Quat::Identity(), common::Vec3(0, 10, 0)}},
                     {"wed", {common::Quat::Identity(), common::Vec3(0, 20, 0)}}};
  request.into = "site";
  request.origin = R"({"site":{"sessions":[{"session":"mon"}],"left_out":[]}})";
  ASSERT_TRUE(c.store->merge(request));
  const auto merged = posesOf(c, "site");
  ASSERT_EQ(merged.size(), 6u);
  const std::vector<std::string> vehicles = {"v", "v-tue", "v-wed"};
  for (size_t i = 0; i < merged.size(); ++i) {
    EXPECT_EQ(merged[i].vehicle_id, vehicles[i / 2]);
    EXPECT_DOUBLE_EQ(merged[i].position[1], 10.0 * static_cast<double>(i / 2));
  }
  auto row = c.store->session("site");
  ASSERT_TRUE(row);
  EXPECT_EQ(row->status().origin, nlohmann::json::parse(request.origin).dump());
  core::MapServer server(core::MapServerOptions{});
  auto loaded = c.store->load("site", server);
  ASSERT_TRUE(loaded) << loaded.error().message;
  EXPECT_EQ((*loaded)->status().origin, row->status().origin);

  request.sources.push_back({"mon", common::Rigid3::identity()});
  request.into = "twice";
  EXPECT_EQ(c.store->merge(request).error().code, common::ErrorCode::kInvalidArgument);
  EXPECT_FALSE(c.store->session("twice"));
}

TEST_F(ClusterStoreTest, OperatorsOpenMergeReplayAndDeleteStoredSessions) {
  auto c = openCluster(url());
  fly(c, "first", "v", 4);
  fly(c, "second", "v", 3);

  auto request = core::MergeRequest::pair("first", "second", "both");
  request.sources[1].T_into_source.translation = common::Vec3(0, 10, 0);
  auto done = c.store->merge(request);
  ASSERT_TRUE(done) << done.error().message;
  const auto merged = posesOf(c, "both");
  ASSERT_EQ(merged.size(), 7u);
  for (size_t i = 0; i < merged.size(); ++i) {
    EXPECT_EQ(merged[i].session_id, "both");
    EXPECT_EQ(merged[i].vehicle_id, i < 4 ? "v" : "v-second") << "a clashing vehicle renamed";
    EXPECT_DOUBLE_EQ(merged[i].position[1], i < 4 ? 0.0 : 10.0) << "the second moved";
  }
  auto row = c.store->session("both");
  ASSERT_TRUE(row);
  EXPECT_EQ(row->state, "closed");
  auto clash = c.store->merge(request);
  ASSERT_FALSE(clash);
  EXPECT_EQ(clash.error().code, common::ErrorCode::kConflict);
  EXPECT_EQ(posesOf(c, "both").size(), 7u) << "a refused merge leaves nothing";
  EXPECT_EQ(c.store->merge(core::MergeRequest::pair("first", "missing", "x")).error().code,
            common::ErrorCode::kNotFound);
  EXPECT_FALSE(c.store->session("x")) << "a failed merge leaves no session";

  // The time slider: the merged session as it was 2.5 s into the first flight's stamps.
  auto replayed = c.store->replay("both", 2'500'000'000);
  ASSERT_TRUE(replayed) << replayed.error().message;
  EXPECT_EQ((*replayed)->poseCount(), 4u) << "poses 1 and 2 of each flight";
  auto whole = c.store->replay("both", std::numeric_limits<int64_t>::max());
  ASSERT_TRUE(whole);
  EXPECT_EQ((*whole)->poseCount(), 7u);

  // Opened read-only by a server: owned (routed there), never revived or deleted as live.
  auto opened = c.store->open("both", "a");
  ASSERT_TRUE(opened) << opened.error().message;
  EXPECT_TRUE(opened->read_only);
  auto owned = c.db->owned();
  ASSERT_TRUE(owned);
  ASSERT_EQ(owned->size(), 1u);
  EXPECT_TRUE((*owned)[0].read_only);
  EXPECT_EQ(c.store->open("both", "a").error().code, common::ErrorCode::kConflict);

  // Deleting: never a live session; anything else with its journal.
  ASSERT_TRUE(c.db->placeSession("first", 0.1));  // flown again: live
  auto live = c.store->remove("first");
  ASSERT_FALSE(live);
  EXPECT_EQ(live.error().code, common::ErrorCode::kConflict);
  ASSERT_TRUE(c.store->remove("both"));
  EXPECT_EQ(c.store->session("both").error().code, common::ErrorCode::kNotFound);
  EXPECT_TRUE(posesOf(c, "both").empty());
  EXPECT_EQ(c.store->remove("both").error().code, common::ErrorCode::kNotFound);

  auto checked = c.store->check();
  ASSERT_TRUE(checked);
  EXPECT_EQ(checked->sessions, 2u);
  EXPECT_EQ(checked->records, 7u);
  EXPECT_TRUE(checked->problems.empty());
}

TEST_F(ClusterStoreTest, AClosedSessionIsCompactedBelowItsSnapshotWithItsTrajectoryKept) {
  auto c = openCluster(url());
  serving(c, "s");
  uint64_t snapshot_at = 0;
  for (uint64_t i = 1; i <= 10; ++i) {
    ASSERT_TRUE(c.journal->append(poseOf("s", "v", i)));
    auto n = c.journal->append(frameOf("s", i, 20000));
    ASSERT_TRUE(n);
    if (i == 6) snapshot_at = *n;
  }
  ASSERT_TRUE(c.journal->saveSnapshot("s", snapshot_at / 2, "an older map"));
  ASSERT_TRUE(c.journal->saveSnapshot("s", snapshot_at, "the map up to cloud 6"));

  auto live = c.store->compact("s");
  ASSERT_FALSE(live);
  EXPECT_EQ(live.error().code, common::ErrorCode::kConflict) << "a live session is not";
  c.journal->drop("s");
  ASSERT_TRUE(c.store->close("s"));
  auto done = c.store->compact("s");
  ASSERT_TRUE(done) << done.error().message;
  EXPECT_EQ(done->up_to, snapshot_at);
  EXPECT_EQ(done->clouds, 6u);
  EXPECT_LT(done->bytes_after, done->bytes_before - 6 * 20000 + 1000);
  EXPECT_EQ(c.store->compact("s")->clouds, 0u) << "once";

  // Every pose kept; the clouds the snapshot holds without their points, the later ones whole.
  EXPECT_EQ(posesOf(c, "s").size(), 10u);
  size_t whole = 0, bare = 0;
  ASSERT_TRUE(
      c.journal->forEachRecord("s", [&](proto::journal::JournalRecord&& record, uint64_t number) {
        if (const auto* frame = std::get_if<proto::CloudFrameMsg>(&record)) {
          (frame->payload.empty() ? bare : whole) += 1;
          EXPECT_EQ(frame->payload.empty(), number <= snapshot_at) << number;
        }
      }));
  EXPECT_EQ(bare, 6u);
  EXPECT_EQ(whole, 4u);
  EXPECT_EQ(postgres().sql("SELECT count(*) FROM sm_snapshots", database_).value_or(""), "1\n")
      << "only the snapshot that holds the compacted clouds is kept";

  // What needs the points says so.
  auto before = c.store->replay("s", 3'000'000'000);
  ASSERT_FALSE(before);
  EXPECT_EQ(before.error().code, common::ErrorCode::kConflict) << before.error().message;
  fly(c, "other", "w", 2);
  auto merged = c.store->merge(core::MergeRequest::pair("other", "s", "both"));
  ASSERT_FALSE(merged);
  EXPECT_EQ(merged.error().code, common::ErrorCode::kInvalidArgument);
  EXPECT_NE(merged.error().message.find("compacted"), std::string::npos);
}

}  // namespace
}  // namespace stereomap::cluster
