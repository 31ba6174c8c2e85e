#include "server/cluster/cluster_db.hpp"

#include <spdlog/spdlog.h>
#include <unistd.h>

#include <iterator>
#include <nlohmann/json.hpp>
#include <random>
#include <span>

#include "server/cluster/snapshot_codec.hpp"
#include "server/core/session_json.hpp"
#include "server/core/validate.hpp"

namespace stereomap::cluster {

using common::ErrorCode;
using common::makeError;

namespace {

// The cluster's schema, one list of statements per version; a database is brought from the
// version it has to the newest, each version's statements once (migrateSchema). Version 1 is
// the schema of the first clusters, whose databases have no sm_schema table.
//
// The fencing trigger reads the session's row FOR SHARE: a takeover (UPDATE of the epoch)
// waits for a write that passed the check to commit, and a write after it sees the new epoch;
// so no row with a stale epoch commits after a takeover.
constexpr const char* kVersion1[] = {
    R"(CREATE TABLE IF NOT EXISTS sm_servers (
         id text PRIMARY KEY,
         http text NOT NULL,
         lease_until timestamptz NOT NULL,
         joined_at timestamptz NOT NULL DEFAULT now()))",
    R"(CREATE TABLE IF NOT EXISTS sm_sessions (
         id text PRIMARY KEY,
         owner text,
         epoch bigint NOT NULL,
         resolution double precision NOT NULL,
         state text NOT NULL CHECK (state IN ('live', 'closed')),
         created_at timestamptz NOT NULL DEFAULT now(),
         owned_since timestamptz NOT NULL DEFAULT clock_timestamp()))",
    R"(CREATE INDEX IF NOT EXISTS sm_sessions_owner ON sm_sessions (owner) WHERE state = 'live')",
    R"(CREATE TABLE IF NOT EXISTS sm_journal (
         session text NOT NULL REFERENCES sm_sessions (id) ON DELETE CASCADE,
         number bigint NOT NULL,
         epoch bigint NOT NULL,
         kind smallint NOT NULL,
         record bytea NOT NULL,
         committed_at timestamptz NOT NULL DEFAULT clock_timestamp(),
         PRIMARY KEY (session, number)))",
    R"(CREATE TABLE IF NOT EXISTS sm_snapshots (
         session text NOT NULL REFERENCES sm_sessions (id) ON DELETE CASCADE,
         number bigint NOT NULL,
         epoch bigint NOT NULL,
         map bytea NOT NULL,
         PRIMARY KEY (session, number)))",
    // Snapshots come compressed (snapshot_codec.hpp): PostgreSQL's own compression would only
    // cost CPU.
    R"(ALTER TABLE sm_snapshots ALTER COLUMN map SET STORAGE EXTERNAL)",
    R"(CREATE OR REPLACE FUNCTION sm_fence() RETURNS trigger LANGUAGE plpgsql AS $$
       DECLARE current bigint;
       BEGIN
         SELECT epoch INTO current FROM sm_sessions WHERE id = NEW.session FOR SHARE;
         IF current IS NULL OR current <> NEW.epoch THEN
           RAISE EXCEPTION 'session % is fenced: epoch % is stale (now %)',
             NEW.session, NEW.epoch, current USING ERRCODE = 'SMF01';
         END IF;
         RETURN NEW;
       END $$)",
    R"(CREATE OR REPLACE TRIGGER sm_journal_fence BEFORE INSERT ON sm_journal
         FOR EACH ROW EXECUTE FUNCTION sm_fence())",
    R"(CREATE OR REPLACE TRIGGER sm_snapshots_fence BEFORE INSERT ON sm_snapshots
         FOR EACH ROW EXECUTE FUNCTION sm_fence())",
};
// Version 2: each server process registers with an incarnation of its own, so that a process
// started again under the same id is told from the one before it (ClusterDb::adopt).
constexpr const char* kVersion2[] = {
    R"(ALTER TABLE sm_servers ADD COLUMN IF NOT EXISTS incarnation text NOT NULL DEFAULT '')",
};

// Version 3: a cloud's row also holds its record without the payload, so that recovery reads
// the frames a snapshot already holds as a few hundred bytes each, not as their clouds; and
// the control plane's version counter, raised by every change of who owns what (never by a
// lease renewal), so that a server's round reads one row instead of scanning the sessions.
constexpr const char* kVersion3[] = {
    R"(ALTER TABLE sm_journal ADD COLUMN IF NOT EXISTS meta bytea)",
    R"(CREATE TABLE IF NOT EXISTS sm_version (
         one boolean PRIMARY KEY DEFAULT true CHECK (one),
         version bigint NOT NULL))",
    R"(INSERT INTO sm_version (one, version) VALUES (true, 1) ON CONFLICT DO NOTHING)",
    R"(CREATE OR REPLACE FUNCTION sm_bump() RETURNS trigger LANGUAGE plpgsql AS $$
       BEGIN
         UPDATE sm_version SET version = version + 1;
         RETURN NULL;
       END $$)",
    R"(CREATE OR REPLACE TRIGGER sm_sessions_changed
         AFTER INSERT OR DELETE OR UPDATE OF owner, epoch, state ON sm_sessions
         FOR EACH STATEMENT EXECUTE FUNCTION sm_bump())",
    R"(CREATE OR REPLACE TRIGGER sm_servers_changed
         AFTER INSERT OR DELETE OR UPDATE OF http, incarnation ON sm_servers
         FOR EACH STATEMENT EXECUTE FUNCTION sm_bump())",
    // Sessions waiting for an owner (imported, handed back), found without a scan.
    R"(CREATE INDEX IF NOT EXISTS sm_sessions_unowned ON sm_sessions (id)
         WHERE owner IS NULL AND state = 'live')",
    // How many sessions a server can hold (its --max-sessions): placement and takeovers stop
    // there.
    R"(ALTER TABLE sm_servers ADD COLUMN IF NOT EXISTS capacity integer NOT NULL DEFAULT 256)",
};

// Version 4: sessions that end. A session whose vehicles ended it (or fell silent) leaves its
// server's memory as 'ended' (revived, at a raised epoch, when a vehicle announces it again);
// an operator's close makes it 'closed' (its samples refused); 'opened' is a stored session
// loaded read-only on one server (owned, so that the proxy routes its tiles there). A session
// that left memory keeps its last status (the SessionStatus JSON) for listings. Owned states
// ('live', 'opened') get indexes of their own.
constexpr const char* kVersion4[] = {
    R"(ALTER TABLE sm_sessions DROP CONSTRAINT IF EXISTS sm_sessions_state_check)",
    R"(ALTER TABLE sm_sessions ADD CONSTRAINT sm_sessions_state_check
         CHECK (state IN ('live', 'ended', 'opened', 'closed')))",
    R"(ALTER TABLE sm_sessions ADD COLUMN IF NOT EXISTS summary text)",
    R"(ALTER TABLE sm_sessions ADD COLUMN IF NOT EXISTS left_at timestamptz)",
    R"(DROP INDEX IF EXISTS sm_sessions_owner)",
    R"(DROP INDEX IF EXISTS sm_sessions_unowned)",
    R"(CREATE INDEX IF NOT EXISTS sm_sessions_held_owner ON sm_sessions (owner)
         WHERE state IN ('live', 'opened'))",
    R"(CREATE INDEX IF NOT EXISTS sm_sessions_held_unowned ON sm_sessions (id)
         WHERE owner IS NULL AND state IN ('live', 'opened'))",
};

// Version 5: a closed session's journal compacted below its newest snapshot (clouds keep
// only their meta, the trajectory whole: ClusterStore::compact); the record number it was
// compacted up to (0: never), which replays and merges must respect.
constexpr const char* kVersion5[] = {
    R"(ALTER TABLE sm_sessions ADD COLUMN IF NOT EXISTS compacted_up_to bigint NOT NULL DEFAULT 0)",
};

struct SchemaVersion {
  int version;
  std::span<const char* const> statements;
};
constexpr SchemaVersion kSchemaVersions[] = {
    {1, kVersion1}, {2, kVersion2}, {3, kVersion3}, {4, kVersion4}, {5, kVersion5}};

// The advisory lock key that serialises schema creation between servers ("smschema").
constexpr int64_t kSchemaLock = 0x736d736368656d61;

std::string madeUpServerId() {
  char host[64] = {};
  ::gethostname(host, sizeof(host) - 1);
  std::string id = host;
  for (char& c : id) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-') c = '-';
  }
  std::random_device random;
  return (id.empty() ? "server" : id.substr(0, 40)) + "-" + std::to_string(::getpid()) + "-" +
         std::to_string(random() % 100000);
}

// What tells this process from another started under the same server id.
std::string madeUpIncarnation() {
  std::random_device random;
  char text[40];
  std::snprintf(text, sizeof(text), "%d-%08x%08x", static_cast<int>(::getpid()), random(),
                random());
  return text;
}

std::string interval(std::chrono::milliseconds span) {
  return std::to_string(span.count()) + " milliseconds";
}

// Columns id, owner, epoch, resolution, state.
Ownership ownershipAt(const PgResult& rows, int row) {
  return {rows.text(row, 0), rows.text(row, 1), rows.integer(row, 2), rows.real(row, 3),
          rows.text(row, 4) == "opened"};
}

}  // namespace

const char* const kSessionRowSelect =
    "SELECT s.id, s.state, coalesce(s.owner, ''), coalesce(v.http, ''), s.epoch, s.resolution, "
    "coalesce(s.summary, ''), s.compacted_up_to FROM sm_sessions s "
    "LEFT JOIN sm_servers v ON v.id = s.owner AND v.lease_until > now() ";

SessionRow sessionRowAt(const PgResult& rows, int i) {
  return {rows.text(i, 0),    rows.text(i, 1),
          rows.text(i, 2),    rows.text(i, 3),
          rows.integer(i, 4), rows.real(i, 5),
          rows.text(i, 6),    static_cast<uint64_t>(rows.integer(i, 7))};
}

core::SessionStatus SessionRow::status() const {
  auto doc = nlohmann::json::parse(summary, nullptr, /*allow_exceptions=*/false);
  core::SessionStatus out = core::sessionFromJson(id, doc.is_object() ? doc : nlohmann::json{});
  out.resolution = resolution;
  out.ended = state != "live";
  out.closed = state == "closed";
  out.read_only = state == "opened";
  out.server = http;
  return out;
}

int latestSchemaVersion() { return std::end(kSchemaVersions)[-1].version; }

common::Result<int> schemaVersion(PgConnection& db) {
  // No sm_schema: version 1 when its tables are there (the first clusters), else none (0).
  auto tables = db.exec(
      "SELECT to_regclass('sm_schema') IS NOT NULL, to_regclass('sm_sessions') IS NOT NULL");
  if (!tables) return tables.error();
  if (tables->text(0, 0) != "t") return tables->text(0, 1) == "t" ? 1 : 0;
  auto stored = db.exec("SELECT max(version) FROM sm_schema");
  if (!stored) return stored.error();
  return static_cast<int>(stored->integer(0, 0));
}

common::Status migrateSchema(PgConnection& db) {
  const auto fail = [](const common::Error& error) -> common::Status {
    return makeError(error.code, "cannot bring the cluster's schema up to date: " + error.message);
  };
  // Read without a lock first: on a schema that is up to date (every start but the first
  // after an upgrade) nothing is locked and no statement changes a table.
  auto version = schemaVersion(db);
  if (!version) return fail(version.error());
  const auto newer = [&](int found) -> common::Status {
    return makeError(ErrorCode::kConflict,
                     "the cluster's database has schema version " + std::to_string(found) +
                         ", newer than this server's " + std::to_string(latestSchemaVersion()) +
                         ": run the newer stereomap-server");
  };
  if (*version > latestSchemaVersion()) return newer(*version);
  if (*version == latestSchemaVersion()) return common::Ok{};

  if (auto begun = db.exec("BEGIN"); !begun) return fail(begun.error());
  auto rollback = [&](const common::Error& error) -> common::Status {
    (void)db.exec("ROLLBACK");
    return fail(error);
  };
  // One server at a time; the others find the new version once this one commits.
  if (auto locked = db.exec("SELECT pg_advisory_xact_lock($1)", {kSchemaLock}); !locked) {
    return rollback(locked.error());
  }
  version = schemaVersion(db);
  if (!version) return rollback(version.error());
  if (*version > latestSchemaVersion()) {
    (void)db.exec("ROLLBACK");
    return newer(*version);
  }
  const int from = *version;
  for (const auto& step : kSchemaVersions) {
    if (step.version <= from) continue;
    for (const char* statement : step.statements) {
      if (auto done = db.exec(statement); !done) return rollback(done.error());
    }
  }
  for (const char* statement : {"CREATE TABLE IF NOT EXISTS sm_schema (version integer NOT NULL, "
                                "upgraded_at timestamptz NOT NULL DEFAULT now())",
                                "DELETE FROM sm_schema"}) {
    if (auto done = db.exec(statement); !done) return rollback(done.error());
  }
  if (auto stored = db.exec("INSERT INTO sm_schema (version) VALUES ($1)", {latestSchemaVersion()});
      !stored) {
    return rollback(stored.error());
  }
  if (auto committed = db.exec("COMMIT"); !committed) return fail(committed.error());
  if (from > 0) {
    spdlog::info("cluster: the database's schema upgraded from version {} to {}", from,
                 latestSchemaVersion());
  }
  return common::Ok{};
}

std::string originSummary(const std::string& id, const std::string& origin) {
  if (origin.empty()) return "";
  core::SessionStatus status;
  status.id = id;
  status.origin = origin;
  return core::sessionJson(status);
}

common::Status importSession(PgConnection& db, const std::string& id, double resolution,
                             const std::string& ot, const std::string& origin) {
  if (!core::isValidId(id)) {
    return makeError(ErrorCode::kInvalidArgument,
                     "session id '" + id.substr(0, 80) + "' is not 1-64 of [A-Za-z0-9._-]");
  }
  if (auto migrated = migrateSchema(db); !migrated) return migrated.error();
  if (auto begun = db.exec("BEGIN"); !begun) return begun.error();
  auto fail = [&](const common::Error& error) -> common::Status {
    (void)db.exec("ROLLBACK");
    return error;
  };
  auto session = db.exec(
      "INSERT INTO sm_sessions (id, owner, epoch, resolution, state, summary) "
      "VALUES ($1, NULL, 1, $2, 'live', $3) ON CONFLICT (id) DO NOTHING",
      {id, resolution, origin.empty() ? PgParam::null() : PgParam(originSummary(id, origin))});
  if (!session) return fail(session.error());
  if (session->affected() == 0) {
    return fail(makeError(ErrorCode::kConflict, "session '" + id + "' already exists"));
  }
  auto snapshot =
      db.exec("INSERT INTO sm_snapshots (session, number, epoch, map) VALUES ($1, 0, 1, $2)",
              {id, PgParam::bytes(packSnapshot(ot))});
  if (!snapshot) return fail(snapshot.error());
  if (auto committed = db.exec("COMMIT"); !committed) return fail(committed.error());
  return common::Ok{};
}

common::Result<std::unique_ptr<ClusterDb>> ClusterDb::open(const ClusterOptions& given) {
  ClusterOptions options = given;
  if (options.server_id.empty()) options.server_id = madeUpServerId();
  if (!core::isValidId(options.server_id)) {
    return makeError(
        ErrorCode::kInvalidArgument,
        "server id '" + options.server_id + "' must be 1-64 letters, digits, '-', '_' or '.'");
  }
  auto db = PgConnection::connect(options.url, controlOptions());
  if (!db) return db.error();
  if (auto migrated = migrateSchema(**db); !migrated) return migrated.error();
  auto lease = PgConnection::connect(options.url, leaseOptions(options.lease));
  if (!lease) return lease.error();
  auto cluster = std::unique_ptr<ClusterDb>(
      new ClusterDb(std::move(options), std::move(*db), std::move(*lease)));
  if (auto registered = cluster->registerServer(); !registered) return registered.error();
  return cluster;
}

PgOptions ClusterDb::controlOptions() {
  // Short statements on small tables: a second is long; a takeover's UPDATE may wait for a
  // journal write that passed the fence (its FOR SHARE lock) to commit.
  return {.connect_timeout = std::chrono::seconds(2),
          .deadline = std::chrono::seconds(3),
          .lock_timeout = std::chrono::seconds(2)};
}

PgOptions ClusterDb::leaseOptions(std::chrono::milliseconds lease) {
  // A renewal that takes a quarter of the lease is a database in trouble: said within
  // seconds (/healthz), long before the lease itself runs out. At least a second, so that
  // one slow flush is not an outage.
  const auto deadline = std::max<std::chrono::milliseconds>(std::chrono::seconds(1), lease / 4);
  return {
      .connect_timeout = std::chrono::seconds(2), .deadline = deadline, .lock_timeout = deadline};
}

ClusterDb::ClusterDb(ClusterOptions options, std::unique_ptr<PgConnection> db,
                     std::unique_ptr<PgConnection> lease)
    : options_(std::move(options)),
      incarnation_(madeUpIncarnation()),
      db_(std::move(db)),
      lease_db_(std::move(lease)) {}

common::Result<PgResult> ClusterDb::exec(std::string_view sql, const std::vector<PgParam>& params) {
  std::lock_guard lock(mutex_);
  return execOn(*db_, sql, params);
}

common::Result<PgResult> ClusterDb::execOn(PgConnection& db, std::string_view sql,
                                           const std::vector<PgParam>& params) {
  if (!db.connected()) {
    if (auto reconnected = db.reconnect(); !reconnected) return reconnected.error();
  }
  auto result = db.exec(sql, params);
  // A connection the database lost while idle (a restart) shows only when used: once more on
  // a new one. Every statement here may run twice: each is one statement in its own
  // transaction whose second run finds the first's outcome.
  if (!result && !db.connected() && db.abandoned() == 0) {
    if (auto reconnected = db.reconnect(); !reconnected) return reconnected.error();
    result = db.exec(sql, params);
  }
  return result;
}

common::Status ClusterDb::registerServer() {
  // A process started again under the same id takes the row over with its own incarnation:
  // the one before it (paused, cut off) can renew nothing and adopt nothing from then on.
  std::lock_guard lock(lease_mutex_);
  auto done = execOn(
      *lease_db_,
      "INSERT INTO sm_servers (id, http, lease_until, incarnation, capacity) "
      "VALUES ($1, $2, now() + $3::interval, $4, $5) "
      "ON CONFLICT (id) DO UPDATE SET http = EXCLUDED.http, lease_until = EXCLUDED.lease_until, "
      "incarnation = EXCLUDED.incarnation, capacity = EXCLUDED.capacity",
      {options_.server_id, options_.http, interval(options_.lease), incarnation_,
       static_cast<int64_t>(options_.capacity)});
  if (!done) return done.error();
  return common::Ok{};
}

common::Result<ClusterDb::Lease> ClusterDb::renewLease() {
  std::unique_lock lock(lease_mutex_);
  auto renewed =
      execOn(*lease_db_,
             "UPDATE sm_servers v SET lease_until = now() + $3::interval "
             "FROM (SELECT id, lease_until FROM sm_servers WHERE id = $1 AND incarnation = $2 "
             "  FOR UPDATE) before "
             "WHERE v.id = before.id RETURNING before.lease_until > now()",
             {options_.server_id, incarnation_, interval(options_.lease)});
  if (!renewed) return renewed.error();
  // No row of this incarnation: another process registered under this id since.
  if (renewed->rows() == 0) return Lease::kSuperseded;
  if (renewed->text(0, 0) == "t") return Lease::kRenewed;
  return Lease::kRenewedAfterExpiry;
}

common::Result<Ownership> ClusterDb::adopt(const Ownership& session) {
  // The epoch rises with every adoption, by whichever process: a write of any earlier one
  // (this server's own earlier process included) is fenced from now on. The UPDATE waits for
  // a write that passed the fence to commit, so what is read after it is all there is.
  auto adopted = exec(
      "UPDATE sm_sessions s SET epoch = s.epoch + 1, owned_since = clock_timestamp() "
      "FROM sm_servers v "
      "WHERE s.id = $1 AND s.owner = $2 AND s.state IN ('live', 'opened') "
      "AND v.id = $2 AND v.incarnation = $3 AND v.lease_until > now() "
      "RETURNING s.id, s.owner, s.epoch, s.resolution, s.state",
      {session.session, options_.server_id, incarnation_});
  if (!adopted) return adopted.error();
  if (adopted->rows() == 0) {
    return makeError(ErrorCode::kConflict,
                     "session '" + session.session +
                         "' is not this process's to adopt (another server or process has it, "
                         "or this one's lease ran out)");
  }
  return ownershipAt(*adopted, 0);
}

common::Result<Ownership> ClusterDb::placeSession(const std::string& id, double resolution) {
  if (!core::isValidId(id)) {
    return makeError(ErrorCode::kInvalidArgument, "session id '" + id + "' is not valid");
  }
  // The least-loaded live server with room; ties go to the lowest id, the same choice on
  // every server. None with room: no owner yet (an orphan, taken once a server has room).
  auto placed = exec(
      "INSERT INTO sm_sessions (id, owner, epoch, resolution, state) "
      "SELECT $1, (SELECT v.id FROM sm_servers v "
      "  CROSS JOIN LATERAL (SELECT count(*) AS n FROM sm_sessions s "
      "    WHERE s.owner = v.id AND s.state IN ('live', 'opened')) load "
      "  WHERE v.lease_until > now() AND load.n < v.capacity ORDER BY load.n, v.id LIMIT 1), "
      "1, $2, 'live' "
      "ON CONFLICT (id) DO UPDATE SET state = 'live', owner = EXCLUDED.owner, "
      "  epoch = sm_sessions.epoch + 1, owned_since = clock_timestamp() "
      "  WHERE sm_sessions.state = 'ended' "
      "RETURNING id, coalesce(owner, ''), epoch, resolution, state",
      {id, resolution});
  if (!placed) return placed.error();
  if (placed->rows() == 1) {
    if (placed->text(0, 1).empty()) {
      return makeError(ErrorCode::kUnavailable, "session '" + id +
                                                    "' waits for a server with room: every "
                                                    "live server holds as many as it can");
    }
    return ownershipAt(*placed, 0);
  }
  auto existing = ownerOf(id);
  if (!existing) return existing.error();
  if (!*existing) {
    return makeError(ErrorCode::kConflict, "session '" + id + "' is closed or has no live server");
  }
  return **existing;
}

common::Result<std::vector<Ownership>> ClusterDb::owned() {
  auto rows = exec(
      "SELECT id, owner, epoch, resolution, state FROM sm_sessions "
      "WHERE owner = $1 AND state IN ('live', 'opened') "
      "ORDER BY id",
      {options_.server_id});
  if (!rows) return rows.error();
  std::vector<Ownership> out;
  for (int i = 0; i < rows->rows(); ++i) out.push_back(ownershipAt(*rows, i));
  return out;
}

common::Result<ClusterDb::Round> ClusterDb::poll() {
  // One row and two index probes: the servers whose lease ran out that still own live
  // sessions (the servers' table is small; the sessions' owner index answers each), and the
  // live sessions with no owner.
  auto polled = exec(
      "SELECT (SELECT version FROM sm_version), "
      "EXISTS (SELECT 1 FROM sm_servers v WHERE v.lease_until <= now() AND EXISTS ("
      "  SELECT 1 FROM sm_sessions s WHERE s.owner = v.id AND s.state IN ('live', 'opened'))) "
      "OR EXISTS (SELECT 1 FROM sm_sessions WHERE owner IS NULL "
      "  AND state IN ('live', 'opened'))",
      {});
  if (!polled) return polled.error();
  return Round{polled->integer(0, 0), polled->text(0, 1) == "t"};
}

uint64_t ClusterDb::statements() const {
  // Read without the connections' locks: a count for /metrics, exact enough.
  return db_->statements() + lease_db_->statements();
}

common::Result<std::vector<Ownership>> ClusterDb::takeOrphans() {
  // This server's share: the orphans divided among the live servers, rounded up, so that
  // the survivors of a failure split the work rather than the first one taking it all; never
  // more than its room.
  auto taken = exec(
      "WITH orphans AS ("
      "  SELECT s.id FROM sm_sessions s LEFT JOIN sm_servers v ON v.id = s.owner "
      "  WHERE s.state IN ('live', 'opened') AND (v.id IS NULL OR v.lease_until <= now())), "
      "share AS ("
      "  SELECT greatest(0, least("
      "    greatest(1, ceil((SELECT count(*) FROM orphans)::numeric / "
      "      greatest(1, (SELECT count(*) FROM sm_servers WHERE lease_until > now()))))::int, "
      "    (SELECT capacity FROM sm_servers WHERE id = $1) - "
      "      (SELECT count(*) FROM sm_sessions WHERE owner = $1 "
      "       AND state IN ('live', 'opened')))) AS n) "
      "UPDATE sm_sessions SET owner = $1, epoch = epoch + 1, owned_since = clock_timestamp() "
      "WHERE id IN (SELECT s.id FROM sm_sessions s WHERE s.id IN (SELECT id FROM orphans) "
      "  ORDER BY s.id LIMIT (SELECT n FROM share) FOR UPDATE SKIP LOCKED) "
      "AND EXISTS (SELECT 1 FROM sm_servers WHERE id = $1 AND incarnation = $2 "
      "  AND lease_until > now()) "
      "RETURNING id, owner, epoch, resolution, state",
      {options_.server_id, incarnation_});
  if (!taken) return taken.error();
  std::vector<Ownership> out;
  for (int i = 0; i < taken->rows(); ++i) out.push_back(ownershipAt(*taken, i));
  return out;
}

common::Result<std::string> ClusterDb::sessionState(const std::string& id) {
  auto rows = exec("SELECT state FROM sm_sessions WHERE id = $1", {id});
  if (!rows) return rows.error();
  return rows->rows() == 0 ? std::string() : rows->text(0, 0);
}

common::Result<std::optional<Ownership>> ClusterDb::ownerOf(const std::string& id) {
  auto rows = exec(
      "SELECT id, owner, epoch, resolution, state FROM sm_sessions "
      "WHERE id = $1 AND state IN ('live', 'opened') "
      "AND owner IS NOT NULL",
      {id});
  if (!rows) return rows.error();
  if (rows->rows() == 0) return std::optional<Ownership>();
  return std::optional<Ownership>(ownershipAt(*rows, 0));
}

common::Result<std::vector<ServerInfo>> ClusterDb::servers() {
  auto rows = exec(
      "SELECT v.id, v.http, v.lease_until > now(), "
      "(SELECT count(*) FROM sm_sessions s WHERE s.owner = v.id AND s.state IN ('live', 'opened')) "
      "FROM sm_servers v ORDER BY v.id",
      {});
  if (!rows) return rows.error();
  std::vector<ServerInfo> out;
  for (int i = 0; i < rows->rows(); ++i) {
    out.push_back(
        {rows->text(i, 0), rows->text(i, 1), rows->text(i, 2) == "t", rows->integer(i, 3)});
  }
  return out;
}

common::Result<std::vector<ClusterDb::Placement>> ClusterDb::directory() {
  auto rows = exec(
      "SELECT s.id, s.owner, s.epoch, s.resolution, s.state, v.http FROM sm_sessions s "
      "JOIN sm_servers v ON v.id = s.owner "
      "WHERE s.state IN ('live', 'opened') AND v.lease_until > now() "
      "ORDER BY s.id",
      {});
  if (!rows) return rows.error();
  std::vector<Placement> out;
  for (int i = 0; i < rows->rows(); ++i) out.push_back({ownershipAt(*rows, i), rows->text(i, 5)});
  return out;
}

common::Result<std::vector<SessionRow>> ClusterDb::outOfMemory() {
  auto rows = exec(
      std::string(kSessionRowSelect) + "WHERE s.state IN ('ended', 'closed') ORDER BY s.id", {});
  if (!rows) return rows.error();
  std::vector<SessionRow> out;
  for (int i = 0; i < rows->rows(); ++i) out.push_back(sessionRowAt(*rows, i));
  return out;
}

common::Status ClusterDb::release(const Ownership& session, Leaving how,
                                  const std::string& summary) {
  // Handed back: still live (or opened), for another server to take. Ended or closed: out of
  // every server's memory, with its last status kept for listings.
  const char* state = how == Leaving::kEnded    ? "ended"
                      : how == Leaving::kClosed ? "closed"
                                                : nullptr;
  auto done = state == nullptr ? exec(
                                     "UPDATE sm_sessions SET owner = NULL "
                                     "WHERE id = $1 AND owner = $2 AND epoch = $3",
                                     {session.session, options_.server_id, session.epoch})
                               : exec(
                                     "UPDATE sm_sessions SET owner = NULL, state = $4, "
                                     "summary = coalesce($5, summary), left_at = now() "
                                     "WHERE id = $1 AND owner = $2 AND epoch = $3",
                                     {session.session, options_.server_id, session.epoch, state,
                                      summary.empty() ? PgParam::null() : PgParam(summary)});
  if (!done) return done.error();
  if (done->affected() == 0) {
    return makeError(ErrorCode::kConflict, "session '" + session.session +
                                               "' is no longer this server's (epoch " +
                                               std::to_string(session.epoch) + " is stale)");
  }
  return common::Ok{};
}

common::Status ClusterDb::leave() {
  auto done = exec("UPDATE sm_servers SET lease_until = now() WHERE id = $1 AND incarnation = $2",
                   {options_.server_id, incarnation_});
  if (!done) return done.error();
  return common::Ok{};
}

}  // namespace stereomap::cluster
