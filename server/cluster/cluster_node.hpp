// A server's part in the cluster (stereomap-server --cluster URL): it keeps its lease, places
// the sessions vehicles announce, takes the sessions of servers whose lease ran out, and
// serves the sessions it owns: each recovered from the database (newest snapshot, then the
// journal after it), read from DDS in its own partition (sm.<session>) and acknowledged from
// there, so that only the owner takes a session's samples and only the owner tells a
// vehicle what is committed. A session it loses (fenced by the database, or found owned by
// another) is unloaded: its readers, acknowledgements and map go.
//
// Threads: the control loop (every `poll`), the session events of every session (one
// wildcard reader: they announce new sessions), the acknowledgements, and each owned
// session's readers (ingest::DdsIngest).
#pragma once

#include <chrono>
#include <condition_variable>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>

#include "proto/dds.hpp"
#include "server/cluster/cluster_admin.hpp"
#include "server/cluster/cluster_db.hpp"
#include "server/cluster/cluster_journal.hpp"
#include "server/core/map_server.hpp"
#include "server/ingest/dds_ingest.hpp"

namespace stereomap::cluster {

struct ClusterNodeOptions {
  std::chrono::milliseconds poll{250};  // how often ownership is looked at
  double default_resolution = 0.1;      // for sessions announced without a hint
  ClusterAdmin* admin = nullptr;        // refreshed every round (the API's directory)
};

class ClusterNode {
 public:
  // Starts the threads; `db`, `journal`, `server` and `participant` outlive the node.
  static common::Result<std::unique_ptr<ClusterNode>> start(
      const ClusterNodeOptions& options, ClusterDb& db, ClusterJournal& journal,
      core::MapServer& server, const std::shared_ptr<proto::Participant>& participant);
  ~ClusterNode();  // stop()
  ClusterNode(const ClusterNode&) = delete;
  ClusterNode& operator=(const ClusterNode&) = delete;

  // Stops taking samples, gives every owned session back to the cluster (so that others
  // take them at once rather than after the lease) and leaves it.
  void stop();
  // The sessions served now, with their epochs.
  std::map<std::string, int64_t> served() const;

 private:
  struct Served {
    int64_t epoch = 0;
    std::unique_ptr<ingest::DdsIngest> ingest;
    std::unique_ptr<proto::Writer<proto::AckMsg>> acks;
  };
  ClusterNode(const ClusterNodeOptions& options, ClusterDb& db, ClusterJournal& journal,
              core::MapServer& server, std::shared_ptr<proto::Participant> participant);
  void controlLoop();
  void eventLoop();
  // One round: the lease, placements, takeovers, and what this server owns now.
  void reconcile();
  // The commit latencies and counts, and the sessions served, into the server's /metrics.
  void publishMetrics();
  void serve(const Ownership& session);
  void unserve(const std::string& session, const std::string& why);
  bool sleepFor(std::chrono::milliseconds period);  // false when stopping

  ClusterNodeOptions options_;
  ClusterDb& db_;
  ClusterJournal& journal_;
  core::MapServer& server_;
  std::shared_ptr<proto::Participant> participant_;
  std::unique_ptr<proto::Reader<proto::SessionEventMsg>> events_;

  mutable std::mutex mutex_;
  std::condition_variable wake_;
  bool stopping_ = false;
  std::map<std::string, Served> served_;       // under mutex_
  std::map<std::string, double> announced_;    // sessions heard of, to place: resolution
  std::map<std::string, std::string> fenced_;  // sessions the database fenced: why
  std::chrono::steady_clock::time_point last_renewal_{};
  bool database_down_ = false;  // said once per outage

  std::thread control_, events_thread_, acks_thread_;
};

}  // namespace stereomap::cluster
