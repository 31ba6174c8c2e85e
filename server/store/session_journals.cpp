#include "server/store/session_journals.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cstdio>
#include <iterator>

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

namespace {

// <dir>/<prefix><digits>.ot: (number, path), unsorted.
std::vector<std::pair<uint64_t, fs::path>> numberedFiles(const fs::path& dir,
                                                         const std::string& prefix) {
  std::vector<std::pair<uint64_t, fs::path>> found;
  const auto entries = common::directoryEntries(dir);
  if (!entries) return found;
  for (const auto& path : *entries) {
    const std::string name = path.filename().string();
    if (name.rfind(prefix, 0) != 0 || path.extension() != ".ot") continue;
    const std::string digits = name.substr(prefix.size(), name.size() - prefix.size() - 3);
    if (digits.empty() || digits.size() > 19 ||
        !std::all_of(digits.begin(), digits.end(), [](char c) { return c >= '0' && c <= '9'; })) {
      continue;
    }
    found.emplace_back(std::stoull(digits), path);
  }
  return found;
}

}  // namespace

std::vector<std::pair<uint64_t, fs::path>> snapshotsIn(const fs::path& dir) {
  auto found = numberedFiles(dir, "snapshot-");
  std::sort(found.rbegin(), found.rend());
  return found;
}

uint64_t legacySnapshotNumber(const JournalReplay& replay,
                              const std::vector<uint64_t>& frame_numbers, uint64_t frames) {
  if (replay.version != 1 || !replay.damage.empty() || frames == 0) return 0;
  return frames <= frame_numbers.size() ? frame_numbers[frames - 1] : 0;
}

std::vector<uint64_t> frameNumbers(const JournalReplay& replay) {
  std::vector<uint64_t> numbers;
  for (size_t i = 0; i < replay.records.size(); ++i) {
    if (std::holds_alternative<proto::CloudFrameMsg>(replay.records[i])) {
      numbers.push_back(replay.numbers[i]);
    }
  }
  return numbers;
}

std::vector<std::string> removeLeftoverTemporaries(const fs::path& dir) {
  std::vector<std::string> removed;
  const auto entries = common::directoryEntries(dir);
  if (!entries) return removed;
  for (const auto& path : *entries) {
    const std::string name = path.filename().string();
    const size_t at = name.rfind(".tmp-");
    if (at == std::string::npos || at == 0) continue;
    const std::string rest = name.substr(at + 5);  // <pid>-<n>
    const size_t dash = rest.find('-');
    auto digits = [](const std::string& text) {
      return !text.empty() &&
             std::all_of(text.begin(), text.end(), [](char c) { return c >= '0' && c <= '9'; });
    };
    if (dash == std::string::npos || !digits(rest.substr(0, dash)) ||
        !digits(rest.substr(dash + 1))) {
      continue;
    }
    std::error_code ec;
    if (fs::remove(path, ec)) removed.push_back(name);
  }
  return removed;
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
  // Format 1 snapshots are labelled by frame counts. They are moved out of sight (named by
  // the record number they will carry, relabel-<number>.ot) before the journal is rewritten,
  // and take their new label only after it: a failure at any step leaves each snapshot
  // either unseen (the journal is replayed further back: slower, never wrong) or correctly
  // labelled. Ones left out of sight by an upgrade that failed before are finished too (a
  // format 1 journal is never appended to, so their numbers still hold).
  if (replay->version == 1) {
    const auto frame_numbers = frameNumbers(*replay);
    for (const auto& [frames, snapshot] : snapshotsIn(dir)) {
      const uint64_t number = legacySnapshotNumber(*replay, frame_numbers, frames);
      std::error_code ec;
      if (number == 0) {
        fs::remove(snapshot, ec);
      } else {
        fs::rename(snapshot, dir / ("relabel-" + std::to_string(number) + ".ot"), ec);
      }
      if (ec) {
        return makeError(ErrorCode::kIo,
                         "cannot relabel " + snapshot.string() + ": " + ec.message());
      }
    }
  }
  if (auto written = rewriteJournal(path, replay->records, replay->numbers); !written) {
    return written.error();
  }
  for (const auto& [number, hidden] : numberedFiles(dir, "relabel-")) {
    std::error_code ec;
    fs::rename(hidden, snapshotPath(dir, number), ec);
    if (ec) {
      spdlog::warn("{}: not relabelled ({}); the journal is replayed without it", hidden.string(),
                   ec.message());
    }
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
  forgetMarks(session);
}

void SessionJournals::retire(const std::string& session) {
  std::lock_guard lock(mutex_);
  journals_.erase(session);
  forgetMarks(session);
  retired_.insert(session);
}

void SessionJournals::forgetMarks(const std::string& session) {
  std::lock_guard marks(marks_mutex_);
  marks_.erase(session);
}

uint64_t SessionJournals::offsetBefore(const std::string& session, uint64_t number) const {
  std::lock_guard lock(marks_mutex_);
  const auto found = marks_.find(session);
  if (found == marks_.end()) return 0;
  const auto& at = found->second.at;
  const auto after = std::upper_bound(at.begin(), at.end(), number,
                                      [](uint64_t n, const auto& mark) { return n < mark.first; });
  return after == at.begin() ? 0 : std::prev(after)->second;
}

void SessionJournals::readmit(const std::string& session) {
  std::lock_guard lock(mutex_);
  retired_.erase(session);
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

common::Result<uint64_t> SessionJournals::append(const proto::PoseCorrectionMsg& correction) {
  return appendTo(correction.session_id, correction);
}

common::Result<uint64_t> SessionJournals::append(const proto::FrameAlignmentMsg& alignment) {
  return appendTo(alignment.session_id, alignment);
}

common::Status SessionJournals::forEachFrame(
    const std::string& session, uint64_t after, uint64_t up_to,
    const std::function<void(const proto::CloudFrameMsg& frame, uint64_t number)>& visit) const {
  // Read beside the appends: a record being written is a torn tail here, and numbered above
  // anything fused (`up_to`). From the open journal's nearest mark: deferred frames are
  // recent, and reading the whole file for them would cost seconds on a long flight, each
  // time fusion falls behind.
  const uint64_t from_offset = offsetBefore(session, after + 1);
  const auto read = visitJournal(
      root_ / session / kJournalName, after + 1,
      [&](JournalRecord&& record, uint64_t number) {
        const auto* frame = std::get_if<proto::CloudFrameMsg>(&record);
        if (frame != nullptr && number <= up_to) visit(*frame, number);
      },
      from_offset);
  if (!read) return read.error();
  return common::Ok{};
}

common::Result<uint64_t> SessionJournals::appendTo(const std::string& session,
                                                   const JournalRecord& record) {
  std::lock_guard lock(mutex_);
  if (retired_.count(session) != 0) {
    return makeError(ErrorCode::kConflict,
                     "session '" + session + "' is being deleted: nothing is recorded for it");
  }
  auto found = journals_.find(session);
  if (found == journals_.end()) {
    auto opened = openJournal(session);
    if (!opened) return opened.error();
    found = journals_.emplace(session, std::move(opened).value()).first;
  }
  const uint64_t offset = found->second->bytes();  // where this record goes
  auto appended = found->second->append(record);
  if (appended) {
    std::lock_guard marks(marks_mutex_);
    auto& kept = marks_[session];
    if (kept.appended++ % kMarkEvery == 0) kept.at.emplace_back(*appended, offset);
  }
  return appended;
}

common::Status SessionJournals::openRecovered(const std::string& session,
                                              const JournalReplay& scanned) {
  std::lock_guard lock(mutex_);
  if (journals_.count(session) != 0 || retired_.count(session) != 0) return common::Ok{};
  auto opened = openJournal(session, &scanned);
  if (!opened) return opened.error();
  journals_.emplace(session, std::move(opened).value());
  return common::Ok{};
}

common::Result<std::unique_ptr<Journal>> SessionJournals::openJournal(
    const std::string& session, const JournalReplay* scanned) {
  const fs::path dir = root_ / session;  // ids are validated: no separators, no ".."
  std::error_code ec;
  if (fs::create_directories(dir, ec); ec) {
    return makeError(ErrorCode::kIo, "cannot create " + dir.string() + ": " + ec.message());
  }
  // The folder's own name is durable only once the store root is flushed (repeated for every
  // open: cheap, and it also covers a folder made by a run that crashed right after).
  if (auto synced = common::syncDirectory(root_); !synced) return synced.error();
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
  forgetMarks(session);  // an upgrade or repair below moves records
  auto opened = Journal::open(dir / kJournalName, first_number, scanned);
  if (!opened && opened.error().code == ErrorCode::kUnavailable && scanned != nullptr) {
    // The file changed since it was read: that reading cannot say where appending goes.
    opened = Journal::open(dir / kJournalName, first_number);
  }
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
