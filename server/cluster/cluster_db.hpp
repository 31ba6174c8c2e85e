// The cluster's shared state in PostgreSQL (stereomap-server --cluster URL): the servers and
// their leases, each session's owner and ownership epoch, and (cluster_journal.hpp) the
// journal and snapshots. Leases are timed by the database's clock, never a server's; the
// epoch is a fencing token: every journal or snapshot write carries it, and a trigger in
// the database refuses one whose epoch is not the session's current one (SQLSTATE SMF01),
// so an owner that was paused or cut off past its lease can commit nothing once another
// server has taken its sessions.
//
// Ownership is per incarnation: each process registers with an incarnation of its own (a
// process started again under the same --server-id takes the id over), and the epoch rises
// each time a process adopts a session, so that no two processes ever write at one epoch.
//
// A server: open() (schema, registration), then renewLease() on a thread of its own several
// times per lease; every poll placeSession() for sessions vehicles announce, takeOrphans()
// for the sessions of servers whose lease ran out, owned() for what it must serve, and
// adopt() before serving one. Every call has a deadline (pg.hpp): a database that hangs makes
// it fail with kUnavailable, never wait.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "common/result.hpp"
#include "server/cluster/pg.hpp"
#include "server/core/session.hpp"

namespace stereomap::cluster {

struct ClusterOptions {
  std::string url;        // libpq URL of the cluster's database
  std::string server_id;  // unique per server process; empty: one is made up
  std::string http;       // where this server's HTTP is reached (host:port), for routing
  std::chrono::milliseconds lease{4000};
  size_t capacity = 256;  // sessions this server can hold (MapServerOptions::max_sessions)
};

// A session as its owner holds it.
struct Ownership {
  std::string session;
  std::string owner;
  int64_t epoch = 0;
  double resolution = 0.1;
  // State 'opened': a stored session loaded read-only (no samples taken, no acknowledgements).
  bool read_only = false;
  bool operator==(const Ownership&) const = default;
};

// A session as the database holds it, whatever its state.
struct SessionRow {
  std::string id;
  std::string state;  // live, ended, opened, closed
  std::string owner;  // "" when none
  std::string http;   // where its owner is reached, when it has a live one
  int64_t epoch = 0;
  double resolution = 0.1;
  std::string summary;  // its status (JSON) when it last left a server's memory; "" if never
  // Its clouds up to this record number keep only their meta (ClusterStore::compact); 0: none.
  uint64_t compacted_up_to = 0;
  // For listings: the summary's counts, this row's state, resolution and server.
  core::SessionStatus status() const;
};
// The SELECT list (and FROM) that sessionRowAt reads; a WHERE or ORDER BY may follow.
extern const char* const kSessionRowSelect;
SessionRow sessionRowAt(const PgResult& rows, int row);

struct ServerInfo {
  std::string id;
  std::string http;
  bool live = false;
  int64_t sessions = 0;  // live sessions it owns
};

class ClusterDb {
 public:
  // Connects, creates the schema when missing (one server at a time), and registers this
  // server with a fresh lease. A URL that cannot be reached or whose credentials are refused
  // is an error naming which.
  static common::Result<std::unique_ptr<ClusterDb>> open(const ClusterOptions& options);

  const std::string& serverId() const { return options_.server_id; }
  const ClusterOptions& options() const { return options_; }

  // Extends this server's lease by options().lease from the database's now (on a connection of
  // its own, so that no other statement delays it). kRenewedAfterExpiry when it had run out
  // (the server was paused or cut off: others may have taken its sessions, and owned() says
  // which are left); kSuperseded when another process registered under this server id since
  // (this one must stop serving: it can adopt nothing, and its writes are fenced);
  // kUnavailable when the database did not answer in time (reconnects at the next call).
  enum class Lease { kRenewed, kRenewedAfterExpiry, kSuperseded };
  common::Result<Lease> renewLease();

  // The owner of session `id`: placed on the least-loaded live server with room when it is
  // new (every server may call this for a session it hears of; one placement wins);
  // kUnavailable when no live server has room (it waits, ownerless, for takeOrphans()).
  common::Result<Ownership> placeSession(const std::string& id, double resolution);
  // What a control round needs to know, in one cheap statement: the cluster's version (raised
  // by every change of owners, epochs, states or servers; a round with the same version as
  // the last has nothing to read again) and whether any live session waits for an owner (its
  // server's lease ran out, or it has none): only then is takeOrphans() worth its scan.
  struct Round {
    int64_t version = 0;
    bool orphans = false;
  };
  common::Result<Round> poll();
  // Statements this server has sent on its control and lease connections (for /metrics).
  uint64_t statements() const;
  // The live sessions this server owns now.
  common::Result<std::vector<Ownership>> owned();
  // Makes a session owned() by this server this process's to write, at an epoch raised by
  // one; kConflict when it is not (another owner, another incarnation, or the lease ran out).
  // What the database holds of the session must be read after this, never before.
  common::Result<Ownership> adopt(const Ownership& session);
  // This process's incarnation (unique per process).
  const std::string& incarnation() const { return incarnation_; }
  // Takes live sessions whose owner's lease ran out, or that have no owner (its fair share of
  // them when several servers are live, never past its capacity), each with its epoch raised
  // by one.
  common::Result<std::vector<Ownership>> takeOrphans();
  // The owner of session `id` (nullopt: no such session, or closed).
  common::Result<std::optional<Ownership>> ownerOf(const std::string& id);
  common::Result<std::vector<ServerInfo>> servers();
  // Every live session with a live owner: the session, its owner's id and HTTP address.
  struct Placement {
    Ownership ownership;
    std::string http;
  };
  common::Result<std::vector<Placement>> directory();
  // The sessions in no server's memory (ended or closed), for listings.
  // A session's state (live, ended, opened, closed), or "" when there is no such session.
  common::Result<std::string> sessionState(const std::string& id);
  common::Result<std::vector<SessionRow>> outOfMemory();
  // Gives up a session this server owns: handed back (its server stopping, or unable to hold
  // it: live, for another to take), ended (its vehicles ended it or fell silent: out of
  // memory until a vehicle announces it again) or closed (by an operator); `summary` (its
  // status as JSON) is kept for listings. Refused (kConflict) when the epoch is stale.
  enum class Leaving { kHandBack, kEnded, kClosed };
  common::Status release(const Ownership& session, Leaving how, const std::string& summary = "");
  // Leaves the cluster: the lease ends now, so that others take the sessions at once (unless
  // another process has taken this server id over).
  common::Status leave();

 private:
  ClusterDb(ClusterOptions options, std::unique_ptr<PgConnection> db,
            std::unique_ptr<PgConnection> lease);
  static PgOptions controlOptions();
  static PgOptions leaseOptions(std::chrono::milliseconds lease);
  common::Status registerServer();
  // Runs one statement on db_, reconnecting once when the connection had been lost.
  common::Result<PgResult> exec(std::string_view sql, const std::vector<PgParam>& params);
  static common::Result<PgResult> execOn(PgConnection& db, std::string_view sql,
                                         const std::vector<PgParam>& params);
  ClusterOptions options_;
  std::string incarnation_;
  std::mutex mutex_;  // one statement at a time on db_
  std::unique_ptr<PgConnection> db_;
  std::mutex lease_mutex_;  // the lease's own connection
  std::unique_ptr<PgConnection> lease_db_;
};

// Makes a map (OctoMap's full format) a new live session of the cluster: its snapshot of
// label 0 and no journal; the least-loaded live server takes it within a round of its
// control loop (an orphan: no owner yet). kConflict when the session exists. One
// transaction: a failure leaves nothing.
// A new session's summary when something other than a flight made it: a status JSON that
// holds only its id and `origin` (SessionStatus::origin). "" when `origin` is.
std::string originSummary(const std::string& id, const std::string& origin);

// `origin` (SessionStatus::origin, "" for none) is kept in its summary: a diff's description.
common::Status importSession(PgConnection& db, const std::string& id, double resolution,
                             const std::string& ot, const std::string& origin = "");

// Brings the cluster's schema to this build's version: nothing (no lock, no statement that
// changes a table) when it is there already; otherwise, under an advisory lock that
// serialises servers, each newer version's statements once, in one transaction. kConflict
// when the database's version is newer than this build's.
common::Status migrateSchema(PgConnection& db);
int latestSchemaVersion();

}  // namespace stereomap::cluster
