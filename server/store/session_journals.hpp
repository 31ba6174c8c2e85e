// The server side of the store's durability: one Journal per session under the store root
// (<root>/<session>/journal.smj, the MapServer's IngestLog), periodic map snapshots
// (<root>/<session>/snapshot-<frames>.ot, the MapServer's SnapshotSink), and recovery at
// start-up: the newest loadable snapshot, then the journal's frames after it (a damaged
// journal tail is cut with a warning, everything before it kept).
#pragma once

#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <string>

#include "server/core/map_server.hpp"
#include "server/store/journal.hpp"

namespace stereomap::store {

class SessionJournals : public core::IngestLog, public core::SnapshotSink {
 public:
  explicit SessionJournals(std::filesystem::path root) : root_(std::move(root)) {}
  common::Status append(const proto::CloudFrameMsg& frame) override;
  common::Status append(const proto::PoseMsg& pose) override;
  common::Status append(const proto::SessionEventMsg& event) override;
  // Written atomically (temporary file + rename); older snapshots are then removed.
  void saveSnapshot(const std::string& session, uint64_t frames_fused,
                    const std::string& ot) override;

 private:
  common::Status appendTo(const std::string& session, const JournalRecord& record);
  std::filesystem::path root_;
  std::mutex mutex_;
  std::map<std::string, std::unique_ptr<Journal>> journals_;
};

struct RecoveredSession {
  std::string id;
  size_t frames = 0, poses = 0;
  uint64_t snapshot_frames = 0;  // frames restored from a snapshot rather than replayed
  std::string problem;           // what was cut or could not be used, if anything
};

// Replays every <root>/*/journal.smj into `server` (Origin::kReplay) and waits until the
// replayed frames are fused.
std::vector<RecoveredSession> recoverSessions(const std::filesystem::path& root,
                                              core::MapServer& server);

}  // namespace stereomap::store
