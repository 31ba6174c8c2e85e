// A session's journal: an append-only file of the frames, poses and session events the server
// received, flushed to disk (fdatasync) before append() returns, so a sample counts as
// received only once its record is whole on disk. A failed write is cut back at once: the
// file always ends at its last whole record before anything else is appended.
//
// Format 2 (docs/PROTOCOL.md, "Journal"): the header "SMJOURN2", then records, each a 24-byte
// header (marker "SMR\x02", body length, record number, CRC-32 of the body, CRC-32 of the
// header) and the body. Record numbers start at 1 and only grow; snapshots name the record
// they cover up to. Reading resynchronises on the next valid header after any damage, so one
// flipped byte costs at most the record it is in, and every lost record is reported by
// number. Format 1 journals (no markers, no numbers) are still read, with a slower resync.
//
//   auto journal = Journal::open("sessions/s1/journal.smj");   // cuts a torn tail
//   auto number = journal->append(cloud_frame);
//   auto replay = readJournal("sessions/s1/journal.smj");     // records + what was lost
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <variant>
#include <vector>

#include "common/result.hpp"
#include "proto/messages.hpp"

namespace stereomap::proto::journal {

using JournalRecord = std::variant<proto::CloudFrameMsg, proto::PoseMsg, proto::SessionEventMsg,
                                   proto::PoseCorrectionMsg, proto::FrameAlignmentMsg>;

// A stretch of the file that could not be read. Reading continued after it.
struct JournalDamage {
  uint64_t begin = 0, end = 0;  // bytes [begin, end)
  // Record numbers that were in it, when the neighbours tell (0, 0: none known lost).
  uint64_t first_lost = 0, last_lost = 0;
  std::string reason;
  std::string describe() const;  // "record 202 (bytes 1234-5678): checksum mismatch"
};

struct JournalReplay {
  int version = 2;
  std::vector<JournalRecord> records;
  std::vector<uint64_t> numbers;      // numbers[i]: records[i]'s record number
  uint64_t kept = 0;                  // intact records (those visitJournal skipped included)
  std::vector<JournalDamage> damage;  // inside the file; the records around it are kept
  uint64_t good_bytes = 0;            // end of the last whole record: where appending continues
  uint64_t file_bytes = 0;            // a torn tail is what lies between the two
  uint64_t last_number = 0;           // highest number in any whole record, damaged ones included
  bool header_damaged = false;
  // The file ends in bytes that are neither records nor a write cut short (a damaged last
  // header): its last `damage` entry. Journal::open sets them aside before appending.
  bool damaged_tail = false;
  // Empty when the file was intact; else every damage and what was cut, for people.
  std::string problem;
  uint64_t lostRecords() const;  // counted from the numbers around each damage
};

// Reads every intact record. A missing file is an error; damage is not (see `damage` and
// `problem`). A file that is not a journal has good_bytes 0 and a problem.
common::Result<JournalReplay> readJournal(const std::filesystem::path& path);

// The same, streamed: each intact record numbered at least `min_number` goes to `visit` in
// file order and is not kept (the result's `records` stay empty); records below it are
// checked but not decoded. For reading a long journal again (re-fusing a session's frames).
// `from_offset` > 0: where a record of a format 2 file starts (SessionJournals::offsetBefore());
// only the bytes from there are read. Byte offsets in the result still count from the file's
// start; `kept` and the record numbers of damage count only what was read.
using JournalVisitor = std::function<void(JournalRecord&& record, uint64_t number)>;
common::Result<JournalReplay> visitJournal(const std::filesystem::path& path, uint64_t min_number,
                                           const JournalVisitor& visit, uint64_t from_offset = 0);

class Journal {
 public:
  // Opens for appending, creating the file (format 2) if needed. An existing file is read
  // first: a torn tail (less than a record header, or a header whose record runs past the
  // end) is cut; a damaged tail is first copied to `journal.smj.tail-<offset>` (when that
  // fails, nothing is cut and open fails); damage inside is left for readers to skip (and for
  // `stereomap-store repair`). A file that exists but cannot be read is an error, never a
  // new journal. New records are numbered above every number the file holds
  // and at least `first_number` (callers pass one past their newest snapshot's).
  // A format 1 file is refused (kConflict): rewriteJournal() upgrades it.
  // `scanned`: the file as readJournal() has just read it (recovery), so that it is not read
  // again; open fails (kUnavailable) when the file has changed size since.
  static common::Result<std::unique_ptr<Journal>> open(const std::filesystem::path& path,
                                                       uint64_t first_number = 1,
                                                       const JournalReplay* scanned = nullptr);
  ~Journal();
  Journal(const Journal&) = delete;
  Journal& operator=(const Journal&) = delete;

  // Appends and makes the record durable (kNow: fdatasync before it returns; kLater: in the
  // page cache, durable at the next sync(), or when the kernel writes it back: what survives
  // the process, not a power loss); its record number. On failure (a full disk) the
  // partial record is cut off again before anything else is written, and the error names
  // the cause; while it cannot be cut, every append fails.
  enum class Durability { kNow, kLater };
  common::Result<uint64_t> append(const JournalRecord& record,
                                  Durability durability = Durability::kNow);
  // Makes everything appended durable.
  common::Status sync();
  // What opening found (damage, the tail cut), without the records themselves.
  const JournalReplay& recovered() const { return recovered_; }
  uint64_t bytes() const { return bytes_; }
  uint64_t nextNumber() const { return next_number_; }

 private:
  Journal() = default;
  // Cuts the file back to bytes_ after a failed write; false when even that failed.
  bool cutBack();
  // Copies the damaged tail (recovered_.damaged_tail) beside the journal.
  common::Status setAsideTail();
  int fd_ = -1;
  std::filesystem::path path_;
  JournalReplay recovered_;
  uint64_t bytes_ = 0;
  uint64_t next_number_ = 1;
  bool needs_cut_ = false;
};

// Writes `records` (with their numbers, which must grow) as a new format 2 journal at
// `path`, atomically: a temporary file, fsync, rename. Used to repair a damaged journal and
// to upgrade a format 1 one.
common::Status rewriteJournal(const std::filesystem::path& path,
                              const std::vector<JournalRecord>& records,
                              const std::vector<uint64_t>& numbers);

// One record's bytes without the file's framing (a type byte and the body, what the CRC
// covers), for stores that keep records elsewhere than in a journal file (the cluster's
// database); and back: nullopt when the bytes are not a whole record of a known type.
std::vector<uint8_t> encodeRecord(const JournalRecord& record);
std::optional<JournalRecord> decodeRecord(const uint8_t* data, size_t size);

// CRC-32 (IEEE 802.3), as zlib's crc32().
uint32_t crc32(const uint8_t* data, size_t size);

}  // namespace stereomap::proto::journal
