#include "server/store/session_journals.hpp"

#include <gtest/gtest.h>

#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <csignal>
#include <cstring>
#include <fstream>

#include "testing/journal_fixture.hpp"
#include "testing/journal_format_one.hpp"

namespace stereomap::store {
namespace {

namespace fs = std::filesystem;
using testing::JournalTest;

// Review of issue 13: upgrading a format 1 journal relabels its snapshots (frame counts
// become record numbers). When the rewrite fails, no snapshot may be left carrying a record
// number the format 1 journal does not mean; the next upgrade finishes the job.
TEST_F(JournalTest, UpgradingFormatOneNeverLeavesASnapshotMislabelled) {
  writeFive();  // cloud frames are records 1, 3 and 5
  const std::string v1 = testing::formatOneOf(path_);
  std::ofstream(path_, std::ios::binary | std::ios::trunc) << v1;
  std::ofstream(snapshotPath(dir_, 2)) << "the map after two frames";

  std::signal(SIGXFSZ, SIG_IGN);
  rlimit saved{};
  ASSERT_EQ(::getrlimit(RLIMIT_FSIZE, &saved), 0);
  rlimit limited = saved;
  limited.rlim_cur = 100;  // the rewritten journal cannot be written
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &limited), 0);
  auto failed = repairJournal(dir_);
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &saved), 0);
  std::signal(SIGXFSZ, SIG_DFL);
  ASSERT_FALSE(failed.ok());
  EXPECT_EQ(readJournal(path_)->version, 1);
  EXPECT_TRUE(snapshotsIn(dir_).empty());  // out of sight, not "snapshot-2" of record 2

  auto repaired = repairJournal(dir_);
  ASSERT_TRUE(repaired.ok()) << repaired.error().message;
  const auto snapshots = snapshotsIn(dir_);
  ASSERT_EQ(snapshots.size(), 1u);
  EXPECT_EQ(snapshots[0].first, 3u);  // two frames: up to record 3
  auto replay = readJournal(path_);
  ASSERT_TRUE(replay.ok());
  EXPECT_EQ(replay->version, 2);
  EXPECT_EQ(replay->numbers, (std::vector<uint64_t>{1, 2, 3, 4, 5}));
}

// A recent record (a deferred frame) is read from the journal's nearest mark: the bytes
// before it are not read at all, so a long flight's journal costs its tail, not its length.
TEST_F(JournalTest, ARecentRecordIsReadFromTheNearestMarkNotFromTheStart) {
  SessionJournals journals(dir_, 0.1);
  const fs::path path = dir_ / "s" / kJournalName;
  EXPECT_EQ(journals.offsetBefore("s", 1), 0u);  // nothing appended yet: the whole file
  std::vector<uint64_t> starts;                  // where each record starts
  for (uint64_t i = 0; i < 300; ++i) {           // frame(i) is record i + 1
    starts.push_back(fs::exists(path) ? fs::file_size(path) : 8);
    ASSERT_TRUE(journals.append(frame(i)).ok());
  }
  EXPECT_EQ(journals.offsetBefore("s", 1), starts[0]);
  EXPECT_EQ(journals.offsetBefore("s", 64), starts[0]);
  EXPECT_EQ(journals.offsetBefore("s", 65), starts[64]);  // marks: records 1, 65, 129, ...
  EXPECT_EQ(journals.offsetBefore("s", 250), starts[192]);
  EXPECT_EQ(journals.offsetBefore("s", 1000), starts[256]);

  // Over record 1, another frame numbered 295: a reading from the file's start meets it
  // among records 291-300; one from the mark (record 257) never does.
  {
    auto planted = frame(999);
    planted.payload.resize(10);
    ASSERT_TRUE(rewriteJournal(dir_ / "planted.smj", {planted}, {295}).ok());
    std::ifstream in(dir_ / "planted.smj", std::ios::binary);
    const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    ASSERT_LE(bytes.size() - 8, starts[1] - starts[0]);
    std::fstream file(path, std::ios::in | std::ios::out | std::ios::binary);
    file.seekp(static_cast<std::streamoff>(starts[0]));
    file.write(bytes.data() + 8, static_cast<std::streamsize>(bytes.size() - 8));
  }
  auto seqs = [&](const SessionJournals& store) {
    std::vector<uint64_t> seen;
    EXPECT_TRUE(
        store
            .forEachFrame("s", 290, 300,
                          [&](const proto::CloudFrameMsg& f, uint64_t) { seen.push_back(f.seq); })
            .ok());
    return seen;
  };
  const auto from_mark = seqs(journals);
  EXPECT_EQ(from_mark.size(), 10u);
  EXPECT_EQ(std::count(from_mark.begin(), from_mark.end(), 999u), 0);
  const SessionJournals unopened(dir_, 0.1);  // no marks: the whole file
  const auto whole = seqs(unopened);
  EXPECT_EQ(std::count(whole.begin(), whole.end(), 999u), 1);

  // Byte figures count from the file's start.
  auto read = visitJournal(
      path, 251, [](JournalRecord&&, uint64_t) {}, starts[192]);
  ASSERT_TRUE(read.ok());
  EXPECT_TRUE(read->damage.empty()) << read->problem;
  EXPECT_EQ(read->kept, 300u - 192u);
  EXPECT_EQ(read->good_bytes, fs::file_size(path));
  EXPECT_EQ(read->file_bytes, fs::file_size(path));
}

// Recovery's reading of a journal is not trusted once the file has changed since: the
// journal is read again and opened as it is. (Before, the refusal looked like a format 1
// journal's, so a journal with damage inside was rewritten without it.)
TEST_F(JournalTest, AJournalThatChangedSinceRecoveryReadItIsReadAgain) {
  SessionJournals journals(dir_, 0.1);
  const fs::path path = dir_ / "s" / kJournalName;
  uint64_t second = 0;  // where the second record starts
  {
    fs::create_directories(dir_ / "s");
    auto writer = Journal::open(path);
    ASSERT_TRUE(writer.ok());
    for (uint64_t i = 0; i < 3; ++i) {
      if (i == 1) second = (*writer)->bytes();
      ASSERT_TRUE((*writer)->append(frame(i)).ok());
    }
  }
  {  // damage inside: the second record's body
    std::fstream file(path, std::ios::in | std::ios::out | std::ios::binary);
    file.seekp(static_cast<std::streamoff>(second + 24 + 60));
    file.put('\x55');
  }
  const auto scanned = readJournal(path);
  ASSERT_TRUE(scanned.ok());
  ASSERT_EQ(scanned->damage.size(), 1u);
  {  // the file grows after that reading
    auto writer = Journal::open(path);
    ASSERT_TRUE(writer.ok());
    ASSERT_TRUE((*writer)->append(frame(3)).ok());
  }
  ASSERT_TRUE(journals.openRecovered("s", *scanned).ok());
  ASSERT_TRUE(journals.append(frame(4)).ok());
  const auto read = readJournal(path);
  ASSERT_TRUE(read.ok());
  EXPECT_EQ(read->numbers, (std::vector<uint64_t>{1, 3, 4, 5}));
  EXPECT_EQ(read->damage.size(), 1u);  // left for readers and `stereomap-store repair`
  for (const auto& entry : fs::directory_iterator(dir_ / "s")) {
    EXPECT_EQ(entry.path().filename().string().find(".damaged-"), std::string::npos)
        << entry.path();
  }
}

// Review of issue 13: while a session is being deleted, a sample let in just before must not
// reopen its journal (it would write into a deleted file, or recreate the folder).
TEST_F(JournalTest, ARetiredSessionRecordsNothingUntilReadmitted) {
  SessionJournals journals(dir_, 0.1);
  auto f = frame(0);
  ASSERT_TRUE(journals.append(f).ok());
  journals.retire("s");
  fs::remove_all(dir_ / "s");
  auto refused = journals.append(f);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.error().code, common::ErrorCode::kConflict);
  EXPECT_FALSE(fs::exists(dir_ / "s"));
  journals.readmit("s");
  EXPECT_EQ(*journals.append(f), 1u);  // a new flight under the same id
}

}  // namespace
}  // namespace stereomap::store
