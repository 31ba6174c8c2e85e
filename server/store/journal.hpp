// A session's journal: an append-only file of the frames and poses the server received,
// each record length-prefixed and CRC-32 checksummed, flushed to disk (fdatasync) before
// append() returns, so a frame counts as received only once it is durable. Reading stops at
// the first torn or corrupt record; recovery cuts the file there and keeps everything before.
//
//   auto journal = Journal::open("sessions/s1/journal.smj");   // recovers a torn tail
//   journal->append(cloud_frame);
//   auto replay = readJournal("sessions/s1/journal.smj");     // records + what was cut
#pragma once

#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>
#include <variant>
#include <vector>

#include "common/result.hpp"
#include "proto/messages.hpp"

namespace stereomap::store {

using JournalRecord = std::variant<proto::CloudFrameMsg, proto::PoseMsg, proto::SessionEventMsg>;

struct JournalReplay {
  std::vector<JournalRecord> records;
  uint64_t good_bytes = 0;  // length of the intact prefix
  uint64_t file_bytes = 0;
  std::string problem;  // empty when the whole file was intact; else what was cut
};

// Reads every intact record. A missing file is an error; a damaged tail is not (it is
// described in `problem`).
common::Result<JournalReplay> readJournal(const std::filesystem::path& path);

class Journal {
 public:
  // Opens for appending, creating the file if needed. An existing file is checked first: a
  // torn or corrupt tail is cut off (described in recovered().problem) and everything before
  // it kept.
  static common::Result<std::unique_ptr<Journal>> open(const std::filesystem::path& path);
  ~Journal();
  Journal(const Journal&) = delete;
  Journal& operator=(const Journal&) = delete;

  // Appends and makes the record durable before returning.
  common::Status append(const JournalRecord& record);
  const JournalReplay& recovered() const { return recovered_; }
  uint64_t bytes() const { return bytes_; }

 private:
  Journal() = default;
  std::FILE* file_ = nullptr;
  std::filesystem::path path_;
  JournalReplay recovered_;
  uint64_t bytes_ = 0;
};

// CRC-32 (IEEE 802.3), as zlib's crc32().
uint32_t crc32(const uint8_t* data, size_t size);

}  // namespace stereomap::store
