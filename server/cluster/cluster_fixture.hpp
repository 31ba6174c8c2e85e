// One throwaway PostgreSQL per test suite (CTest runs each test case in its own process),
// and a fresh database for each test. Tests fail (saying why) when PostgreSQL is not installed:
// scripts/install-deps installs it, so its absence is a broken setup, never a silent pass.
#pragma once

#include <gtest/gtest.h>

#include <cctype>
#include <memory>
#include <string>

#include "proto/messages.hpp"
#include "tests/support/postgres.hpp"

namespace stereomap::cluster {

class PostgresTest : public ::testing::Test {
 public:
  static void SetUpTestSuite() {
    if (!db_ && why_.empty()) db_ = testing::TestPostgres::start(&why_).release();
  }
  static void TearDownTestSuite() {
    delete db_;  // stops it and removes its directory
    db_ = nullptr;
    why_.clear();
  }

 protected:
  void SetUp() override {
    if (db_ == nullptr) GTEST_FAIL() << why_;
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    database_ = "t" + std::to_string(++count_) + "_" + info->name();
    for (char& c : database_)
      c = std::isalnum(static_cast<unsigned char>(c)) ? std::tolower(c) : '_';
    database_ = database_.substr(0, 60);
    std::string why;
    ASSERT_TRUE(db_->createDatabase(database_, &why)) << why;
  }
  std::string url() const { return db_->url(database_); }
  testing::TestPostgres& postgres() { return *db_; }
  std::string database_;

 private:
  static inline testing::TestPostgres* db_ = nullptr;  // one per suite (CTest: per process)
  static inline std::string why_;
  static inline int count_ = 0;
};

// A vehicle's pose number `seq` (stream 7), stamped `seq` seconds in, at x = seq metres.
inline proto::PoseMsg poseOf(const std::string& session, const std::string& vehicle, uint64_t seq) {
  proto::PoseMsg pose;
  pose.session_id = session;
  pose.vehicle_id = vehicle;
  pose.stream = 7;
  pose.seq = seq;
  pose.stamp_ns = static_cast<int64_t>(seq) * 1000000000;
  pose.position = {1.0 * static_cast<double>(seq), 0, 0};
  pose.orientation = {0, 0, 0, 1};
  return pose;
}

// Vehicle "v"'s cloud number `seq`, stamped `seq` seconds in, with `payload_bytes` of payload
// (not a cloud that decodes: the database only keeps it).
inline proto::CloudFrameMsg frameOf(const std::string& session, uint64_t seq,
                                    size_t payload_bytes) {
  proto::CloudFrameMsg frame;
  frame.session_id = session;
  frame.vehicle_id = "v";
  frame.seq = seq;
  frame.stamp_ns = static_cast<int64_t>(seq) * 1000000000;
  frame.point_count = 1;
  frame.payload.assign(payload_bytes, static_cast<uint8_t>(seq));
  return frame;
}

}  // namespace stereomap::cluster
