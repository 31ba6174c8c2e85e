// The server side of the journal: one Journal per session under the store root
// (<root>/<session>/journal.smj), used as the MapServer's IngestLog, and recovery at start-up:
// every session's intact journal is replayed into the MapServer (a damaged tail is cut with a
// warning, everything before it kept).
#pragma once

#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <string>

#include "server/core/map_server.hpp"
#include "server/store/journal.hpp"

namespace stereomap::store {

class SessionJournals : public core::IngestLog {
 public:
  explicit SessionJournals(std::filesystem::path root) : root_(std::move(root)) {}
  common::Status append(const proto::CloudFrameMsg& frame) override;
  common::Status append(const proto::PoseMsg& pose) override;

 private:
  common::Status appendTo(const std::string& session, const JournalRecord& record);
  std::filesystem::path root_;
  std::mutex mutex_;
  std::map<std::string, std::unique_ptr<Journal>> journals_;
};

struct RecoveredSession {
  std::string id;
  size_t frames = 0, poses = 0;
  std::string problem;  // what was cut from the journal's tail, if anything
};

// Replays every <root>/*/journal.smj into `server` (Origin::kReplay) and waits until the
// replayed frames are fused.
std::vector<RecoveredSession> recoverSessions(const std::filesystem::path& root,
                                              core::MapServer& server);

}  // namespace stereomap::store
