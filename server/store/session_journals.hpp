// The server side of the store's durability: one Journal per session under the store root
// (<root>/<session>/journal.smj, the MapServer's IngestLog; a new session's directory also
// gets meta.json with its resolution) and periodic map snapshots
// (<root>/<session>/snapshot-<journal frames>.ot, the MapServer's SnapshotSink).
// Recovery lives in store_admin.hpp.
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
  // `resolution`: what new sessions are created with (the server's --resolution).
  SessionJournals(std::filesystem::path root, double resolution)
      : root_(std::move(root)), resolution_(resolution) {}
  common::Status append(const proto::CloudFrameMsg& frame) override;
  common::Status append(const proto::PoseMsg& pose) override;
  common::Status append(const proto::SessionEventMsg& event) override;
  // Written atomically (temporary file + rename); older snapshots are then removed.
  void saveSnapshot(const std::string& session, uint64_t journal_frames,
                    const std::string& ot) override;
  // Closes a session's journal file (the session was closed or deleted).
  void release(const std::string& session);

 private:
  common::Status appendTo(const std::string& session, const JournalRecord& record);
  std::filesystem::path root_;
  double resolution_;
  std::mutex mutex_;
  std::map<std::string, std::unique_ptr<Journal>> journals_;
};

// <dir>/snapshot-*.ot, newest (most journal frames) first: (frames, path).
std::vector<std::pair<uint64_t, std::filesystem::path>> snapshotsIn(
    const std::filesystem::path& dir);

// Writes `content` to a temporary file beside `path`, flushes it, and renames it over `path`.
common::Status writeAtomically(const std::filesystem::path& path, const std::string& content);

inline constexpr const char* kJournalName = "journal.smj";
// The size of a session directory's journal (0 when there is none).
uint64_t journalBytes(const std::filesystem::path& session_dir);
inline constexpr const char* kMetaName = "meta.json";

}  // namespace stereomap::store
