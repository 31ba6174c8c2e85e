// The server side of the store's durability: one Journal per session under the store root
// (<root>/<session>/journal.smj, the MapServer's IngestLog and FrameArchive; a new session's
// directory also gets meta.json with its resolution), periodic map snapshots
// (<root>/<session>/snapshot-<record number>.ot, the MapServer's SnapshotSink), and the
// repair of damaged or format 1 journals. Recovery lives in store_admin.hpp.
#pragma once

#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <vector>

#include "proto/journal/journal.hpp"
#include "server/core/map_server.hpp"

namespace stereomap::store {

// The journal's file format is proto/journal's (the vehicle's spool writes it too); the store
// names what it uses of it as its own.
using proto::journal::crc32;
using proto::journal::Journal;
using proto::journal::JournalDamage;
using proto::journal::JournalRecord;
using proto::journal::JournalReplay;
using proto::journal::readJournal;
using proto::journal::rewriteJournal;
using proto::journal::visitJournal;

class SessionJournals : public core::IngestLog,
                        public core::SnapshotSink,
                        public core::FrameArchive {
 public:
  // `resolution`: what new sessions are created with (the server's --resolution).
  SessionJournals(std::filesystem::path root, double resolution)
      : root_(std::move(root)), resolution_(resolution) {}
  common::Result<uint64_t> append(const proto::CloudFrameMsg& frame) override;
  common::Result<uint64_t> append(const proto::PoseMsg& pose) override;
  common::Result<uint64_t> append(const proto::SessionEventMsg& event) override;
  common::Result<uint64_t> append(const proto::PoseCorrectionMsg& correction) override;
  common::Result<uint64_t> append(const proto::FrameAlignmentMsg& alignment) override;
  // Reads the session's journal file (streamed: one frame in memory at a time).
  common::Status forEachFrame(const std::string& session, uint64_t after, uint64_t up_to,
                              const std::function<void(const proto::CloudFrameMsg& frame,
                                                       uint64_t number)>& visit) const override;
  // Written atomically (temporary file + rename); older snapshots are then removed.
  common::Status saveSnapshot(const std::string& session, uint64_t journal_number,
                              const std::string& ot) override;
  // Opens a session's journal for appending now, from what recovery has just read of it
  // (`scanned`), instead of at its first append: that would read the whole file again, on an
  // ingest thread, holding every session's appends up meanwhile.
  common::Status openRecovered(const std::string& session, const JournalReplay& scanned);
  // Where a whole record of the session's journal numbered at most `number` starts, for
  // visitJournal(): reading a recent record (a deferred frame) then costs its distance from
  // the end, not the file. One mark per kMarkEvery records appended since the journal was
  // opened; 0 (the whole file) before the first.
  uint64_t offsetBefore(const std::string& session, uint64_t number) const;
  static constexpr uint64_t kMarkEvery = 64;
  // Closes a session's journal file (the session was closed or deleted).
  void release(const std::string& session);
  // While a session is deleted: its journal is closed and every append fails (a sample let
  // in just before must not reopen the file being removed, nor write into a deleted one).
  // readmit() ends it (the id may start afresh).
  void retire(const std::string& session);
  void readmit(const std::string& session);

 private:
  common::Result<uint64_t> appendTo(const std::string& session, const JournalRecord& record);
  common::Result<std::unique_ptr<Journal>> openJournal(const std::string& session,
                                                       const JournalReplay* scanned = nullptr);
  std::filesystem::path root_;
  double resolution_;
  // Forgets the session's marks (its journal was opened again, closed or retired).
  void forgetMarks(const std::string& session);
  std::mutex mutex_;
  std::map<std::string, std::unique_ptr<Journal>> journals_;
  std::set<std::string> retired_;
  // Record offsets, apart from mutex_ (held through every append's fdatasync and a journal's
  // opening): readers of deferred frames never wait behind another session's disk. Taken
  // alone, or inside mutex_.
  struct Marks {
    uint64_t appended = 0;
    std::vector<std::pair<uint64_t, uint64_t>> at;  // (record number, offset), growing
  };
  mutable std::mutex marks_mutex_;
  std::map<std::string, Marks> marks_;
};

// <dir>/snapshot-<label>.ot. Label 0: an imported map (it covers no journal record).
std::filesystem::path snapshotPath(const std::filesystem::path& dir, uint64_t label);

// <dir>/snapshot-*.ot, newest first: (label, path). The label is the journal record number
// the snapshot covers up to (format 1 journals: the number of cloud frames).
std::vector<std::pair<uint64_t, std::filesystem::path>> snapshotsIn(
    const std::filesystem::path& dir);

// The record number a format 1 snapshot label (a count of cloud frames) stands for in a
// journal read as `replay` (format 1, numbered 1..n) whose cloud frames have the record
// numbers `frame_numbers`, or 0 when it cannot be told (damage, too few frames).
uint64_t legacySnapshotNumber(const JournalReplay& replay,
                              const std::vector<uint64_t>& frame_numbers, uint64_t frames);
// The record numbers of the cloud frames in `replay.records`.
std::vector<uint64_t> frameNumbers(const JournalReplay& replay);

struct RepairReport {
  uint64_t records_kept = 0, records_lost = 0;
  std::string problem;             // what was wrong (JournalReplay::problem)
  std::filesystem::path original;  // where the damaged file was kept (empty: not kept)
};

// Rewrites <dir>/journal.smj as an intact format 2 journal of every readable record
// (numbers kept, so snapshots stay valid; a format 1 journal's snapshots are renamed to
// record numbers, or removed when damage makes them ambiguous). A damaged original is kept
// beside it as journal.smj.damaged-<unix time>. Nothing is written when the journal is
// intact and already format 2.
common::Result<RepairReport> repairJournal(const std::filesystem::path& dir);

// Removes what a crash left in <dir>: temporaries of atomic writes (`NAME.tmp-<pid>-<n>`,
// e.g. a snapshot killed mid-write); the files they were to replace are intact. Returns the
// names removed.
std::vector<std::string> removeLeftoverTemporaries(const std::filesystem::path& dir);

inline constexpr const char* kJournalName = "journal.smj";
// The size of a session directory's journal (0 when there is none).
uint64_t journalBytes(const std::filesystem::path& session_dir);
inline constexpr const char* kMetaName = "meta.json";

}  // namespace stereomap::store
