#include "server/store/session_journals.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cstdio>

#include "common/files.hpp"
#include "common/time.hpp"

namespace stereomap::store {

namespace fs = std::filesystem;
using common::ErrorCode;
using common::makeError;

fs::path snapshotPath(const fs::path& dir, uint64_t label) {
  char name[40];
  std::snprintf(name, sizeof(name), "snapshot-%010llu.ot", static_cast<unsigned long long>(label));
  return dir / name;
}

uint64_t journalBytes(const fs::path& session_dir) {
  std::error_code ec;
  const auto bytes = fs::file_size(session_dir / kJournalName, ec);
  return ec ? 0 : bytes;
}

std::vector<std::pair<uint64_t, fs::path>> snapshotsIn(const fs::path& dir) {
  std::vector<std::pair<uint64_t, fs::path>> found;
  const auto entries = common::directoryEntries(dir);
  if (!entries) return found;
  for (const auto& path : *entries) {
    const std::string name = path.filename().string();
    if (name.rfind("snapshot-", 0) != 0 || path.extension() != ".ot") continue;
    const std::string digits = name.substr(9, name.size() - 9 - 3);
    if (digits.empty() || digits.size() > 19 ||
        !std::all_of(digits.begin(), digits.end(), [](char c) { return c >= '0' && c <= '9'; })) {
      continue;
    }
    found.emplace_back(std::stoull(digits), path);
  }
  std::sort(found.rbegin(), found.rend());
  return found;
}

uint64_t legacySnapshotNumber(const JournalReplay& replay, uint64_t frames) {
  if (replay.version != 1 || !replay.damage.empty() || frames == 0) return 0;
  uint64_t clouds = 0;
  for (size_t i = 0; i < replay.records.size(); ++i) {
    clouds += std::holds_alternative<proto::CloudFrameMsg>(replay.records[i]);
    if (clouds == frames) return replay.numbers[i];
  }
  return 0;
}

common::Result<RepairReport> repairJournal(const fs::path& dir) {
  const fs::path path = dir / kJournalName;
  auto replay = readJournal(path);
  if (!replay) return replay.error();
  RepairReport report{replay->records.size(), replay->lostRecords(), replay->problem, {}};
  if (replay->version == 2 && replay->problem.empty()) return report;
  if (replay->good_bytes == 0 && replay->file_bytes > 0) {
    return makeError(ErrorCode::kCorrupt, path.string() + ": " + replay->problem);
  }
  if (!replay->problem.empty()) {  // keep the damaged file for inspection
    report.original = dir / (std::string(kJournalName) + ".damaged-" +
                             std::to_string(common::nowNs() / 1'000'000'000));
    std::error_code ec;
    fs::copy_file(path, report.original, ec);
    if (ec) {
      return makeError(ErrorCode::kIo, "cannot keep the damaged journal as " +
                                           report.original.string() + ": " + ec.message());
    }
  }
  if (replay->version == 1) {  // snapshots were labelled by frame counts
    for (const auto& [frames, snapshot] : snapshotsIn(dir)) {
      const uint64_t number = legacySnapshotNumber(*replay, frames);
      std::error_code ec;
      if (number == 0) {
        fs::remove(snapshot, ec);
      } else if (snapshotPath(dir, number) != snapshot) {
        fs::rename(snapshot, snapshotPath(dir, number), ec);
      }
      if (ec)
        return makeError(ErrorCode::kIo,
                         "cannot relabel " + snapshot.string() + ": " + ec.message());
    }
  }
  if (auto written = rewriteJournal(path, replay->records, replay->numbers); !written) {
    return written.error();
  }
  return report;
}

common::Status SessionJournals::saveSnapshot(const std::string& session, uint64_t journal_number,
                                             const std::string& ot) {
  const fs::path dir = root_ / session;
  if (auto written = common::writeFileAtomically(snapshotPath(dir, journal_number), ot); !written) {
    return written;
  }
  std::error_code ec;
  for (const auto& [label, older] : snapshotsIn(dir)) {
    if (label < journal_number) fs::remove(older, ec);
  }
  return common::Ok{};
}

void SessionJournals::release(const std::string& session) {
  std::lock_guard lock(mutex_);
  journals_.erase(session);
}

common::Result<uint64_t> SessionJournals::append(const proto::CloudFrameMsg& frame) {
  return appendTo(frame.session_id, frame);
}

common::Result<uint64_t> SessionJournals::append(const proto::PoseMsg& pose) {
  return appendTo(pose.session_id, pose);
}

common::Result<uint64_t> SessionJournals::append(const proto::SessionEventMsg& event) {
  return appendTo(event.session_id, event);
}

common::Result<uint64_t> SessionJournals::appendTo(const std::string& session,
                                                   const JournalRecord& record) {
  std::lock_guard lock(mutex_);
  auto found = journals_.find(session);
  if (found == journals_.end()) {
    auto opened = openJournal(session);
    if (!opened) return opened.error();
    found = journals_.emplace(session, std::move(opened).value()).first;
  }
  return found->second->append(record);
}

common::Result<std::unique_ptr<Journal>> SessionJournals::openJournal(const std::string& session) {
  const fs::path dir = root_ / session;  // ids are validated: no separators, no ".."
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) return makeError(ErrorCode::kIo, "cannot create " + dir.string() + ": " + ec.message());
  if (!fs::exists(dir / kMetaName, ec)) {
    const std::string meta = "{\"resolution\": " + std::to_string(resolution_) + "}\n";
    if (auto written = common::writeFileAtomically(dir / kMetaName, meta); !written) {
      return written.error();
    }
  }
  // A snapshot may hold records the file no longer does (a damaged tail): their numbers are
  // never given to new records.
  const auto snapshots = snapshotsIn(dir);
  const uint64_t first_number = snapshots.empty() ? 1 : snapshots.front().first + 1;
  auto opened = Journal::open(dir / kJournalName, first_number);
  if (!opened && opened.error().code == ErrorCode::kConflict) {  // format 1: upgrade it
    if (auto repaired = repairJournal(dir); !repaired) return repaired.error();
    spdlog::info("session '{}': journal rewritten in format 2", session);
    const auto relabelled = snapshotsIn(dir);
    opened =
        Journal::open(dir / kJournalName, relabelled.empty() ? 1 : relabelled.front().first + 1);
  }
  return opened;
}

}  // namespace stereomap::store
