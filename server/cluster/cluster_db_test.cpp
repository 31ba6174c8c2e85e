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
    ASSERT_TRUE(b->renewLease());
    ASSERT_TRUE(c->renewLease());
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
  ASSERT_FALSE(renewed);
  EXPECT_EQ(renewed.error().code, common::ErrorCode::kConflict);
  auto a_owns = a->owned();
  ASSERT_TRUE(a_owns);
  EXPECT_TRUE(a_owns->empty());
  EXPECT_TRUE(a->renewLease()) << "registered again: renewals go on";
}

TEST_F(ClusterDbTest, ReleasingNeedsTheCurrentEpoch) {
  auto a = openServer(url(), "a");
  auto placed = a->placeSession("s", 0.1);
  ASSERT_TRUE(placed);
  Ownership stale = *placed;
  stale.epoch = 0;
  EXPECT_FALSE(a->release(stale, /*closed=*/true));
  EXPECT_TRUE(a->release(*placed, /*closed=*/true));
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
