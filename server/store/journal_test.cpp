#include "server/store/journal.hpp"

#include <gtest/gtest.h>

#include <fstream>

namespace stereomap::store {
namespace {

namespace fs = std::filesystem;

class JournalTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string name = "stereomap-journal-";  // built step by step: g++ 12 warns otherwise
    name += std::to_string(::getpid());
    name += ::testing::UnitTest::GetInstance()->current_test_info()->name();
    dir_ = fs::temp_directory_path() / name;
    fs::create_directories(dir_);
    path_ = dir_ / "journal.smj";
  }
  void TearDown() override { fs::remove_all(dir_); }

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
    auto journal = Journal::open(path_);
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
  fs::path dir_, path_;
};

TEST_F(JournalTest, RecordsRoundTrip) {
  const auto sizes = writeFive();
  EXPECT_EQ(fs::file_size(path_), sizes.back());
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok()) << replay.error().message;
  EXPECT_TRUE(replay->problem.empty()) << replay->problem;
  ASSERT_EQ(replay->records.size(), 5u);
  const auto& f2 = std::get<proto::CloudFrameMsg>(replay->records[4]);
  EXPECT_EQ(f2.seq, 2u);
  EXPECT_EQ(f2.payload, frame(2).payload);
  EXPECT_EQ(f2.sensor_position, frame(2).sensor_position);
  const auto& p1 = std::get<proto::PoseMsg>(replay->records[3]);
  EXPECT_EQ(p1.position, pose(1).position);
  EXPECT_EQ(p1.covariance, pose(1).covariance);
  EXPECT_EQ(p1.tracking_state, proto::TrackingState::kOk);
}

TEST_F(JournalTest, SessionEventsRoundTrip) {
  auto journal = Journal::open(path_);
  ASSERT_TRUE(journal.ok());
  proto::SessionEventMsg event;
  event.vehicle_id = "uav";
  event.session_id = "s";
  event.stamp_ns = 77;
  event.kind = proto::SessionEventKind::kEnded;
  event.baseline = 0.12;
  ASSERT_TRUE((*journal)->append(event).ok());
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  ASSERT_EQ(replay->records.size(), 1u);
  const auto& back = std::get<proto::SessionEventMsg>(replay->records[0]);
  EXPECT_EQ(back.kind, proto::SessionEventKind::kEnded);
  EXPECT_EQ(back.stamp_ns, 77);
  EXPECT_DOUBLE_EQ(back.baseline, 0.12);
}

TEST_F(JournalTest, TornTailIsCutAndEverythingBeforeKept) {
  const auto sizes = writeFive();
  fs::resize_file(path_, sizes[3] + 20);  // mid-way through the fifth record
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  EXPECT_EQ(replay->records.size(), 4u);
  EXPECT_EQ(replay->good_bytes, sizes[3]);
  EXPECT_NE(replay->problem.find("torn record"), std::string::npos) << replay->problem;

  // Reopening cuts the tail; appending goes on from the intact prefix.
  auto journal = Journal::open(path_);
  ASSERT_TRUE(journal.ok()) << journal.error().message;
  EXPECT_EQ((*journal)->recovered().records.size(), 4u);
  ASSERT_TRUE((*journal)->append(frame(7)).ok());
  journal->reset();
  replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  EXPECT_TRUE(replay->problem.empty()) << replay->problem;
  ASSERT_EQ(replay->records.size(), 5u);
  EXPECT_EQ(std::get<proto::CloudFrameMsg>(replay->records[4]).seq, 7u);
}

TEST_F(JournalTest, FlippedByteStopsAtThatRecord) {
  const auto sizes = writeFive();
  {
    std::fstream file(path_, std::ios::in | std::ios::out | std::ios::binary);
    file.seekp(static_cast<std::streamoff>(sizes[1] + 30));  // inside the third record
    file.put('\x5A');
  }
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  EXPECT_EQ(replay->records.size(), 2u);
  EXPECT_NE(replay->problem.find("checksum mismatch"), std::string::npos) << replay->problem;
  EXPECT_NE(replay->problem.find("kept 2 records"), std::string::npos) << replay->problem;
}

TEST_F(JournalTest, ForeignFilesAreRefusedNotOverwritten) {
  std::ofstream(path_) << "this is somebody's notes, not a journal\n";
  auto journal = Journal::open(path_);
  ASSERT_FALSE(journal.ok());
  EXPECT_NE(journal.error().message.find("not a stereomap journal"), std::string::npos);
  EXPECT_GT(fs::file_size(path_), 10u);  // untouched
  EXPECT_FALSE(readJournal(dir_ / "missing.smj").ok());
}

}  // namespace
}  // namespace stereomap::store
