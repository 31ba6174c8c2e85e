#include "server/cluster/pg.hpp"

#include <gtest/gtest.h>

#include <thread>

#include "server/cluster/cluster_fixture.hpp"

namespace stereomap::cluster {
namespace {

TEST(RedactPassword, HidesThePasswordInUrlsAndKeywords) {
  EXPECT_EQ(redactPassword("postgresql://sm:s3cr@t@db.example:5432/x"),
            "postgresql://sm:***@db.example:5432/x");
  EXPECT_EQ(redactPassword("postgres://sm@db/x"), "postgres://sm@db/x");
  EXPECT_EQ(redactPassword("host=db user=sm password=hunter2 dbname=x"),
            "host=db user=sm password=*** dbname=x");
}

TEST(PgConnection, AnAddressWhereNothingListensIsUnreachable) {
  const int port = testing::unusedPort();
  auto db = PgConnection::connect("postgresql://sm:pw@127.0.0.1:" + std::to_string(port) + "/x",
                                  {.connect_timeout = std::chrono::seconds(2)});
  ASSERT_FALSE(db);
  EXPECT_EQ(db.error().code, common::ErrorCode::kUnavailable);
  EXPECT_NE(db.error().message.find("cannot be reached"), std::string::npos) << db.error().message;
  EXPECT_EQ(db.error().message.find(":pw@"), std::string::npos) << "the password must not show";
}

using PgTest = PostgresTest;

TEST_F(PgTest, RefusedCredentialsAreSaidAsSuch) {
  auto db = PgConnection::connect(postgres().urlWithPassword("wrong", database_));
  ASSERT_FALSE(db);
  EXPECT_EQ(db.error().code, common::ErrorCode::kInvalidArgument);
  EXPECT_NE(db.error().message.find("refused the credentials"), std::string::npos)
      << db.error().message;
  EXPECT_EQ(db.error().message.find("wrong"), std::string::npos) << db.error().message;
}

TEST_F(PgTest, ValuesTravelAsParametersNeverAsSql) {
  auto db = PgConnection::connect(url());
  ASSERT_TRUE(db) << db.error().message;
  ASSERT_TRUE((*db)->exec("CREATE TABLE t (name text, data bytea, x double precision)"));
  const std::string hostile = "x'); DROP TABLE t; --";
  const std::string binary("\0\x01\xff\x00zz", 6);
  ASSERT_TRUE(
      (*db)->exec("INSERT INTO t VALUES ($1, $2, $3)", {hostile, PgParam::bytes(binary), 0.1}));
  auto rows = (*db)->exec("SELECT name, data, x FROM t WHERE name = $1", {hostile});
  ASSERT_TRUE(rows) << rows.error().message;
  ASSERT_EQ(rows->rows(), 1);
  EXPECT_EQ(rows->text(0, 0), hostile);
  EXPECT_EQ(rows->bytes(0, 1), binary);
  EXPECT_EQ(rows->real(0, 2), 0.1);  // exact: doubles travel with 17 digits
}

TEST_F(PgTest, ErrorsCarryTheirStateAndALostConnectionIsUnavailable) {
  auto db = PgConnection::connect(url());
  ASSERT_TRUE(db) << db.error().message;
  ASSERT_TRUE((*db)->exec("CREATE TABLE u (k int PRIMARY KEY)"));
  ASSERT_TRUE((*db)->exec("INSERT INTO u VALUES (1)"));
  auto duplicate = (*db)->exec("INSERT INTO u VALUES (1)");
  ASSERT_FALSE(duplicate);
  EXPECT_EQ(duplicate.error().code, common::ErrorCode::kConflict);
  EXPECT_EQ((*db)->lastState(), "23505");

  postgres().crash();
  auto lost = (*db)->exec("SELECT 1");
  ASSERT_FALSE(lost);
  EXPECT_EQ(lost.error().code, common::ErrorCode::kUnavailable) << lost.error().message;
  std::string why;
  ASSERT_TRUE(postgres().restart(&why)) << why;
  ASSERT_TRUE((*db)->reconnect()) << "the database is back";
  EXPECT_TRUE((*db)->exec("SELECT 1"));
}

// A statement past its deadline is abandoned within it, and its backend is ended before the
// next statement: a write it had under way can never commit after the caller was told it
// failed (without the ending, this INSERT commits two seconds later).
TEST_F(PgTest, AStatementPastItsDeadlineIsAbandonedAndCanCommitNothingLater) {
  using namespace std::chrono_literals;
  auto db = PgConnection::connect(url(), {.deadline = 300ms});
  ASSERT_TRUE(db) << db.error().message;
  ASSERT_TRUE((*db)->exec("CREATE TABLE late (k int)"));
  const auto started = std::chrono::steady_clock::now();
  auto slow = (*db)->exec("INSERT INTO late SELECT 1 FROM pg_sleep(2)");
  const auto waited = std::chrono::steady_clock::now() - started;
  ASSERT_FALSE(slow);
  EXPECT_EQ(slow.error().code, common::ErrorCode::kUnavailable);
  EXPECT_NE(slow.error().message.find("did not answer within 300 ms"), std::string::npos)
      << slow.error().message;
  EXPECT_LT(waited, 1s);
  EXPECT_EQ((*db)->lastState(), "") << "no SQLSTATE: the outcome is unknown to the database's "
                                       "client until the backend is ended";
  EXPECT_FALSE((*db)->connected());
  EXPECT_EQ((*db)->abandoned(), 1u);
  ASSERT_TRUE((*db)->reconnect());
  std::this_thread::sleep_for(2500ms);
  auto rows = (*db)->exec("SELECT count(*) FROM late");
  ASSERT_TRUE(rows) << rows.error().message;
  EXPECT_EQ(rows->integer(0, 0), 0) << "the abandoned INSERT committed after all";
}

// A database that hangs without closing its connections (every process stopped: TCP still
// accepts, SQL never answers) costs a statement its deadline and a connect its timeout, never
// more; when it resumes, the next reconnect works.
TEST_F(PgTest, AHungDatabaseCostsADeadlineNotAnEndlessWait) {
  using namespace std::chrono_literals;
  auto db = PgConnection::connect(url(), {.connect_timeout = 2s, .deadline = 800ms});
  ASSERT_TRUE(db) << db.error().message;
  ASSERT_TRUE((*db)->exec("SELECT 1"));
  postgres().pause();
  auto started = std::chrono::steady_clock::now();
  auto hung = (*db)->exec("SELECT 1");
  auto waited = std::chrono::steady_clock::now() - started;
  ASSERT_FALSE(hung);
  EXPECT_EQ(hung.error().code, common::ErrorCode::kUnavailable);
  EXPECT_LT(waited, 1500ms);
  started = std::chrono::steady_clock::now();
  EXPECT_FALSE((*db)->reconnect());
  waited = std::chrono::steady_clock::now() - started;
  EXPECT_LT(waited, 3500ms);
  postgres().resume();
  ASSERT_TRUE((*db)->reconnect());
  EXPECT_TRUE((*db)->exec("SELECT 1"));
}

}  // namespace
}  // namespace stereomap::cluster
