// The cluster's side of session management for the API (core::SessionAdmin): where each
// session is served (the proxy's route lookups), the sessions other servers serve and those
// in no server's memory (for listings), as the control loop last read them (refresh(), in
// its rounds: the HTTP thread never waits on the database for a listing or a route, however
// many requests come); and operators' open, close, delete, merge and replay, each against the
// database (cluster_store.hpp) and this server's node.
//
// Requests reach the server that serves a session (the proxy routes by session), so closing
// a live session is normally its owner's: it stops taking samples, snapshots the map and
// lets it go. Any other server closes it in the database, which fences the owner. Opening
// loads a stored session read-only on the server that was asked (the directory then routes
// its tiles there).
#pragma once

#include <mutex>
#include <string>
#include <vector>

#include "server/cluster/cluster_db.hpp"
#include "server/cluster/cluster_store.hpp"
#include "server/core/session_admin.hpp"

namespace stereomap::cluster {

class ClusterNode;

class ClusterAdmin : public core::SessionAdmin {
 public:
  // Answers nothing of the cluster until attach(): the server's HTTP port must be bound (and
  // known) before it can join the cluster, and the HTTP server takes its admin when made.
  ClusterAdmin() = default;
  // The cluster's database and this server's address; before the HTTP server starts.
  void attach(ClusterDb& db, std::string self, ClusterStore& store);
  // The node that serves this server's sessions, once started (operators' changes need it).
  void serveWith(ClusterNode* node);

  std::vector<core::SessionStatus> closedSessions() const override;
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
  struct Parts {
    ClusterDb* db = nullptr;
    ClusterStore* store = nullptr;
    ClusterNode* node = nullptr;
  };
  // What operators' changes need, or kUnavailable before the server has joined the cluster.
  common::Result<Parts> parts() const;
  std::vector<ClusterDb::Placement> placements() const;
  mutable std::mutex mutex_;
  ClusterDb* db_ = nullptr;  // under mutex_, as the rest
  ClusterStore* store_ = nullptr;
  ClusterNode* node_ = nullptr;
  std::string self_;
  std::vector<ClusterDb::Placement> placements_;
  std::vector<core::SessionStatus> out_of_memory_;
  // The store's connection is one: operators' changes take turns (a listing never waits).
  mutable std::mutex store_mutex_;
};

}  // namespace stereomap::cluster
