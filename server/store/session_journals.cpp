#include "server/store/session_journals.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cstdio>
#include <fstream>

namespace stereomap::store {

namespace fs = std::filesystem;

namespace {
constexpr const char* kJournalName = "journal.smj";

// Snapshots of a session directory, newest (most frames) first: (frames, path).
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
}  // namespace

void SessionJournals::saveSnapshot(const std::string& session, uint64_t frames_fused,
                                   const std::string& ot) {
  const fs::path dir = root_ / session;
  char name[40];
  std::snprintf(name, sizeof(name), "snapshot-%010llu.ot",
                static_cast<unsigned long long>(frames_fused));
  const fs::path path = dir / name, temporary = dir / (std::string(name) + ".tmp");
  {
    std::ofstream out(temporary, std::ios::binary | std::ios::trunc);
    out.write(ot.data(), static_cast<std::streamsize>(ot.size()));
    if (!out.flush()) {
      spdlog::warn("session '{}': cannot write snapshot {}", session, temporary.string());
      return;
    }
  }
  std::error_code ec;
  fs::rename(temporary, path, ec);
  if (ec) {
    spdlog::warn("session '{}': cannot keep snapshot {}: {}", session, path.string(), ec.message());
    return;
  }
  for (const auto& [frames, older] : snapshotsIn(dir)) {
    if (frames < frames_fused) fs::remove(older, ec);
  }
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
    auto opened = Journal::open(dir / kJournalName);
    if (!opened) {
      journals_.erase(session);
      return opened.error();
    }
    journal = std::move(opened).value();
  }
  return journal->append(record);
}

std::vector<RecoveredSession> recoverSessions(const fs::path& root, core::MapServer& server) {
  std::vector<RecoveredSession> recovered;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(root, ec)) {
    const fs::path journal = entry.path() / kJournalName;
    if (!entry.is_directory() || !fs::exists(journal)) continue;
    auto replay = readJournal(journal);
    RecoveredSession session{entry.path().filename().string()};
    if (!replay) {
      session.problem = replay.error().message;
      recovered.push_back(std::move(session));
      continue;
    }
    session.problem = replay->problem;
    // The newest snapshot that loads and that the journal covers; else a full replay.
    size_t journal_frames = 0;
    for (const auto& record : replay->records) {
      journal_frames += std::holds_alternative<proto::CloudFrameMsg>(record);
    }
    for (const auto& [frames, path] : snapshotsIn(entry.path())) {
      if (frames > journal_frames) continue;  // newer than the intact journal: not usable
      std::ifstream ot(path, std::ios::binary);
      if (auto restored = server.restoreSession(session.id, ot, frames); restored) {
        session.snapshot_frames = frames;
        break;
      } else {
        session.problem += (session.problem.empty() ? "" : "; ") + path.filename().string() +
                           " unusable (" + restored.error().message + ")";
      }
    }
    size_t cloud_index = 0;
    for (const auto& record : replay->records) {
      if (const auto* frame = std::get_if<proto::CloudFrameMsg>(&record)) {
        const bool covered = cloud_index++ < session.snapshot_frames;
        session.frames +=
            server.ingest(*frame, covered ? core::Origin::kCovered : core::Origin::kReplay);
      } else if (const auto* pose = std::get_if<proto::PoseMsg>(&record)) {
        session.poses += server.ingest(*pose, core::Origin::kReplay);
      } else {
        server.ingest(std::get<proto::SessionEventMsg>(record), core::Origin::kReplay);
      }
    }
    if (auto live = server.find(session.id)) live->waitUntilIdle();
    recovered.push_back(std::move(session));
  }
  return recovered;
}

}  // namespace stereomap::store
