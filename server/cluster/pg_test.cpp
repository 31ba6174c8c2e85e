#include "server/cluster/pg.hpp"

#include <gtest/gtest.h>

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
                                  std::chrono::seconds(2));
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

}  // namespace
}  // namespace stereomap::cluster
