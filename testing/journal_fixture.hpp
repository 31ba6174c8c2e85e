// Tests only: a temporary folder per test with a journal path in it, and the frames and poses
// the journal's and the store's tests write (proto/journal, server/store).
#pragma once

#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <string>
#include <vector>

#include "proto/journal/journal.hpp"

namespace stereomap::testing {

class JournalTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string name = "stereomap-journal-";  // built step by step: g++ 12 warns otherwise
    name += std::to_string(::getpid());
    name += ::testing::UnitTest::GetInstance()->current_test_info()->name();
    dir_ = std::filesystem::temp_directory_path() / name;
    std::filesystem::create_directories(dir_);
    path_ = dir_ / "journal.smj";
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }

  static proto::CloudFrameMsg frame(uint64_t seq) {
    proto::CloudFrameMsg f;
    f.vehicle_id = "uav";
    f.session_id = "s";
    f.seq = seq;
    f.stamp_ns = 1000 + static_cast<int64_t>(seq);
    f.sensor_position = {1.0 * seq, 2, 3};
    f.max_range = 6;
    f.point_count = 3;
    f.payload.assign(100 + seq, static_cast<uint8_t>(seq));
    return f;
  }
  static proto::PoseMsg pose(uint64_t seq) {
    proto::PoseMsg p;
    p.vehicle_id = "uav";
    p.session_id = "s";
    p.seq = seq;
    p.position = {0.5 * seq, 0, 1};
    p.covariance[7] = 0.25;
    p.tracking_state = proto::TrackingState::kOk;
    return p;
  }
  // Writes frame(0), pose(0), frame(1), pose(1), frame(2); returns the file size after each.
  std::vector<uint64_t> writeFive() {
    auto journal = proto::journal::Journal::open(path_);
    EXPECT_TRUE(journal.ok());
    std::vector<uint64_t> sizes;
    for (uint64_t i = 0; i < 3; ++i) {
      EXPECT_TRUE((*journal)->append(frame(i)).ok());
      sizes.push_back((*journal)->bytes());
      if (i < 2) {
        EXPECT_TRUE((*journal)->append(pose(i)).ok());
        sizes.push_back((*journal)->bytes());
      }
    }
    return sizes;
  }
  std::filesystem::path dir_, path_;
};

}  // namespace stereomap::testing
