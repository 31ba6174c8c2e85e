#include "server/cluster/cluster_journal.hpp"

#include <gtest/gtest.h>

#include <atomic>
#include <set>
#include <thread>

#include "server/cluster/cluster_db.hpp"
#include "server/cluster/cluster_fixture.hpp"

namespace stereomap::cluster {
namespace {

class ClusterJournalTest : public PostgresTest {
 protected:
  void loseACommitsAnswer(ClusterJournal& journal);
};
using namespace std::chrono_literals;

struct Server {
  std::unique_ptr<ClusterDb> db;
  std::unique_ptr<ClusterJournal> journal;
};

Server openServer(const std::string& url, const std::string& id,
                  std::chrono::milliseconds lease = 4000ms) {
  Server server;
  auto db = ClusterDb::open({.url = url, .server_id = id, .http = "127.0.0.1:1", .lease = lease});
  EXPECT_TRUE(db) << (db ? "" : db.error().message);
  if (db) server.db = std::move(*db);
  auto journal = ClusterJournal::open(url);
  EXPECT_TRUE(journal) << (journal ? "" : journal.error().message);
  if (journal) server.journal = std::move(*journal);
  return server;
}

TEST_F(ClusterJournalTest, AppendsFromManyThreadsAreCommittedInGroupsNumberedWithoutGaps) {
  auto server = openServer(url(), "a");
  auto placed = server.db->placeSession("s", 0.1);
  ASSERT_TRUE(placed);
  server.journal->adopt("s", placed->epoch, 0);
  constexpr int kThreads = 8, kEach = 250;
  std::vector<std::thread> threads;
  std::mutex mutex;
  std::set<uint64_t> numbers;
  std::atomic<int> failures = 0;
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([&, t] {
      for (int i = 0; i < kEach; ++i) {
        auto n = server.journal->append(poseOf("s", "v" + std::to_string(t), i));
        if (!n) {
          ++failures;
          continue;
        }
        std::lock_guard lock(mutex);
        numbers.insert(*n);
      }
    });
  }
  for (auto& thread : threads) thread.join();
  EXPECT_EQ(failures, 0);
  ASSERT_EQ(numbers.size(), static_cast<size_t>(kThreads * kEach));
  EXPECT_EQ(*numbers.begin(), 1u);
  EXPECT_EQ(*numbers.rbegin(), static_cast<uint64_t>(kThreads * kEach)) << "no gaps";
  EXPECT_LT(server.journal->committedGroups(), static_cast<uint64_t>(kThreads * kEach))
      << "appends waiting together share a commit";
  EXPECT_EQ(server.journal->committedSamples(), static_cast<uint64_t>(kThreads * kEach));

  auto stored = server.journal->read("s");
  ASSERT_TRUE(stored) << stored.error().message;
  ASSERT_EQ(stored->records.size(), static_cast<size_t>(kThreads * kEach));
  EXPECT_EQ(stored->last_number, static_cast<uint64_t>(kThreads * kEach));
  for (size_t i = 0; i < stored->numbers.size(); ++i) EXPECT_EQ(stored->numbers[i], i + 1);
  const auto& first = std::get<proto::PoseMsg>(stored->records.front());
  EXPECT_EQ(first.stream, 7u);
  EXPECT_EQ(first.orientation[3], 1.0);
}

TEST_F(ClusterJournalTest, AStaleOwnerIsFencedByTheDatabaseAndTheNewOwnerContinues) {
  auto a = openServer(url(), "a", 500ms);
  auto b = openServer(url(), "b");
  auto placed = a.db->placeSession("s", 0.1);
  ASSERT_TRUE(placed);
  ASSERT_EQ(placed->owner, "a");
  a.journal->adopt("s", placed->epoch, 0);
  std::vector<std::string> fenced;
  a.journal->onFenced(
      [&](const std::string& session, const std::string&) { fenced.push_back(session); });
  for (uint64_t i = 0; i < 10; ++i) ASSERT_TRUE(a.journal->append(poseOf("s", "v", i)));

  // a is paused past its lease; b takes the session.
  std::this_thread::sleep_for(600ms);
  ASSERT_TRUE(b.db->renewLease());
  auto taken = b.db->takeOrphans();
  ASSERT_TRUE(taken);
  ASSERT_EQ(taken->size(), 1u);
  EXPECT_EQ((*taken)[0].epoch, 2);
  auto stored = b.journal->read("s");
  ASSERT_TRUE(stored);
  EXPECT_EQ(stored->last_number, 10u);
  b.journal->adopt("s", (*taken)[0].epoch, stored->last_number);

  // a wakes up and writes with its old epoch: refused, reported once, the session dropped.
  auto stale = a.journal->append(poseOf("s", "v", 10));
  ASSERT_FALSE(stale);
  EXPECT_EQ(stale.error().code, common::ErrorCode::kConflict);
  EXPECT_NE(stale.error().message.find("fenced"), std::string::npos) << stale.error().message;
  EXPECT_EQ(fenced, std::vector<std::string>{"s"});
  EXPECT_FALSE(a.journal->epochOf("s").has_value());
  EXPECT_FALSE(a.journal->saveSnapshot("s", 10, "map")) << "nor can it save a snapshot";

  auto next = b.journal->append(poseOf("s", "v", 10));
  ASSERT_TRUE(next) << next.error().message;
  EXPECT_EQ(*next, 11u);
  auto rows =
      postgres().sql("SELECT count(*), max(epoch) FROM sm_journal WHERE epoch = 1", database_);
  ASSERT_TRUE(rows);
  EXPECT_EQ(*rows, "10|1\n") << "nothing committed with the stale epoch after the takeover";
}

TEST_F(ClusterJournalTest, OneFencedSessionDoesNotHoldUpTheOthersInItsGroup) {
  auto a = openServer(url(), "a");
  ASSERT_TRUE(a.db->placeSession("kept", 0.1));
  ASSERT_TRUE(a.db->placeSession("lost", 0.1));
  a.journal->adopt("kept", 1, 0);
  a.journal->adopt("lost", 1, 0);
  // Another server raised "lost"'s epoch (as a takeover does).
  ASSERT_TRUE(
      postgres().sql("UPDATE sm_sessions SET epoch = 2, owner = 'b' WHERE id = 'lost'", database_));
  std::vector<std::thread> threads;
  std::atomic<int> kept_ok = 0, lost_ok = 0;
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&, t] {
      for (int i = 0; i < 50; ++i) {
        const bool lost = (t % 2) == 1;
        auto n = a.journal->append(poseOf(lost ? "lost" : "kept", "v" + std::to_string(t), i));
        if (n) ++(lost ? lost_ok : kept_ok);
      }
    });
  }
  for (auto& thread : threads) thread.join();
  EXPECT_EQ(kept_ok, 100);
  EXPECT_EQ(lost_ok, 0);
  auto stored = a.journal->read("kept");
  ASSERT_TRUE(stored);
  EXPECT_EQ(stored->last_number, 100u) << "numbers given back by failed groups leave no gap";
}

TEST_F(ClusterJournalTest, SnapshotsAndFramesAreReadBackForRecovery) {
  auto a = openServer(url(), "a");
  ASSERT_TRUE(a.db->placeSession("s", 0.1));
  a.journal->adopt("s", 1, 0);
  for (uint64_t i = 0; i < 6; ++i) {
    ASSERT_TRUE(a.journal->append(frameOf("s", i, 1000 + i)));
    ASSERT_TRUE(a.journal->append(poseOf("s", "v", i)));
  }
  ASSERT_TRUE(a.journal->saveSnapshot("s", 2, "first"));
  ASSERT_TRUE(a.journal->saveSnapshot("s", 4, "second"));
  ASSERT_TRUE(a.journal->saveSnapshot("s", 6, std::string("third\0map", 9)));
  auto stored = a.journal->read("s");
  ASSERT_TRUE(stored) << stored.error().message;
  EXPECT_EQ(stored->snapshot_number, 6u);
  EXPECT_EQ(stored->snapshot, std::string("third\0map", 9));
  ASSERT_EQ(stored->records.size(), 12u);
  // Frames 1, 3, 5 (numbers) are covered by the snapshot: no payload; 7, 9, 11 whole.
  for (size_t i = 0; i < stored->records.size(); ++i) {
    if (const auto* frame = std::get_if<proto::CloudFrameMsg>(&stored->records[i])) {
      EXPECT_EQ(frame->payload.empty(), stored->numbers[i] <= 6) << stored->numbers[i];
    }
  }
  std::vector<uint64_t> visited;
  ASSERT_TRUE(
      a.journal->forEachFrame("s", 2, 9, [&](const proto::CloudFrameMsg& frame, uint64_t n) {
        EXPECT_EQ(frame.payload.size(), 1000 + frame.seq);
        visited.push_back(n);
      }));
  EXPECT_EQ(visited, (std::vector<uint64_t>{3, 5, 7, 9}));
  auto count = postgres().sql(
      "SELECT string_agg(number::text, ',' ORDER BY number) FROM "
      "sm_snapshots",
      database_);
  ASSERT_TRUE(count);
  EXPECT_EQ(*count, "4,6\n") << "the newest two are kept, the older removed";
  // Every cloud's row has its record without the payload, which recovery reads below the
  // snapshot: a few dozen bytes for a cloud of a kilobyte.
  auto meta = postgres().sql(
      "SELECT count(*), max(octet_length(meta)) < 200, min(octet_length(record)) >= 1000 FROM "
      "sm_journal WHERE kind = 1",
      database_);
  ASSERT_TRUE(meta);
  EXPECT_EQ(*meta, "6|t|t\n");

  // The newest snapshot damaged: recovery starts from the one before, and the frames after
  // that one come whole.
  ASSERT_TRUE(postgres().sql("UPDATE sm_snapshots SET map = '\\x28b52ffd0000' WHERE number = 6",
                             database_));
  stored = a.journal->read("s");
  ASSERT_TRUE(stored) << stored.error().message;
  EXPECT_EQ(stored->snapshot_number, 4u);
  EXPECT_EQ(stored->snapshot, "second");
  for (size_t i = 0; i < stored->records.size(); ++i) {
    if (const auto* frame = std::get_if<proto::CloudFrameMsg>(&stored->records[i])) {
      EXPECT_EQ(frame->payload.empty(), stored->numbers[i] <= 4) << stored->numbers[i];
    }
  }
}

// Records are read in pages bounded in bytes (8 MB): clouds of 3 MB come two or three a page,
// all of them, in order.
TEST_F(ClusterJournalTest, LargeRecordsAreReadInPagesBoundedInBytes) {
  auto a = openServer(url(), "a");
  ASSERT_TRUE(a.db->placeSession("s", 0.1));
  a.journal->adopt("s", 1, 0);
  for (uint64_t i = 0; i < 7; ++i) {
    ASSERT_TRUE(a.journal->append(frameOf("s", i, 3'000'000 + i)));
    ASSERT_TRUE(a.journal->append(poseOf("s", "v", i)));
  }
  std::vector<uint64_t> numbers;
  auto scan =
      a.journal->forEachRecord("s", [&](proto::journal::JournalRecord&& record, uint64_t number) {
        numbers.push_back(number);
        if (const auto* frame = std::get_if<proto::CloudFrameMsg>(&record)) {
          EXPECT_EQ(frame->payload.size(), 3'000'000 + frame->seq);
        }
      });
  ASSERT_TRUE(scan) << scan.error().message;
  ASSERT_EQ(numbers.size(), 14u);
  for (size_t i = 0; i < numbers.size(); ++i) EXPECT_EQ(numbers[i], i + 1);
  EXPECT_EQ(scan->last_number, 14u);
}

TEST_F(ClusterJournalTest, AppendsFailWhileTheDatabaseIsDownAndResumeAfter) {
  auto a = openServer(url(), "a");
  ASSERT_TRUE(a.db->placeSession("s", 0.1));
  a.journal->adopt("s", 1, 0);
  ASSERT_TRUE(a.journal->append(poseOf("s", "v", 0)));
  postgres().crash();
  auto refused = a.journal->append(poseOf("s", "v", 1));
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error().code, common::ErrorCode::kUnavailable) << refused.error().message;
  std::string why;
  ASSERT_TRUE(postgres().restart(&why)) << why;
  auto resumed = a.journal->append(poseOf("s", "v", 1));
  ASSERT_TRUE(resumed) << resumed.error().message;
  EXPECT_EQ(*resumed, 2u) << "the failed append's number was given back";
}

// Session "s" (adopted at epoch 1) gets seq 0 journaled as number 1; then the database dies
// under the append of seq 1, and when it is back that row stands at number 2 as if the append
// had committed and only its answer had been lost.
void ClusterJournalTest::loseACommitsAnswer(ClusterJournal& journal) {
  ASSERT_TRUE(journal.append(poseOf("s", "v", 0)));
  postgres().crash();
  ASSERT_FALSE(journal.append(poseOf("s", "v", 1)));
  std::string why;
  ASSERT_TRUE(postgres().restart(&why)) << why;
  auto outside = PgConnection::connect(url());
  ASSERT_TRUE(outside) << outside.error().message;
  const auto record = proto::journal::encodeRecord(poseOf("s", "v", 1));
  ASSERT_TRUE((*outside)->exec(
      "INSERT INTO sm_journal (session, number, epoch, kind, record) VALUES ('s', 2, 1, 2, $1)",
      {PgParam::bytes(
          std::string_view(reinterpret_cast<const char*>(record.data()), record.size()))}));
}

// A commit whose answer is lost (the connection broke after PostgreSQL committed the INSERT):
// the server cannot tell it from a failure, and the vehicle was not acknowledged. Made here by
// writing that row from outside while the database is back, at the number given back. The
// next append deletes it and writes in its place: numbers go on without a gap, and the
// journal holds exactly what was acknowledged (before the fix: 23505 on every append after).
TEST_F(ClusterJournalTest, ACommitWhoseAnswerWasLostIsUndoneBeforeTheNextWrite) {
  auto a = openServer(url(), "a");
  ASSERT_TRUE(a.db->placeSession("s", 0.1));
  a.journal->adopt("s", 1, 0);
  ASSERT_NO_FATAL_FAILURE(loseACommitsAnswer(*a.journal));
  for (uint64_t seq = 2; seq < 5; ++seq) {
    auto appended = a.journal->append(poseOf("s", "v", seq));
    ASSERT_TRUE(appended) << appended.error().message;
    EXPECT_EQ(*appended, seq);
  }
  auto stored = a.journal->read("s");
  ASSERT_TRUE(stored) << stored.error().message;
  EXPECT_EQ(stored->numbers, (std::vector<uint64_t>{1, 2, 3, 4}));
  std::vector<uint64_t> seqs;
  for (const auto& r : stored->records) seqs.push_back(std::get<proto::PoseMsg>(r).seq);
  EXPECT_EQ(seqs, (std::vector<uint64_t>{0, 2, 3, 4})) << "the unacknowledged seq 1 is gone";
}

// The same doubt, but another server took the session meanwhile and read that row as its own:
// the stale owner's next write is fenced, and its DELETE is rolled back with it.
TEST_F(ClusterJournalTest, ADoubtIsNotUndoneOnceAnotherServerOwnsTheSession) {
  auto a = openServer(url(), "a", 500ms);
  auto placed = a.db->placeSession("s", 0.1);
  ASSERT_TRUE(placed);
  a.journal->adopt("s", placed->epoch, 0);
  ASSERT_NO_FATAL_FAILURE(loseACommitsAnswer(*a.journal));
  // b joins once the database is back, and a's lease has run out meanwhile.
  auto b = openServer(url(), "b");
  std::this_thread::sleep_for(600ms);
  auto taken = b.db->takeOrphans();
  ASSERT_TRUE(taken);
  ASSERT_EQ(taken->size(), 1u);
  auto stored = b.journal->read("s");
  ASSERT_TRUE(stored) << stored.error().message;
  EXPECT_EQ(stored->last_number, 2u);
  b.journal->adopt("s", (*taken)[0].epoch, stored->last_number);

  auto stale = a.journal->append(poseOf("s", "v", 2));
  ASSERT_FALSE(stale);
  EXPECT_NE(stale.error().message.find("fenced"), std::string::npos) << stale.error().message;
  auto rows = postgres().sql("SELECT count(*) FROM sm_journal WHERE session = 's'", database_);
  ASSERT_TRUE(rows);
  EXPECT_EQ(*rows, "2\n") << "the new owner's rows are all there";
  auto next = b.journal->append(poseOf("s", "v", 2));
  ASSERT_TRUE(next) << next.error().message;
  EXPECT_EQ(*next, 3u);
}

TEST_F(ClusterJournalTest, AnUnownedSessionIsRefusedAtOnce) {
  auto a = openServer(url(), "a");
  auto refused = a.journal->append(poseOf("nobody's", "v", 0));
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error().code, common::ErrorCode::kConflict);
}

}  // namespace
}  // namespace stereomap::cluster
