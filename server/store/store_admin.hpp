// Session management over the store, for stereomap-server (REST) and stereomap-store
// (offline): start-up recovery (every session that is not closed is loaded: its newest
// usable snapshot, then the journal after it, at the session's own resolution), opening a
// stored session read-only, closing, deleting and merging sessions, and the SQLite catalog.
//
// One writer per store: a writable StoreAdmin holds an exclusive lock on <root>/store.lock
// for its lifetime, so a second server or an offline delete cannot run beside a server.
// A read-only StoreAdmin takes no lock and never writes (exports beside a running server).
#pragma once

#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "server/core/map_server.hpp"
#include "server/core/session_admin.hpp"
#include "server/store/catalog.hpp"
#include "server/store/map_import.hpp"
#include "server/store/session_journals.hpp"
#include "server/store/store.hpp"

namespace stereomap::store {

struct RecoveredSession {
  std::string id;
  size_t frames = 0, poses = 0;
  uint64_t snapshot_frames = 0;  // frames restored from a snapshot rather than replayed
  uint64_t lost_records = 0;     // records the journal's damage cost
  double seconds = 0;            // how long recovering it took
  std::string problem;           // what was damaged, cut or could not be used, if anything
};

struct StoreAdminOptions {
  double default_resolution = 0.1;  // for a session directory without meta.json
  bool writable = true;
};

class StoreAdmin : public core::SessionAdmin {
 public:
  // `journals` (the server's IngestLog/SnapshotSink) is required when writable.
  static common::Result<std::unique_ptr<StoreAdmin>> create(const std::filesystem::path& root,
                                                            core::MapServer& server,
                                                            SessionJournals* journals,
                                                            const StoreAdminOptions& options);
  ~StoreAdmin() override;

  // Loads every stored session that is not closed into the server (waits until fused) and
  // marks the closed ones, whose samples the server then refuses.
  std::vector<RecoveredSession> recoverAll();
  // Saves the map, trajectory and session.json of every loaded session that changed since
  // (ended and idle ones only, unless `all`: at shutdown), and updates the catalog rows.
  // Writable only. Without `all` it returns at once while another operation is under way.
  void checkpoint(bool all);
  // Set when the catalog was damaged and has been rebuilt.
  const std::string& catalogWarning() const { return catalog_warning_; }
  // Ids of every session on disk (those with a journal), sorted.
  std::vector<std::string> storedIds() const;
  // Their statuses as last saved (session.json; counts are zero for a session never saved).
  std::vector<core::SessionStatus> savedSessions() const;
  const std::filesystem::path& root() const { return root_; }

  std::vector<core::SessionStatus> closedSessions() const override;
  // Whether the store holds session `id` closed (its session.json says so).
  bool isClosedOnDisk(const std::string& id) const;
  common::Status open(const std::string& id) override;
  common::Status close(const std::string& id) override;
  common::Status remove(const std::string& id) override;
  common::Result<std::shared_ptr<core::Session>> replay(const std::string& id,
                                                        int64_t until_ns) const override;
  common::Status merge(const core::MergeRequest& request) override;
  // Makes an OctoMap file (.bt or .ot, checked whole before anything is written) a closed
  // session `id` of the store at the file's resolution, with no trajectory; it is left
  // opened read-only. Writable only.
  common::Result<RecoveredSession> importMap(const std::filesystem::path& file,
                                             const std::string& id);
  // The same for a map already read and checked (a diff's); `about` (a JSON object) is kept
  // in the session's meta.json beside its resolution.
  common::Result<RecoveredSession> importMap(const ImportableMap& map, const std::string& id,
                                             const nlohmann::json& about);

 private:
  StoreAdmin(std::filesystem::path root, core::MapServer& server, SessionJournals* journals,
             const StoreAdminOptions& options)
      : root_(std::move(root)), server_(server), journals_(journals), options_(options) {}
  common::Result<RecoveredSession> load(const std::string& id, bool read_only);
  common::Status closeLocked(const std::string& id);
  common::Status requireWritable(const char* what) const;
  // Why session `id` cannot be imported (not writable, a bad id, taken), or Ok.
  common::Status refuseImport(const std::string& id) const;
  void openCatalog();  // catalog_ stays null (and catalog_warning_ says why) when it cannot
  void record(const core::SessionStatus& status);
  // A session's status as last saved on disk.
  core::SessionStatus savedStatus(const std::string& id) const;
  // The closed sessions' statuses, kept in memory for listings (closedSessions() is asked on
  // every REST and viewer listing; it must not read files, nor wait behind a long merge).
  void rememberClosed(const core::SessionStatus& status);
  void forgetClosed(const std::string& id);

  std::filesystem::path root_;
  core::MapServer& server_;
  SessionJournals* journals_;
  StoreAdminOptions options_;
  std::optional<SessionStore> files_;  // writable only
  std::unique_ptr<Catalog> catalog_;   // writable only
  std::string catalog_warning_;
  int lock_fd_ = -1;
  std::map<std::string, uint64_t> saved_versions_;
  std::map<std::string, std::string> save_errors_;     // last logged failure, per session
  std::string catalog_error_;                          // the last one logged
  mutable std::mutex mutex_;                           // one operation at a time
  std::map<std::string, core::SessionStatus> closed_;  // writable only; see rememberClosed
  mutable std::mutex closed_mutex_;                    // guards closed_ alone
};

}  // namespace stereomap::store
