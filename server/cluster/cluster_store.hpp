// Operators' work on the sessions a cluster's database holds, from any server (the REST API,
// cluster_admin.hpp) or offline (stereomap-store --cluster): listings, closing, opening,
// deleting, merging, replaying and checking. Each change is one transaction; a session's
// owner learns of it through the epoch (its writes are fenced) and its next control round.
//
// States (cluster_db.cpp, schema version 4): live (owned, taking samples), ended (its vehicles
// ended it; out of memory until one announces it again), opened (loaded read-only by one
// server), closed (by an operator: its samples are refused).
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "common/result.hpp"
#include "server/cluster/cluster_db.hpp"
#include "server/cluster/cluster_journal.hpp"
#include "server/cluster/pg.hpp"
#include "server/core/map_server.hpp"
#include "server/core/session_admin.hpp"

namespace stereomap::cluster {

class ClusterStore {
 public:
  // `journal` reads the records (a server's own, or one the tool opened); it outlives this.
  static common::Result<std::unique_ptr<ClusterStore>> open(const std::string& url,
                                                            ClusterJournal& journal);

  // Every session, by id.
  common::Result<std::vector<SessionRow>> sessions();
  // kNotFound when there is no such session.
  common::Result<SessionRow> session(const std::string& id);
  // Closes a session that is not closed: no owner, its samples refused, its owner (if any)
  // fenced. kNotFound, or kConflict when it is closed already.
  common::Status close(const std::string& id);
  // A closed or ended session, opened read-only by server `server_id` (which then serves it).
  // kNotFound, or kConflict when it is live or opened already.
  common::Result<Ownership> open(const std::string& id, const std::string& server_id);
  // Deletes a session that is not live, its journal and snapshots. kNotFound, or kConflict
  // when it is live (close it first).
  common::Status remove(const std::string& id);
  // A new, closed session whose journal holds both sessions' records (store/replay.hpp,
  // MergedRecords), written in one transaction: a failure leaves nothing.
  common::Status merge(const core::MergeRequest& request);
  // The session as it was at `until_ns` (store/replay.hpp, replayUntil).
  common::Result<std::shared_ptr<core::Session>> replay(const std::string& id, int64_t until_ns);
  // The session as the database holds it, loaded read-only into `server` (its newest
  // snapshot, then the journal after it) and fused.
  common::Result<std::shared_ptr<core::Session>> load(const std::string& id,
                                                      core::MapServer& server);

  // Compacts a closed session's journal below its newest snapshot: each cloud there keeps only
  // its meta (pose, stamp, counts; not its points), every pose, event and correction stays (the
  // trajectory is whole), and older snapshots go. PostgreSQL reuses the space after its next
  // (auto)vacuum. Opening the session still works (from the snapshot); a replay cannot go back
  // before the snapshot, a merge refuses it, and its MCAP has no points for those clouds.
  // kConflict unless it is closed (a live or ended session may yet be corrected, which fuses
  // every frame again); kInvalidArgument without a snapshot that covers its corrections.
  struct Compaction {
    uint64_t up_to = 0;                          // the snapshot's record number
    uint64_t clouds = 0;                         // clouds compacted now
    uint64_t bytes_before = 0, bytes_after = 0;  // the journal's records
  };
  common::Result<Compaction> compact(const std::string& id);

  // Every record and snapshot of every session read and decoded.
  struct Check {
    size_t sessions = 0;
    uint64_t records = 0, unreadable = 0;
    size_t snapshots = 0, bad_snapshots = 0;
    std::vector<std::string> problems;  // one line per damaged session
  };
  common::Result<Check> check();

 private:
  ClusterStore(std::unique_ptr<PgConnection> db, ClusterJournal& journal)
      : db_(std::move(db)), journal_(journal) {}
  // One statement, reconnecting once when the connection had been lost.
  common::Result<PgResult> exec(std::string_view sql, const std::vector<PgParam>& params = {});
  // Writes the records of `first` then `second`, moved into `into`, inside the open transaction.
  common::Status writeMerged(const core::MergeRequest& request);
  common::Result<Compaction> compactInTransaction(const std::string& id);
  // The session as it was at `until_ns`, from its snapshot on (a compacted session).
  common::Result<std::shared_ptr<core::Session>> replayCompacted(const SessionRow& row,
                                                                 int64_t until_ns);

  std::unique_ptr<PgConnection> db_;
  ClusterJournal& journal_;
};

}  // namespace stereomap::cluster
