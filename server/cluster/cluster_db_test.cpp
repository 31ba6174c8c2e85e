#include "server/cluster/cluster_db.hpp"

#include <gtest/gtest.h>

#include <thread>

#include "server/cluster/cluster_fixture.hpp"

namespace stereomap::cluster {
namespace {

using ClusterDbTest = PostgresTest;
using namespace std::chrono_literals;

std::unique_ptr<ClusterDb> openServer(const std::string& url, const std::string& id,
                                      std::chrono::milliseconds lease = 4000ms) {
  auto db = ClusterDb::open({.url = url, .server_id = id, .http = "127.0.0.1:1", .lease = lease});
  EXPECT_TRUE(db) << (db ? "" : db.error().message);
  return db ? std::move(*db) : nullptr;
}

TEST_F(ClusterDbTest, ServersStartingTogetherCreateTheSchemaOnce) {
  std::vector<std::thread> threads;
  std::vector<std::unique_ptr<ClusterDb>> servers(4);
  for (int i = 0; i < 4; ++i) {
    threads.emplace_back([&, i] { servers[i] = openServer(url(), "s" + std::to_string(i)); });
  }
  for (auto& thread : threads) thread.join();
  for (const auto& server : servers) ASSERT_NE(server, nullptr);
  auto listed = servers[0]->servers();
  ASSERT_TRUE(listed) << listed.error().message;
  ASSERT_EQ(listed->size(), 4u);
  for (const auto& info : *listed) EXPECT_TRUE(info.live) << info.id;
}

TEST_F(ClusterDbTest, ABadServerIdOrSessionIdIsRefusedBeforeAnySql) {
  auto bad = ClusterDb::open({.url = url(), .server_id = "a'; DROP TABLE sm_sessions; --"});
  ASSERT_FALSE(bad);
  EXPECT_EQ(bad.error().code, common::ErrorCode::kInvalidArgument);
  auto server = openServer(url(), "a");
  auto placed = server->placeSession("x'); DELETE FROM sm_sessions; --", 0.1);
  ASSERT_FALSE(placed);
  EXPECT_EQ(placed.error().code, common::ErrorCode::kInvalidArgument);
}

TEST_F(ClusterDbTest, NewSessionsGoToTheLeastLoadedLiveServer) {
  auto a = openServer(url(), "a");
  auto b = openServer(url(), "b");
  std::map<std::string, int> per_owner;
  for (int i = 0; i < 6; ++i) {
    // Either server may place a session it hears of: the database decides the same way.
    auto placed = (i % 2 == 0 ? a : b)->placeSession("flight" + std::to_string(i), 0.1);
    ASSERT_TRUE(placed) << placed.error().message;
    EXPECT_EQ(placed->epoch, 1);
    ++per_owner[placed->owner];
  }
  EXPECT_EQ(per_owner["a"], 3);
  EXPECT_EQ(per_owner["b"], 3);
  // Placing a known session again names its owner, unchanged.
  auto again = b->placeSession("flight0", 0.2);
  ASSERT_TRUE(again);
  EXPECT_EQ(again->owner, "a");
  EXPECT_EQ(again->resolution, 0.1);
  auto owned = a->owned();
  ASSERT_TRUE(owned);
  EXPECT_EQ(owned->size(), 3u);
}

TEST_F(ClusterDbTest, AServerWhoseLeaseRanOutLosesItsSessionsToTheSurvivorsWithANewEpoch) {
  auto a = openServer(url(), "a", 600ms);
  auto b = openServer(url(), "b", 600ms);
  auto c = openServer(url(), "c", 600ms);
  for (int i = 0; i < 6; ++i) ASSERT_TRUE(a->placeSession("s" + std::to_string(i), 0.1));
  // Nothing is orphaned while every lease is fresh.
  auto none = b->takeOrphans();
  ASSERT_TRUE(none);
  EXPECT_TRUE(none->empty());
  // a stops renewing (killed); b and c go on.
  const auto deadline = std::chrono::steady_clock::now() + 1500ms;
  while (std::chrono::steady_clock::now() < deadline) {
    ASSERT_EQ(b->renewLease().value(), ClusterDb::Lease::kRenewed);
    ASSERT_EQ(c->renewLease().value(), ClusterDb::Lease::kRenewed);
    std::this_thread::sleep_for(100ms);
  }
  auto by_b = b->takeOrphans();
  ASSERT_TRUE(by_b) << by_b.error().message;
  auto by_c = c->takeOrphans();
  ASSERT_TRUE(by_c) << by_c.error().message;
  // a owned two of the six (placement spreads them): the survivors share those.
  const auto a_had = 2u;
  EXPECT_EQ(by_b->size() + by_c->size(), a_had);
  EXPECT_LE(by_b->size(), 1u);  // a fair share each
  for (const auto& taken : *by_b) {
    EXPECT_EQ(taken.owner, "b");
    EXPECT_EQ(taken.epoch, 2);
  }
  // a comes back: its lease had run out, which it is told, and it owns nothing.
  auto renewed = a->renewLease();
  ASSERT_TRUE(renewed) << renewed.error().message;
  EXPECT_EQ(*renewed, ClusterDb::Lease::kRenewedAfterExpiry);
  auto a_owns = a->owned();
  ASSERT_TRUE(a_owns);
  EXPECT_TRUE(a_owns->empty());
  renewed = a->renewLease();
  ASSERT_TRUE(renewed);
  EXPECT_EQ(*renewed, ClusterDb::Lease::kRenewed) << "renewed in time: renewals go on";
}

// The fault that lost acknowledged samples: a server paused, a new process started under the
// same id, the old one resumed. The new process supersedes the old: the old can neither renew,
// nor adopt, nor end the new one's lease, and each adoption raises the epoch, so the two never
// write at one epoch.
TEST_F(ClusterDbTest, AProcessStartedAgainUnderTheSameIdSupersedesTheOldOne) {
  auto old_process = openServer(url(), "a");
  auto placed = old_process->placeSession("s", 0.1);
  ASSERT_TRUE(placed);
  auto old_adopted = old_process->adopt(*placed);
  ASSERT_TRUE(old_adopted) << old_adopted.error().message;
  EXPECT_EQ(old_adopted->epoch, 2) << "placed at 1, adopted at 2";

  auto new_process = openServer(url(), "a");
  EXPECT_NE(new_process->incarnation(), old_process->incarnation());
  auto owned = new_process->owned();
  ASSERT_TRUE(owned);
  ASSERT_EQ(owned->size(), 1u) << "the server id's sessions";
  auto new_adopted = new_process->adopt((*owned)[0]);
  ASSERT_TRUE(new_adopted) << new_adopted.error().message;
  EXPECT_EQ(new_adopted->epoch, 3) << "a new incarnation, a new epoch";

  auto renewed = old_process->renewLease();
  ASSERT_TRUE(renewed) << renewed.error().message;
  EXPECT_EQ(*renewed, ClusterDb::Lease::kSuperseded);
  auto again = old_process->adopt(*new_adopted);
  ASSERT_FALSE(again) << "the old process cannot take the session back";
  EXPECT_EQ(again.error().code, common::ErrorCode::kConflict);
  EXPECT_TRUE(old_process->takeOrphans()->empty());
  ASSERT_TRUE(old_process->leave());
  renewed = new_process->renewLease();
  ASSERT_TRUE(renewed);
  EXPECT_EQ(*renewed, ClusterDb::Lease::kRenewed) << "the old one's leave() ended nothing";
  auto owner = new_process->ownerOf("s");
  ASSERT_TRUE(owner && owner->has_value());
  EXPECT_EQ((*owner)->epoch, 3);
}

// A database with the first clusters' schema (no version table) is upgraded once, keeping
// its rows; a start on an up-to-date schema takes no lock, so a busy journal (an open
// transaction holding locks as ingest does) does not hold it up.
TEST_F(ClusterDbTest, AnOldSchemaIsUpgradedOnceAndAnUpToDateOneIsNotLocked) {
  auto admin = PgConnection::connect(url());
  ASSERT_TRUE(admin) << admin.error().message;
  for (const char* statement : {
           "CREATE TABLE sm_servers (id text PRIMARY KEY, http text NOT NULL, "
           "lease_until timestamptz NOT NULL, joined_at timestamptz NOT NULL DEFAULT now())",
           "CREATE TABLE sm_sessions (id text PRIMARY KEY, owner text, epoch bigint NOT NULL, "
           "resolution double precision NOT NULL, state text NOT NULL, created_at timestamptz "
           "NOT NULL DEFAULT now(), owned_since timestamptz NOT NULL DEFAULT clock_timestamp())",
           "CREATE TABLE sm_journal (session text NOT NULL REFERENCES sm_sessions (id) ON DELETE "
           "CASCADE, number bigint NOT NULL, epoch bigint NOT NULL, kind smallint NOT NULL, "
           "record bytea NOT NULL, committed_at timestamptz NOT NULL DEFAULT clock_timestamp(), "
           "PRIMARY KEY (session, number))",
           "CREATE TABLE sm_snapshots (session text NOT NULL REFERENCES sm_sessions (id) ON "
           "DELETE CASCADE, number bigint NOT NULL, epoch bigint NOT NULL, map bytea NOT NULL, "
           "PRIMARY KEY (session, number))",
           "INSERT INTO sm_servers VALUES ('old', '127.0.0.1:1', now())",
           "INSERT INTO sm_sessions (id, owner, epoch, resolution, state) "
           "VALUES ('flown', NULL, 4, 0.2, 'live')",
           "INSERT INTO sm_journal (session, number, epoch, kind, record) "
           "VALUES ('flown', 1, 4, 2, '\\x00')",
       }) {
    ASSERT_TRUE((*admin)->exec(statement)) << statement;
  }
  auto upgraded = openServer(url(), "a");
  ASSERT_NE(upgraded, nullptr);
  auto version = (*admin)->exec("SELECT version FROM sm_schema");
  ASSERT_TRUE(version) << version.error().message;
  EXPECT_EQ(version->integer(0, 0), latestSchemaVersion());
  auto kept = (*admin)->exec(
      "SELECT (SELECT count(*) FROM sm_journal), (SELECT epoch FROM sm_sessions WHERE id = "
      "'flown'), (SELECT count(*) FROM sm_servers WHERE incarnation = '')");
  ASSERT_TRUE(kept);
  EXPECT_EQ(kept->integer(0, 0), 1);
  EXPECT_EQ(kept->integer(0, 1), 4);
  EXPECT_EQ(kept->integer(0, 2), 1) << "the old server's row, its incarnation empty";

  // Ingest under way: a transaction holding the journal's and the sessions' row locks.
  auto busy = PgConnection::connect(url());
  ASSERT_TRUE(busy);
  ASSERT_TRUE((*busy)->exec("BEGIN"));
  ASSERT_TRUE((*busy)->exec("LOCK TABLE sm_journal, sm_snapshots IN ROW EXCLUSIVE MODE"));
  ASSERT_TRUE((*busy)->exec("SELECT * FROM sm_sessions FOR SHARE"));
  const auto started = std::chrono::steady_clock::now();
  auto second = openServer(url(), "b");
  EXPECT_NE(second, nullptr) << "a start on an up-to-date schema waits for no lock";
  EXPECT_LT(std::chrono::steady_clock::now() - started, 1500ms);
  ASSERT_TRUE((*busy)->exec("ROLLBACK"));

  // A schema newer than this build is refused with what to do.
  ASSERT_TRUE((*admin)->exec("UPDATE sm_schema SET version = version + 1"));
  auto newer = ClusterDb::open({.url = url(), .server_id = "c"});
  ASSERT_FALSE(newer);
  EXPECT_NE(newer.error().message.find("newer"), std::string::npos) << newer.error().message;
}

// A control round reads one row: the version moves with every change of who owns what, never
// with a lease renewal, and "orphans" says when takeOrphans() has something to take.
TEST_F(ClusterDbTest, AControlRoundSeesChangesWithoutScanning) {
  auto a = openServer(url(), "a", 500ms);
  auto b = openServer(url(), "b", 500ms);
  auto first = b->poll();
  ASSERT_TRUE(first) << first.error().message;
  EXPECT_FALSE(first->orphans);
  ASSERT_EQ(b->renewLease().value(), ClusterDb::Lease::kRenewed);
  EXPECT_EQ(b->poll()->version, first->version) << "a renewal changes nothing";
  auto placed = a->placeSession("s", 0.1);
  ASSERT_TRUE(placed);
  const auto after_placement = b->poll()->version;
  EXPECT_GT(after_placement, first->version);
  ASSERT_TRUE(a->adopt(*placed));
  EXPECT_GT(b->poll()->version, after_placement) << "an adoption is a change";
  // a stops renewing: its session waits for an owner.
  const auto deadline = std::chrono::steady_clock::now() + 800ms;
  while (std::chrono::steady_clock::now() < deadline) {
    ASSERT_TRUE(b->renewLease());
    std::this_thread::sleep_for(100ms);
  }
  EXPECT_TRUE(b->poll()->orphans);
  ASSERT_EQ(b->takeOrphans()->size(), 1u);
  EXPECT_FALSE(b->poll()->orphans);
  EXPECT_GT(b->statements(), 5u);
}

// A server at its capacity is given no more: a session placed when every live server is full
// waits without an owner, and the next server with room takes it.
TEST_F(ClusterDbTest, AServerAtItsCapacityIsGivenNoMore) {
  auto a = ClusterDb::open({.url = url(), .server_id = "a", .http = "127.0.0.1:1", .capacity = 2});
  ASSERT_TRUE(a) << a.error().message;
  ASSERT_TRUE((*a)->placeSession("s0", 0.1));
  ASSERT_TRUE((*a)->placeSession("s1", 0.1));
  auto full = (*a)->placeSession("s2", 0.1);
  ASSERT_FALSE(full);
  EXPECT_EQ(full.error().code, common::ErrorCode::kUnavailable) << full.error().message;
  EXPECT_TRUE((*a)->poll()->orphans) << "it waits for an owner";
  EXPECT_TRUE((*a)->takeOrphans()->empty()) << "not past a's capacity";
  auto b = openServer(url(), "b");
  auto taken = b->takeOrphans();
  ASSERT_TRUE(taken);
  ASSERT_EQ(taken->size(), 1u);
  EXPECT_EQ((*taken)[0].session, "s2");
  EXPECT_EQ((*taken)[0].owner, "b");
}

TEST_F(ClusterDbTest, ReleasingNeedsTheCurrentEpoch) {
  auto a = openServer(url(), "a");
  auto placed = a->placeSession("s", 0.1);
  ASSERT_TRUE(placed);
  Ownership stale = *placed;
  stale.epoch = 0;
  EXPECT_FALSE(a->release(stale, ClusterDb::Leaving::kClosed));
  EXPECT_TRUE(a->release(*placed, ClusterDb::Leaving::kClosed));
  auto owner = a->ownerOf("s");
  ASSERT_TRUE(owner);
  EXPECT_FALSE(owner->has_value()) << "a closed session has no owner";
}

TEST_F(ClusterDbTest, ALeavingServersSessionsAreTakenAtOnce) {
  auto a = openServer(url(), "a");
  auto b = openServer(url(), "b");
  ASSERT_TRUE(a->placeSession("s0", 0.1));  // a: ties go to the lowest id
  ASSERT_TRUE(a->leave());
  auto taken = b->takeOrphans();
  ASSERT_TRUE(taken);
  ASSERT_EQ(taken->size(), 1u);
  EXPECT_EQ((*taken)[0].owner, "b");
}

}  // namespace
}  // namespace stereomap::cluster
