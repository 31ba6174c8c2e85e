#include "server/store/session_journals.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cstdio>
#include <fstream>

namespace stereomap::store {

namespace fs = std::filesystem;

uint64_t journalBytes(const fs::path& session_dir) {
  std::error_code ec;
  const auto bytes = fs::file_size(session_dir / kJournalName, ec);
  return ec ? 0 : bytes;
}

std::vector<std::pair<uint64_t, fs::path>> snapshotsIn(const fs::path& dir) {
  std::vector<std::pair<uint64_t, fs::path>> found;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(dir, ec)) {
    const std::string name = entry.path().filename().string();
    if (name.rfind("snapshot-", 0) != 0 || entry.path().extension() != ".ot") continue;
    try {
      found.emplace_back(std::stoull(name.substr(9)), entry.path());
    } catch (const std::exception&) {
    }
  }
  std::sort(found.rbegin(), found.rend());
  return found;
}

common::Status writeAtomically(const fs::path& path, const std::string& content) {
  const fs::path temporary = path.string() + ".tmp";
  {
    std::ofstream out(temporary, std::ios::binary | std::ios::trunc);
    out.write(content.data(), static_cast<std::streamsize>(content.size()));
    out.flush();
    if (!out) return common::makeError(common::ErrorCode::kIo, "cannot write " + temporary.string());
  }
  std::error_code ec;
  fs::rename(temporary, path, ec);
  if (ec) {
    return common::makeError(common::ErrorCode::kIo,
                             "cannot rename to " + path.string() + ": " + ec.message());
  }
  return common::Ok{};
}

void SessionJournals::saveSnapshot(const std::string& session, uint64_t journal_frames,
                                   const std::string& ot) {
  const fs::path dir = root_ / session;
  char name[40];
  std::snprintf(name, sizeof(name), "snapshot-%010llu.ot",
                static_cast<unsigned long long>(journal_frames));
  if (auto written = writeAtomically(dir / name, ot); !written) {
    spdlog::warn("session '{}': snapshot not kept: {}", session, written.error().message);
    return;
  }
  std::error_code ec;
  for (const auto& [frames, older] : snapshotsIn(dir)) {
    if (frames < journal_frames) fs::remove(older, ec);
  }
}

void SessionJournals::release(const std::string& session) {
  std::lock_guard lock(mutex_);
  journals_.erase(session);
}

common::Status SessionJournals::append(const proto::CloudFrameMsg& frame) {
  return appendTo(frame.session_id, frame);
}

common::Status SessionJournals::append(const proto::PoseMsg& pose) {
  return appendTo(pose.session_id, pose);
}

common::Status SessionJournals::append(const proto::SessionEventMsg& event) {
  return appendTo(event.session_id, event);
}

common::Status SessionJournals::appendTo(const std::string& session, const JournalRecord& record) {
  std::lock_guard lock(mutex_);
  auto& journal = journals_[session];
  if (!journal) {
    const fs::path dir = root_ / session;  // ids are validated: no separators, no ".."
    std::error_code ec;
    fs::create_directories(dir, ec);
    if (!fs::exists(dir / kMetaName)) {
      const std::string meta = "{\"resolution\": " + std::to_string(resolution_) + "}\n";
      if (auto written = writeAtomically(dir / kMetaName, meta); !written) return written;
    }
    auto opened = Journal::open(dir / kJournalName);
    if (!opened) {
      journals_.erase(session);
      return opened.error();
    }
    journal = std::move(opened).value();
  }
  return journal->append(record);
}

}  // namespace stereomap::store
