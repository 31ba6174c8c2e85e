// The cluster's shared state in PostgreSQL (stereomap-server --cluster URL): the servers and
// their leases, each session's owner and ownership epoch, and (cluster_journal.hpp) the
// journal and snapshots. Leases are timed by the database's clock, never a server's; the
// epoch is a fencing token: every journal or snapshot write carries it, and a trigger in
// the database refuses one whose epoch is not the session's current one (SQLSTATE SMF01),
// so an owner that was paused or cut off past its lease can commit nothing once another
// server has taken its sessions.
//
// A server: open() (schema, registration), then every second renewLease(); every poll
// placeSession() for sessions vehicles announce, owned() for what it must serve, and
// takeOrphans() for the sessions of servers whose lease ran out.
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

namespace stereomap::cluster {

struct ClusterOptions {
  std::string url;        // libpq URL of the cluster's database
  std::string server_id;  // unique per server process; empty: one is made up
  std::string http;       // where this server's HTTP is reached (host:port), for routing
  std::chrono::milliseconds lease{4000};
};

// A session as its owner holds it.
struct Ownership {
  std::string session;
  std::string owner;
  int64_t epoch = 0;
  double resolution = 0.1;
  bool operator==(const Ownership&) const = default;
};

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

  // Extends this server's lease by options().lease from the database's now. kConflict when
  // it had already run out (the server was paused or cut off: others may have taken its
  // sessions; it registers again, and must check owned() before writing anything);
  // kUnavailable when the database cannot be reached (reconnects at the next call).
  common::Status renewLease();

  // The owner of session `id`: placed on the least-loaded live server when it is new
  // (every server may call this for a session it hears of; one placement wins).
  common::Result<Ownership> placeSession(const std::string& id, double resolution);
  // The live sessions this server owns now.
  common::Result<std::vector<Ownership>> owned();
  // Takes live sessions whose owner's lease ran out (its fair share of them when several
  // servers are live), each with its epoch raised by one.
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
  // Gives up a session this server owns (closed, or its server stopping): no owner until
  // another takes it; refused (kConflict) when the epoch is stale.
  common::Status release(const Ownership& session, bool closed);
  // Leaves the cluster: the lease ends now, so that others take the sessions at once.
  common::Status leave();

 private:
  explicit ClusterDb(ClusterOptions options, std::unique_ptr<PgConnection> db);
  common::Status registerServer();
  // Runs one statement, reconnecting once when the connection had been lost.
  common::Result<PgResult> exec(std::string_view sql, const std::vector<PgParam>& params);
  ClusterOptions options_;
  std::mutex mutex_;  // one statement at a time on db_
  std::unique_ptr<PgConnection> db_;
};

// Makes a map (OctoMap's full format) a new live session of the cluster: its snapshot of
// label 0 and no journal; the least-loaded live server takes it within a round of its
// control loop (an orphan: no owner yet). kConflict when the session exists. One
// transaction: a failure leaves nothing.
common::Status importSession(PgConnection& db, const std::string& id, double resolution,
                             const std::string& ot);

// Creates the cluster's tables, functions and triggers when missing (idempotent; serialised
// between servers by an advisory lock).
common::Status migrateSchema(PgConnection& db);

}  // namespace stereomap::cluster
