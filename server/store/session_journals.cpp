#include "server/store/session_journals.hpp"

namespace stereomap::store {

namespace fs = std::filesystem;

namespace {
constexpr const char* kJournalName = "journal.smj";
}

common::Status SessionJournals::append(const proto::CloudFrameMsg& frame) {
  return appendTo(frame.session_id, frame);
}

common::Status SessionJournals::append(const proto::PoseMsg& pose) {
  return appendTo(pose.session_id, pose);
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
    for (const auto& record : replay->records) {
      if (const auto* frame = std::get_if<proto::CloudFrameMsg>(&record)) {
        session.frames += server.ingest(*frame, core::Origin::kReplay);
      } else {
        session.poses += server.ingest(std::get<proto::PoseMsg>(record), core::Origin::kReplay);
      }
    }
    if (auto live = server.find(session.id)) live->waitUntilIdle();
    recovered.push_back(std::move(session));
  }
  return recovered;
}

}  // namespace stereomap::store
