// A server's part in the cluster (stereomap-server --cluster URL): it keeps its lease, places
// the sessions vehicles announce, takes the sessions of servers whose lease ran out, and
// serves the sessions it owns: each recovered from the database (newest snapshot, then the
// journal after it), read from DDS in its own partition (sm.<session>) and acknowledged from
// there, so that only the owner takes a session's samples and only the owner tells a
// vehicle what is committed. A session it loses (fenced by the database, or found owned by
// another) is unloaded: its readers, acknowledgements and map go.
//
// Sessions end: one whose vehicles ended it and fell quiet is retired (snapshotted, 'ended'
// in the database, out of memory) and served again, by whichever server has room, when a
// vehicle announces it again. An operator's open serves a stored session read-only ('opened').
//
// Threads: the lease (renewed several times per lease on a connection of its own, never
// behind recovery or a slow query; it also says whether the database answers, for /healthz),
// the control loop (every `poll`), the recoveries (a few, side by side: a session is adopted,
// read and replayed there, or retired), the session events of every session (one wildcard reader:
// they announce new sessions), the acknowledgements, and each owned session's readers
// (ingest::DdsIngest).
//
// A process that finds its server id taken over by a newer process (started again while this
// one was paused or cut off) is superseded: it unloads every session at once, without
// releasing any, and calls on_superseded (the server then exits).
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "proto/dds.hpp"
#include "server/cluster/cluster_admin.hpp"
#include "server/cluster/cluster_db.hpp"
#include "server/cluster/cluster_journal.hpp"
#include "server/core/map_server.hpp"
#include "server/ingest/ack_router.hpp"
#include "server/ingest/dds_ingest.hpp"

namespace stereomap::cluster {

struct ClusterNodeOptions {
  std::chrono::milliseconds poll{250};  // how often ownership is looked at
  // Sessions recovered side by side (each on a database connection of its own while it is),
  // off the control loop: a server taking many sessions takes them in parallel.
  int recovery_threads = 4;
  double default_resolution = 0.1;  // for sessions announced without a hint
  // A session its vehicles ended (their end event, or silence past --vehicle-timeout) leaves
  // memory once no sample came for this long: its last acknowledgements have gone out by
  // then. It is 'ended' in the database, and served again when a vehicle announces it.
  std::chrono::milliseconds retire_after{10000};
  ClusterAdmin* admin = nullptr;        // refreshed every round (the API's directory)
  std::function<void()> on_superseded;  // from the lease thread, once
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
  // True once another process took this server id over.
  bool superseded() const;

  // Serves a session the database says this server owns now (an operator's open), on the
  // caller's thread; Ok once it is loaded (at once when it is already).
  common::Status serveNow(const Ownership& session);
  // Takes a session served here out of memory and out of this server's hands: its readers
  // stop, its map is snapshotted (live sessions) and its last status kept for listings; `how`
  // is ended or closed. kNotFound when it is not served here.
  common::Status retire(const std::string& session, ClusterDb::Leaving how);
  // Stops serving a session that is no longer this server's (deleted), at once rather than at
  // the next round.
  void drop(const std::string& session, const std::string& why) { unserve(session, why); }

 private:
  struct Served {
    int64_t epoch = 0;
    double resolution = 0.1;
    bool read_only = false;  // opened: no readers, no acknowledgements
    std::unique_ptr<ingest::DdsIngest> ingest;
  };
  ClusterNode(const ClusterNodeOptions& options, ClusterDb& db, ClusterJournal& journal,
              core::MapServer& server, std::shared_ptr<proto::Participant> participant);
  void controlLoop();
  void leaseLoop();
  void recoveryLoop();
  // Unloads every session: another process has this server id now.
  void stepDown();
  void eventLoop();
  // One round: the lease, placements, takeovers, and what this server owns now.
  void reconcile();
  void noteRoundFailed(const std::string& why);
  // The commit latencies and counts, and the sessions served, into the server's /metrics.
  void publishMetrics();
  void serve(const Ownership& session);
  // Tells the vehicles that announced `session` (announcers_ taken for it) that it takes no
  // samples: MapServer::answerClosed, sent with the acknowledgements.
  void answerClosed(const std::string& session,
                    const std::set<std::pair<std::string, uint64_t>>& announcers,
                    const std::string& reason);
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
  std::map<std::string, Served> served_;     // under mutex_
  std::map<std::string, double> announced_;  // sessions heard of, to place: resolution
  // Who announced them (vehicle, stream), to answer when a session is closed or read-only:
  // at most kMaxAnnouncers per session.
  std::map<std::string, std::set<std::pair<std::string, uint64_t>>> announcers_;
  static constexpr size_t kMaxAnnouncers = 64;
  // The acknowledgements thread's alone: those of the sessions served here, and the answers
  // of sessions no server reads (AckStatus::kSessionClosed).
  ingest::AckRouter acks_;
  std::map<std::string, std::string> fenced_;  // sessions the database fenced: why
  bool database_down_ = false;                 // under mutex_: the lease could not be renewed
  bool superseded_ = false;                    // under mutex_
  // Orphans are taken only after this: once a lease renewed late (the database hung, or this
  // server was paused), every server's lease looks run out for a moment; the others get a
  // whole lease to renew theirs before their sessions count as orphans.
  std::chrono::steady_clock::time_point take_orphans_after_{};  // under mutex_
  // The control thread's: the cluster's version when owned() was last read, and when the next
  // round reads everything whatever the version says.
  int64_t seen_version_ = -1;
  uint64_t round_failures_ = 0;      // in a row
  std::atomic<bool> reread_{false};  // a recovery failed: the next round reads owners again
  std::chrono::steady_clock::time_point next_full_round_{};

  // The sessions whose vehicles ended them and fell quiet: retired on a recovery thread.
  void queueRetirements();

  std::deque<Ownership> to_recover_;   // under mutex_: owned, to be served
  std::deque<std::string> to_retire_;  // under mutex_: ended, to leave memory
  std::set<std::string> recovering_;   // under mutex_: queued or being recovered or retired
  std::condition_variable recover_wake_;

  std::thread control_, lease_thread_, events_thread_, acks_thread_;
  std::vector<std::thread> recoverers_;
};

}  // namespace stereomap::cluster
