#include "onboard/link/spool.hpp"

#include <gtest/gtest.h>

#include <sys/resource.h>
#include <unistd.h>

#include <csignal>
#include <filesystem>
#include <fstream>

namespace stereomap::link {
namespace {

namespace fs = std::filesystem;
constexpr uint64_t kStream = 42;

proto::PoseMsg pose(uint64_t seq) {
  proto::PoseMsg p;
  p.vehicle_id = "uav";
  p.session_id = "s";
  p.stream = kStream;
  p.seq = seq;
  p.stamp_ns = 1000 + static_cast<int64_t>(seq);
  return p;
}

proto::CloudFrameMsg cloud(uint64_t seq, size_t bytes = 1000) {
  proto::CloudFrameMsg c;
  c.vehicle_id = "uav";
  c.session_id = "s";
  c.stream = kStream;
  c.seq = seq;
  c.payload.assign(bytes, static_cast<uint8_t>(seq));
  return c;
}

proto::AckMsg ack(uint64_t poses, uint64_t clouds, const std::string& session = "s") {
  proto::AckMsg a;
  a.vehicle_id = "uav";
  a.session_id = session;
  a.stream = kStream;
  a.poses = poses;
  a.clouds = clouds;
  return a;
}

// The seqs of each topic forEachDue() visits, in order.
std::vector<std::pair<SpoolTopic, uint64_t>> due(Spool& spool) {
  std::vector<std::pair<SpoolTopic, uint64_t>> visited;
  spool.forEachDue(1'000'000'000'000, std::chrono::seconds(1), [&](const SpoolRecord& r) {
    visited.emplace_back(spoolTopicOf(r), std::visit([](const auto& m) { return m.seq; }, r));
    return true;
  });
  return visited;
}

class SpoolTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string name = "stereomap-spool-";
    name += std::to_string(::getpid());
    name += ::testing::UnitTest::GetInstance()->current_test_info()->name();
    dir_ = fs::temp_directory_path() / name;
    fs::remove_all(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::unique_ptr<Spool> open(SpoolOptions options = {}) {
    if (options.dir.empty()) options.dir = dir_;
    auto spool = Spool::open(options);
    EXPECT_TRUE(spool.ok()) << spool.error().message;
    return std::move(spool).value();
  }
  std::vector<fs::path> segments() const {
    std::vector<fs::path> found;
    for (const auto& item : fs::directory_iterator(dir_)) {
      if (item.path().extension() == ".smj") found.push_back(item.path());
    }
    std::sort(found.begin(), found.end());
    return found;
  }
  fs::path dir_;
};

TEST_F(SpoolTest, HoldsUntilAcknowledgedAndSendsSmallFirst) {
  auto spool = open();
  for (uint64_t i = 0; i < 3; ++i) {
    spool->add(cloud(i), 0);
    spool->add(pose(i), 0);
  }
  EXPECT_EQ(due(*spool), (std::vector<std::pair<SpoolTopic, uint64_t>>{{SpoolTopic::kPose, 0},
                                                                       {SpoolTopic::kPose, 1},
                                                                       {SpoolTopic::kPose, 2},
                                                                       {SpoolTopic::kCloud, 0},
                                                                       {SpoolTopic::kCloud, 1},
                                                                       {SpoolTopic::kCloud, 2}}));
  EXPECT_EQ(spool->acknowledge(ack(2, 1)), 3u);
  EXPECT_EQ(spool->stats().held, 3u);
  EXPECT_EQ(spool->lowestHeld(kStream, SpoolTopic::kPose), 2u);
  EXPECT_EQ(spool->lowestHeld(kStream, SpoolTopic::kCloud), 1u);
  EXPECT_EQ(spool->acknowledge(ack(3, 3)), 3u);
  EXPECT_TRUE(spool->empty());
}

// A sample sent again counts as sent then: it is due again only resend_after later.
TEST_F(SpoolTest, ASampleSentAgainWaitsItsTurn) {
  auto spool = open({.dir = {}});
  spool->add(pose(0), 0);
  int visits = 0;
  auto count = [&](const SpoolRecord&) { return ++visits, true; };
  spool->forEachDue(500'000'000, std::chrono::seconds(1), count);
  EXPECT_EQ(visits, 0);
  spool->forEachDue(1'000'000'000, std::chrono::seconds(1), count);
  EXPECT_EQ(visits, 1);
  spool->forEachDue(1'500'000'000, std::chrono::seconds(1), count);
  EXPECT_EQ(visits, 1);
}

TEST_F(SpoolTest, ForgedAcknowledgementsDropNothing) {
  auto spool = open();
  spool->add(pose(0), 0);
  spool->add(cloud(0), 0);
  EXPECT_FALSE(spool->acknowledge(ack(1, 1, "other-session")));
  EXPECT_FALSE(spool->acknowledge(ack(5, 1)));  // more poses than were ever sent
  auto other_stream = ack(1, 1);
  other_stream.stream = kStream + 1;
  EXPECT_FALSE(spool->acknowledge(other_stream));
  EXPECT_EQ(spool->stats().held, 2u);
  EXPECT_EQ(spool->stats().refused_acks, 3u);
  EXPECT_EQ(spool->acknowledge(ack(1, 1)), 2u);
}

// A process killed with samples held: the next one on the same folder holds them again.
TEST_F(SpoolTest, ANewProcessHoldsWhatTheLastLeft) {
  {
    auto spool = open();
    for (uint64_t i = 0; i < 10; ++i) spool->add(pose(i), 0);
    spool->acknowledge(ack(4, 0));
  }
  auto again = open();
  EXPECT_EQ(again->stats().recovered, 6u);
  EXPECT_EQ(again->lowestHeld(kStream, SpoolTopic::kPose), 4u);
  EXPECT_EQ(again->streams(), std::vector<uint64_t>{kStream});
}

// Given up because the server closed the session: only that session's streams, counted, and
// a later process does not hold them again.
TEST_F(SpoolTest, SamplesOfAClosedSessionGivenUpStayGiven) {
  {
    auto spool = open();
    for (uint64_t i = 0; i < 5; ++i) spool->add(pose(i), 0);
    spool->add(cloud(0), 0);
    auto other = pose(0);
    other.session_id = "t";
    other.stream = kStream + 1;
    spool->add(other, 0);
    EXPECT_EQ(spool->giveUp("s"), 6u);
    EXPECT_EQ(spool->stats().dropped_closed, 6u);
    EXPECT_EQ(spool->stats().acknowledged, 0u);
    EXPECT_EQ(spool->stats().held, 1u);  // session t's
  }
  auto again = open();
  EXPECT_EQ(again->stats().recovered, 1u);
  EXPECT_FALSE(again->lowestHeld(kStream, SpoolTopic::kPose));
  EXPECT_FALSE(again->lowestHeld(kStream, SpoolTopic::kCloud));
  EXPECT_EQ(again->lowestHeld(kStream + 1, SpoolTopic::kPose), 0u);
}

// Acknowledged segments go from the disk; the one being written stays.
TEST_F(SpoolTest, AcknowledgedSegmentsAreDeleted) {
  auto spool = open({.segment_bytes = 4000});
  for (uint64_t i = 0; i < 20; ++i) spool->add(cloud(i), 0);
  const size_t written = segments().size();
  EXPECT_GE(written, 4u);
  spool->acknowledge(ack(0, 20));
  EXPECT_EQ(segments().size(), 1u);
}

// Power lost while writing: a flipped byte costs its record, a file cut short its last one.
TEST_F(SpoolTest, DamageCostsTheDamagedRecordsOnly) {
  {
    auto spool = open();
    for (uint64_t i = 0; i < 10; ++i) spool->add(cloud(i), 0);
  }
  const auto files = segments();
  ASSERT_EQ(files.size(), 1u);
  const auto size = fs::file_size(files[0]);
  {
    std::fstream file(files[0], std::ios::in | std::ios::out | std::ios::binary);
    file.seekp(static_cast<std::streamoff>(size / 2));
    file.put('\x5a');
  }
  fs::resize_file(files[0], size - 300);
  auto again = open();
  EXPECT_EQ(again->stats().recovered, 8u);
  EXPECT_EQ(again->stats().lost_records, 1u);  // the flipped one; the cut one was never whole
  EXPECT_EQ(due(*again).size(), 8u);
}

TEST_F(SpoolTest, AFullSpoolGivesUpTheOldestCloudsFirst) {
  auto spool = open({.max_bytes = 8000});
  for (uint64_t i = 0; i < 4; ++i) spool->add(pose(i), 0);
  for (uint64_t i = 0; i < 10; ++i) spool->add(cloud(i), 0);
  EXPECT_LE(spool->stats().held_bytes, 8000u);
  EXPECT_EQ(spool->stats().dropped_other, 0u);
  EXPECT_GT(spool->stats().dropped_clouds, 0u);
  EXPECT_EQ(spool->lowestHeld(kStream, SpoolTopic::kPose), 0u);
  EXPECT_EQ(spool->lowestHeld(kStream, SpoolTopic::kCloud), spool->stats().dropped_clouds);
}

// Beyond the memory bound, samples are read back from their segment when sent again.
TEST_F(SpoolTest, SamplesBeyondTheMemoryBoundAreReadBack) {
  auto spool = open({.memory_bytes = 3000, .segment_bytes = 5000});
  for (uint64_t i = 0; i < 12; ++i) spool->add(cloud(i), 0);
  EXPECT_LE(spool->stats().memory_bytes, 3000u);
  std::vector<uint64_t> payload_seqs;
  spool->forEachDue(1'000'000'000'000, std::chrono::seconds(1), [&](const SpoolRecord& r) {
    const auto& c = std::get<proto::CloudFrameMsg>(r);
    EXPECT_EQ(c.payload.size(), 1000u);
    payload_seqs.push_back(c.payload[0]);
    return true;
  });
  EXPECT_EQ(payload_seqs, (std::vector<uint64_t>{0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11}));
}

// A disk that fills: samples stay in memory and the spool says so.
TEST_F(SpoolTest, AFullDiskKeepsSamplesInMemory) {
  auto spool = open();
  std::signal(SIGXFSZ, SIG_IGN);
  rlimit saved{};
  ASSERT_EQ(::getrlimit(RLIMIT_FSIZE, &saved), 0);
  rlimit limited = saved;
  limited.rlim_cur = 3000;
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &limited), 0);
  for (uint64_t i = 0; i < 6; ++i) spool->add(cloud(i), 0);
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &saved), 0);
  std::signal(SIGXFSZ, SIG_DFL);
  EXPECT_FALSE(spool->stats().disk_ok);
  EXPECT_NE(spool->stats().disk_problem.find("journal write failed"), std::string::npos)
      << spool->stats().disk_problem;
  EXPECT_EQ(spool->stats().held, 6u);
  EXPECT_EQ(due(*spool).size(), 6u);
}

// Names in the folder that are not the spool's segments (a number past 64 bits among them) are
// left alone.
TEST_F(SpoolTest, ForeignFilesInTheFolderAreLeftAlone) {
  fs::create_directories(dir_);
  for (const char* name : {"spool-99999999999999999999.smj", "spool-.smj", "spool--1.smj",
                           "spool-1x.smj", "notes.txt"}) {
    std::ofstream(dir_ / name) << "not a segment";
  }
  auto spool = open();
  EXPECT_EQ(spool->stats().recovered, 0u);
  EXPECT_TRUE(fs::exists(dir_ / "spool-99999999999999999999.smj"));
}

TEST_F(SpoolTest, ANewerCorrectionReplacesTheOlder) {
  auto spool = open({.dir = {}});
  for (uint64_t i = 0; i < 3; ++i) {
    proto::PoseCorrectionMsg c;
    c.vehicle_id = "uav";
    c.session_id = "s";
    c.stream = kStream;
    c.seq = i;
    spool->add(c, 0);
  }
  EXPECT_EQ(spool->stats().held, 1u);
  EXPECT_EQ(spool->stats().superseded, 2u);
  EXPECT_EQ(spool->lowestHeld(kStream, SpoolTopic::kCorrection), 2u);
}

}  // namespace
}  // namespace stereomap::link
