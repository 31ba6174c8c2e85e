#include "proto/journal/journal.hpp"

#include <gtest/gtest.h>

#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <csignal>
#include <cstring>
#include <fstream>

#include "testing/journal_fixture.hpp"
#include "testing/journal_format_one.hpp"

namespace stereomap::proto::journal {
namespace {

namespace fs = std::filesystem;
using testing::JournalTest;

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

// A vehicle in its own frame: its start event's trailing frame byte, and the server's
// alignment record; a session-frame event is written byte for byte as before (no byte more).
TEST_F(JournalTest, OwnFrameEventsAndFrameAlignmentsRoundTrip) {
  proto::SessionEventMsg event;
  event.vehicle_id = "uav";
  event.session_id = "s";
  const size_t session_frame_bytes = encodeRecord(event).size();
  event.frame = proto::VehicleFrame::kOwn;
  EXPECT_EQ(encodeRecord(event).size(), session_frame_bytes + 1);
  proto::FrameAlignmentMsg alignment;
  alignment.vehicle_id = "uav";
  alignment.session_id = "s";
  alignment.stamp_ns = 99;
  alignment.position = {1.5, -2.0, 0.25};
  alignment.orientation = {0, 0, 0.6, 0.8};
  alignment.overlap = 0.7;
  alignment.rmse_m = 0.03;
  {
    auto journal = Journal::open(path_);
    ASSERT_TRUE(journal.ok());
    ASSERT_TRUE((*journal)->append(event).ok());
    ASSERT_TRUE((*journal)->append(alignment).ok());
  }
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  ASSERT_EQ(replay->records.size(), 2u) << replay->problem;
  EXPECT_EQ(std::get<proto::SessionEventMsg>(replay->records[0]).frame, proto::VehicleFrame::kOwn);
  const auto& back = std::get<proto::FrameAlignmentMsg>(replay->records[1]);
  EXPECT_EQ(back.stamp_ns, 99);
  EXPECT_EQ(back.position, alignment.position);
  EXPECT_EQ(back.orientation, alignment.orientation);
  EXPECT_DOUBLE_EQ(back.overlap, 0.7);
  EXPECT_DOUBLE_EQ(back.rmse_m, 0.03);
  // A frame byte out of range is damage, not a frame.
  auto bytes = encodeRecord(event);
  bytes.back() = 2;
  EXPECT_FALSE(decodeRecord(bytes.data(), bytes.size()).has_value());
}

TEST_F(JournalTest, PoseCorrectionsRoundTripAndStreamFromANumber) {
  auto journal = Journal::open(path_);
  ASSERT_TRUE(journal.ok());
  proto::PoseCorrectionMsg correction;
  correction.vehicle_id = "uav";
  correction.session_id = "s";
  correction.seq = 4;
  correction.stamp_ns = 99;
  for (int i = 0; i < 3; ++i) {
    correction.keyframes.push_back({10 + i, {0.5 * i, 1, 2}, {0, 0, 0.6, 0.8}});
  }
  ASSERT_TRUE((*journal)->append(frame(0)).ok());
  ASSERT_TRUE((*journal)->append(correction).ok());
  ASSERT_TRUE((*journal)->append(frame(1)).ok());
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  ASSERT_EQ(replay->records.size(), 3u);
  const auto& back = std::get<proto::PoseCorrectionMsg>(replay->records[1]);
  EXPECT_EQ(back.seq, 4u);
  EXPECT_EQ(back.stamp_ns, 99);
  ASSERT_EQ(back.keyframes.size(), 3u);
  EXPECT_EQ(back.keyframes[2].stamp_ns, 12);
  EXPECT_EQ(back.keyframes[2].position, correction.keyframes[2].position);
  EXPECT_EQ(back.keyframes[2].orientation, correction.keyframes[2].orientation);
  // Streamed from record 2: the records before are checked, not handed over.
  std::vector<uint64_t> numbers;
  auto streamed =
      visitJournal(path_, 2, [&](JournalRecord&&, uint64_t number) { numbers.push_back(number); });
  ASSERT_TRUE(streamed.ok());
  EXPECT_EQ(numbers, (std::vector<uint64_t>{2, 3}));
  EXPECT_EQ(streamed->kept, 3u);
  EXPECT_TRUE(streamed->problem.empty());
}

TEST_F(JournalTest, TornTailIsCutAndEverythingBeforeKept) {
  const auto sizes = writeFive();
  fs::resize_file(path_, sizes[3] + 20);  // mid-way through the fifth record
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  EXPECT_EQ(replay->records.size(), 4u);
  EXPECT_EQ(replay->good_bytes, sizes[3]);
  EXPECT_NE(replay->problem.find("torn tail"), std::string::npos) << replay->problem;

  // Reopening cuts the tail; appending goes on from the intact prefix.
  auto journal = Journal::open(path_);
  ASSERT_TRUE(journal.ok()) << journal.error().message;
  EXPECT_EQ((*journal)->recovered().kept, 4u);
  EXPECT_TRUE((*journal)->recovered().records.empty());  // checked, not kept
  EXPECT_EQ(fs::file_size(path_), sizes[3]);
  ASSERT_TRUE((*journal)->append(frame(7)).ok());
  journal->reset();
  replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  EXPECT_TRUE(replay->problem.empty()) << replay->problem;
  ASSERT_EQ(replay->records.size(), 5u);
  EXPECT_EQ(std::get<proto::CloudFrameMsg>(replay->records[4]).seq, 7u);
  EXPECT_EQ(replay->numbers, (std::vector<uint64_t>{1, 2, 3, 4, 5}));
}

// Issue 13: one flipped byte anywhere may cost at most the record it is in.
TEST_F(JournalTest, AFlippedByteAnywhereCostsAtMostItsRecord) {
  const auto sizes = writeFive();
  std::ifstream in(path_, std::ios::binary);
  const std::string original((std::istreambuf_iterator<char>(in)),
                             std::istreambuf_iterator<char>());
  in.close();
  const fs::path damaged = dir_ / "damaged.smj";
  for (size_t at = 0; at < original.size(); ++at) {
    std::string bytes = original;
    bytes[at] = static_cast<char>(bytes[at] ^ 0x10);
    std::ofstream(damaged, std::ios::binary | std::ios::trunc) << bytes;
    auto replay = readJournal(damaged);
    ASSERT_TRUE(replay.ok());
    ASSERT_FALSE(replay->problem.empty()) << "byte " << at;
    if (at < 8) {  // the file header: nothing lost
      EXPECT_TRUE(replay->header_damaged);
      EXPECT_EQ(replay->records.size(), 5u) << "byte " << at;
      continue;
    }
    const size_t record = std::upper_bound(sizes.begin(), sizes.end(), at) - sizes.begin();
    ASSERT_EQ(replay->records.size(), 4u) << "byte " << at << ": " << replay->problem;
    std::vector<uint64_t> expected = {1, 2, 3, 4, 5};
    expected.erase(expected.begin() + static_cast<long>(record));
    EXPECT_EQ(replay->numbers, expected) << "byte " << at;
    // Which record was lost is told by number, the last record's own header included (it
    // is not taken for a write cut short).
    ASSERT_EQ(replay->damage.size(), 1u) << "byte " << at << ": " << replay->problem;
    EXPECT_EQ(replay->damage[0].first_lost, record + 1) << "byte " << at;
    EXPECT_EQ(replay->damage[0].last_lost, record + 1) << "byte " << at;
    EXPECT_EQ(replay->lostRecords(), 1u);
  }
}

// Review of issue 13: a flipped byte in the last record's header must not make open() cut an
// acknowledged record as if it were a torn write. Its bytes are set aside, its number is
// never reused, and appending goes on after the record before it.
TEST_F(JournalTest, ADamagedLastHeaderIsSetAsideNotCut) {
  const auto sizes = writeFive();
  {
    std::fstream file(path_, std::ios::in | std::ios::out | std::ios::binary);
    file.seekp(static_cast<std::streamoff>(sizes[3] + 10));  // the fifth record's number
    file.put('\x7F');
  }
  auto journal = Journal::open(path_);
  ASSERT_TRUE(journal.ok()) << journal.error().message;
  const auto& recovered = (*journal)->recovered();
  EXPECT_TRUE(recovered.damaged_tail);
  EXPECT_EQ(recovered.lostRecords(), 1u);
  EXPECT_NE(recovered.problem.find("record 5 lost"), std::string::npos) << recovered.problem;
  const fs::path tail = path_.string() + ".tail-" + std::to_string(sizes[3]);
  EXPECT_NE(recovered.problem.find(tail.string()), std::string::npos) << recovered.problem;
  ASSERT_TRUE(fs::exists(tail));
  EXPECT_EQ(fs::file_size(tail), sizes[4] - sizes[3]);
  EXPECT_EQ(fs::file_size(path_), sizes[3]);
  EXPECT_EQ(*(*journal)->append(pose(4)), 6u);
  journal->reset();
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  EXPECT_TRUE(replay->problem.empty()) << replay->problem;
  EXPECT_EQ(replay->numbers, (std::vector<uint64_t>{1, 2, 3, 4, 6}));

  // Less than a header at the end is a write cut short: cut, nothing set aside.
  fs::remove(tail);
  fs::resize_file(path_, fs::file_size(path_) + 23);
  journal = Journal::open(path_);
  ASSERT_TRUE(journal.ok());
  EXPECT_FALSE((*journal)->recovered().damaged_tail);
  EXPECT_EQ((*journal)->recovered().lostRecords(), 0u);
  EXPECT_FALSE(fs::exists(path_.string() + ".tail-" + std::to_string(fs::file_size(path_))));
}

// Review of issue 13: a journal that exists but cannot be read is an error, never a missing
// journal to be started afresh over the old one.
TEST_F(JournalTest, AnUnreadableJournalIsNotTakenForAMissingOne) {
  fs::create_directories(path_);  // reads fail with EISDIR, as they would with EIO
  auto replay = readJournal(path_);
  ASSERT_FALSE(replay.ok());
  EXPECT_EQ(replay.error().code, common::ErrorCode::kIo) << replay.error().message;
  auto journal = Journal::open(path_);
  ASSERT_FALSE(journal.ok());
  EXPECT_EQ(journal.error().code, common::ErrorCode::kIo) << journal.error().message;
  EXPECT_TRUE(fs::is_directory(path_));
  EXPECT_EQ(readJournal(dir_ / "missing.smj").error().code, common::ErrorCode::kNotFound);
}

TEST_F(JournalTest, AppendingGoesOnAfterDamageWithNewNumbers) {
  const auto sizes = writeFive();
  {
    std::fstream file(path_, std::ios::in | std::ios::out | std::ios::binary);
    file.seekp(static_cast<std::streamoff>(sizes[1] + 30));  // inside the third record
    file.put('\x5A');
  }
  auto journal = Journal::open(path_);
  ASSERT_TRUE(journal.ok()) << journal.error().message;
  EXPECT_EQ((*journal)->nextNumber(), 6u);
  auto number = (*journal)->append(frame(9));
  ASSERT_TRUE(number.ok());
  EXPECT_EQ(*number, 6u);
  journal->reset();
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  EXPECT_EQ(replay->numbers, (std::vector<uint64_t>{1, 2, 4, 5, 6}));
  EXPECT_NE(replay->problem.find("record 3 lost"), std::string::npos) << replay->problem;
  EXPECT_NE(replay->problem.find("checksum mismatch"), std::string::npos) << replay->problem;

  // Rewritten without the damaged record, numbers kept (snapshots name them).
  ASSERT_TRUE(rewriteJournal(path_, replay->records, replay->numbers).ok());
  auto rewritten = readJournal(path_);
  ASSERT_TRUE(rewritten.ok());
  EXPECT_TRUE(rewritten->problem.empty()) << rewritten->problem;
  EXPECT_EQ(rewritten->numbers, replay->numbers);
  // New numbers start above every number a snapshot may hold.
  journal = Journal::open(path_, 40);
  ASSERT_TRUE(journal.ok());
  EXPECT_EQ(*(*journal)->append(pose(3)), 40u);
}

// Issue 13: a failed write (a full disk) leaves the journal at its last whole record, and
// the next append after space is freed lands right after it.
TEST_F(JournalTest, AFailedWriteIsCutBackBeforeAnythingElseIsAppended) {
  auto journal = Journal::open(path_);
  ASSERT_TRUE(journal.ok());
  ASSERT_TRUE((*journal)->append(frame(0)).ok());
  const uint64_t whole = (*journal)->bytes();
  // RLIMIT_FSIZE makes the kernel refuse writes past a size, as a full disk does, after
  // a partial write.
  std::signal(SIGXFSZ, SIG_IGN);
  rlimit saved{};
  ASSERT_EQ(::getrlimit(RLIMIT_FSIZE, &saved), 0);
  rlimit limited = saved;
  limited.rlim_cur = whole + 50;  // room for part of the next record only
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &limited), 0);
  auto failed = (*journal)->append(frame(1));
  auto failed_again = (*journal)->append(pose(1));
  const uint64_t size_while_full = fs::file_size(path_);
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &saved), 0);
  std::signal(SIGXFSZ, SIG_DFL);
  ASSERT_FALSE(failed.ok());
  EXPECT_NE(failed.error().message.find("File too large"), std::string::npos)
      << failed.error().message;
  EXPECT_FALSE(failed_again.ok());
  EXPECT_EQ(size_while_full, whole);  // the partial record was cut off again
  EXPECT_EQ((*journal)->bytes(), whole);

  auto number = (*journal)->append(frame(2));  // space again
  ASSERT_TRUE(number.ok()) << number.error().message;
  EXPECT_EQ(*number, 2u);
  journal->reset();
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  EXPECT_TRUE(replay->problem.empty()) << replay->problem;
  ASSERT_EQ(replay->records.size(), 2u);
  EXPECT_EQ(std::get<proto::CloudFrameMsg>(replay->records[1]).seq, 2u);
}

TEST_F(JournalTest, AHeaderCutShortByAFailedFirstWriteIsAnEmptyJournal) {
  std::ofstream(path_, std::ios::binary) << "SMJO";
  auto journal = Journal::open(path_);
  ASSERT_TRUE(journal.ok()) << journal.error().message;
  ASSERT_TRUE((*journal)->append(frame(1)).ok());
  journal->reset();
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  EXPECT_TRUE(replay->problem.empty()) << replay->problem;
  EXPECT_EQ(replay->records.size(), 1u);
}

// Format 1 (before issue 13): the same payloads behind an 8-byte header (length, CRC).
TEST_F(JournalTest, FormatOneIsReadWithResynchronisation) {
  writeFive();
  std::vector<size_t> starts;
  std::string v1 = testing::formatOneOf(path_, &starts);
  const fs::path old = dir_ / "old.smj";
  std::ofstream(old, std::ios::binary) << v1;
  auto replay = readJournal(old);
  ASSERT_TRUE(replay.ok());
  EXPECT_EQ(replay->version, 1);
  EXPECT_TRUE(replay->problem.empty()) << replay->problem;
  EXPECT_EQ(replay->records.size(), 5u);
  auto refused = Journal::open(old);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.error().code, common::ErrorCode::kConflict);

  v1[starts[2] + 1] ^= 0x40;  // the third record's length: found again by scanning
  std::ofstream(old, std::ios::binary | std::ios::trunc) << v1;
  replay = readJournal(old);
  ASSERT_TRUE(replay.ok());
  EXPECT_EQ(replay->records.size(), 4u) << replay->problem;
  ASSERT_EQ(replay->damage.size(), 1u);
  EXPECT_EQ(replay->damage[0].begin, starts[2]);
  EXPECT_EQ(replay->damage[0].end, starts[3]);
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
}  // namespace stereomap::proto::journal
