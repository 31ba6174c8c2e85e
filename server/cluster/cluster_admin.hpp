// The cluster's side of session management for the API (core::SessionAdmin): where each
// session is served (the proxy's route lookups) and the sessions other servers serve (for
// listings), as the control loop last read them (refresh(), every round: the HTTP thread
// never waits on the database, and route lookups cost it nothing however many requests
// come). Operators' open, close, delete, merge and replay are not offered in a cluster yet
// (503).
#pragma once

#include <mutex>
#include <string>
#include <vector>

#include "server/cluster/cluster_db.hpp"
#include "server/core/session_admin.hpp"

namespace stereomap::cluster {

class ClusterAdmin : public core::SessionAdmin {
 public:
  // Answers nothing of the cluster until attach(): the server's HTTP port must be bound (and
  // known) before it can join the cluster, and the HTTP server takes its admin when made.
  ClusterAdmin() = default;
  // The cluster's database and this server's address; before the HTTP server starts.
  void attach(ClusterDb& db, std::string self);

  std::vector<core::SessionStatus> closedSessions() const override { return {}; }
  common::Status open(const std::string& id) override;
  common::Status close(const std::string& id) override;
  common::Status remove(const std::string& id) override;
  common::Status merge(const core::MergeRequest& request) override;
  common::Result<std::shared_ptr<core::Session>> replay(const std::string& id,
                                                        int64_t until_ns) const override;
  std::vector<core::SessionStatus> remoteSessions() const override;
  std::optional<std::string> routeTo(const std::string& id) const override;
  std::optional<std::string> selfAddress() const override;
  // Reads the directory again (kept as it was when the database cannot be reached).
  void refresh();

 private:
  std::vector<ClusterDb::Placement> placements() const;
  mutable std::mutex mutex_;
  ClusterDb* db_ = nullptr;  // under mutex_, as self_
  std::string self_;
  std::vector<ClusterDb::Placement> placements_;
};

}  // namespace stereomap::cluster
