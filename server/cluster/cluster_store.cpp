#include "server/cluster/cluster_store.hpp"

#include <spdlog/spdlog.h>

#include <limits>
#include <set>

#include "server/cluster/cluster_recovery.hpp"
#include "server/cluster/snapshot_codec.hpp"
#include "server/core/validate.hpp"
#include "server/store/replay.hpp"

namespace stereomap::cluster {

using common::ErrorCode;
using common::makeError;

namespace {

common::Error invalidId(const std::string& id) {
  return makeError(ErrorCode::kInvalidArgument,
                   "session id '" + id.substr(0, 80) + "' is not 1-64 of [A-Za-z0-9._-]");
}

common::Error noSession(const std::string& id) {
  return makeError(ErrorCode::kNotFound, "no session '" + id + "' in the cluster");
}

}  // namespace

common::Result<std::unique_ptr<ClusterStore>> ClusterStore::open(const std::string& url,
                                                                 ClusterJournal& journal) {
  // Deletes and merges of long sessions move gigabytes: minutes, not seconds.
  auto db = PgConnection::connect(
      url, {.connect_timeout = std::chrono::seconds(5), .deadline = std::chrono::minutes(10)});
  if (!db) return db.error();
  if (auto migrated = migrateSchema(**db); !migrated) return migrated.error();
  return std::unique_ptr<ClusterStore>(new ClusterStore(std::move(*db), journal));
}

common::Result<PgResult> ClusterStore::exec(std::string_view sql,
                                            const std::vector<PgParam>& params) {
  if (!db_->connected()) {
    if (auto reconnected = db_->reconnect(); !reconnected) return reconnected.error();
  }
  return db_->exec(sql, params);
}

common::Result<std::vector<SessionRow>> ClusterStore::sessions() {
  auto rows = exec(std::string(kSessionRowSelect) + "ORDER BY s.id");
  if (!rows) return rows.error();
  std::vector<SessionRow> out;
  for (int i = 0; i < rows->rows(); ++i) out.push_back(sessionRowAt(*rows, i));
  return out;
}

common::Result<SessionRow> ClusterStore::session(const std::string& id) {
  if (!core::isValidId(id)) return invalidId(id);
  auto rows = exec(std::string(kSessionRowSelect) + "WHERE s.id = $1", {id});
  if (!rows) return rows.error();
  if (rows->rows() == 0) return noSession(id);
  return sessionRowAt(*rows, 0);
}

common::Status ClusterStore::close(const std::string& id) {
  if (!core::isValidId(id)) return invalidId(id);
  // The epoch rises: an owner still writing it is fenced, and unloads it at its next round.
  auto closed = exec(
      "UPDATE sm_sessions SET state = 'closed', owner = NULL, epoch = epoch + 1, "
      "left_at = now() WHERE id = $1 AND state <> 'closed'",
      {id});
  if (!closed) return closed.error();
  if (closed->affected() == 1) return common::Ok{};
  auto existing = session(id);
  if (!existing) return existing.error();
  return makeError(ErrorCode::kConflict, "session '" + id + "' is closed already");
}

common::Result<Ownership> ClusterStore::open(const std::string& id, const std::string& server_id) {
  if (!core::isValidId(id)) return invalidId(id);
  auto opened = exec(
      "UPDATE sm_sessions SET state = 'opened', owner = $2, epoch = epoch + 1, "
      "owned_since = clock_timestamp() WHERE id = $1 AND state IN ('closed', 'ended') "
      "RETURNING id, owner, epoch, resolution",
      {id, server_id});
  if (!opened) return opened.error();
  if (opened->rows() == 1) {
    return Ownership{opened->text(0, 0), opened->text(0, 1), opened->integer(0, 2),
                     opened->real(0, 3), /*read_only=*/true};
  }
  auto existing = session(id);
  if (!existing) return existing.error();
  return makeError(ErrorCode::kConflict,
                   "session '" + id + "' is " + existing->state +
                       (existing->http.empty() ? "" : " on " + existing->http) +
                       ", not closed or ended");
}

common::Status ClusterStore::remove(const std::string& id) {
  if (!core::isValidId(id)) return invalidId(id);
  // The journal and snapshots go with it (ON DELETE CASCADE).
  auto removed = exec("DELETE FROM sm_sessions WHERE id = $1 AND state <> 'live'", {id});
  if (!removed) return removed.error();
  if (removed->affected() == 1) return common::Ok{};
  auto existing = session(id);
  if (!existing) return existing.error();
  return makeError(ErrorCode::kConflict,
                   "session '" + id + "' is live: close it first (its vehicles are flying it)");
}

common::Status ClusterStore::merge(const core::MergeRequest& request) {
  if (const auto problem = request.problem(); !problem.empty()) {
    return makeError(ErrorCode::kInvalidArgument, problem);
  }
  for (const auto& source : request.sources) {
    const std::string* id = &source.id;
    auto existing = session(*id);
    if (!existing) return existing.error();
    if (existing->compacted_up_to > 0) {
      return makeError(ErrorCode::kInvalidArgument,
                       "session '" + *id +
                           "' was compacted: its clouds before its snapshot are gone, and a "
                           "merge fuses every frame again");
    }
    // Merging re-fuses journaled frames; an imported map has none.
    auto imported = exec("SELECT 1 FROM sm_snapshots WHERE session = $1 AND number = 0", {*id});
    if (!imported) return imported.error();
    if (imported->rows() > 0) {
      return makeError(ErrorCode::kInvalidArgument,
                       "session '" + *id + "' is an imported map: it has no frames to merge");
    }
  }
  if (auto begun = exec("BEGIN"); !begun) return begun.error();
  auto written = writeMerged(request);
  if (written) {
    if (auto committed = exec("COMMIT"); !committed) return committed.error();
    return common::Ok{};
  }
  if (db_->connected()) (void)db_->exec("ROLLBACK");
  return written;
}

common::Status ClusterStore::writeMerged(const core::MergeRequest& request) {
  auto first = session(request.sources.front().id);
  if (!first) return first.error();
  // Born closed at epoch 1, in this transaction: the fencing trigger finds it.
  auto created = exec(
      "INSERT INTO sm_sessions (id, owner, epoch, resolution, state, summary) "
      "VALUES ($1, NULL, 1, $2, 'closed', $3) ON CONFLICT (id) DO NOTHING",
      {request.into, first->resolution,
       request.origin.empty() ? PgParam::null()
                              : PgParam(originSummary(request.into, request.origin))});
  if (!created) return created.error();
  if (created->affected() == 0) {
    return makeError(ErrorCode::kConflict, "session '" + request.into + "' already exists");
  }
  // Each source's vehicles, so that a later one's of the same name is renamed, and those in
  // their own frame.
  std::vector<store::SourceVehicles> vehicles;
  for (const auto& source : request.sources) {
    store::SourceVehicles named;
    auto read = journal_.forEachRecord(
        source.id, [&](proto::journal::JournalRecord&& record, uint64_t) { named.note(record); },
        static_cast<uint64_t>(std::numeric_limits<int64_t>::max()));
    if (!read) return read.error();
    vehicles.push_back(std::move(named));
  }
  const store::MergedRecords merged(request, vehicles);
  JournalRows rows;
  uint64_t number = 0;
  common::Status written = common::Ok{};
  const auto flush = [&]() -> common::Status {
    if (rows.empty()) return common::Ok{};
    auto inserted = exec(rows.statement(), rows.params());
    rows.clear();
    if (!inserted) return inserted.error();
    return common::Ok{};
  };
  for (size_t source = 0; source < request.sources.size() && written; ++source) {
    auto read = journal_.forEachRecord(request.sources[source].id,
                                       [&](proto::journal::JournalRecord&& record, uint64_t) {
                                         if (!written) return;
                                         merged.apply(record, source);
                                         rows.add(request.into, ++number, 1, record);
                                         if (rows.full()) written = flush();
                                       });
    if (!read) return read.error();
  }
  if (written) written = flush();
  if (!written) return written;
  spdlog::info("{} sessions merged into '{}': {} records", request.sources.size(), request.into,
               number);
  return common::Ok{};
}

common::Result<std::shared_ptr<core::Session>> ClusterStore::replay(const std::string& id,
                                                                    int64_t until_ns) {
  auto row = session(id);
  if (!row) return row.error();
  if (row->compacted_up_to > 0) return replayCompacted(*row, until_ns);
  return store::replayUntil(
      id, row->resolution, until_ns,
      [&](bool payloads, const store::RecordVisitor& visit) -> common::Status {
        auto read = journal_.forEachRecord(
            id, visit, payloads ? 0 : static_cast<uint64_t>(std::numeric_limits<int64_t>::max()));
        if (!read) return read.error();
        return common::Ok{};
      });
}

common::Result<std::shared_ptr<core::Session>> ClusterStore::load(const std::string& id,
                                                                  core::MapServer& server) {
  auto row = session(id);
  if (!row) return row.error();
  auto stored = journal_.read(id);
  if (!stored) return stored.error();
  size_t frames = 0, poses = 0;
  if (auto recovered = recoverSession(server, journal_,
                                      {id, "", row->epoch, row->resolution, /*read_only=*/true},
                                      *stored, frames, poses, /*wait_until_fused=*/true);
      !recovered) {
    return recovered.error();
  }
  return server.find(id);
}

common::Result<std::shared_ptr<core::Session>> ClusterStore::replayCompacted(const SessionRow& row,
                                                                             int64_t until_ns) {
  auto stored = journal_.read(row.id);
  if (!stored) return stored.error();
  // Its map up to the snapshot is the snapshot's: the time slider starts where it was taken.
  int64_t compacted_until = std::numeric_limits<int64_t>::min();
  for (size_t i = 0; i < stored->records.size(); ++i) {
    const auto* frame = std::get_if<proto::CloudFrameMsg>(&stored->records[i]);
    if (frame != nullptr && stored->numbers[i] <= stored->snapshot_number) {
      compacted_until = std::max(compacted_until, frame->stamp_ns);
    }
  }
  if (stored->snapshot_number < row.compacted_up_to || until_ns < compacted_until) {
    return makeError(ErrorCode::kConflict,
                     "session '" + row.id + "' was compacted: its clouds before " +
                         std::to_string(compacted_until / 1'000'000'000) +
                         " s (since the epoch) are gone; replay it from then on");
  }
  // What came later than `until_ns` is left out.
  proto::journal::JournalReplay kept;
  for (size_t i = 0; i < stored->records.size(); ++i) {
    const int64_t stamp = std::visit([](const auto& m) { return m.stamp_ns; }, stored->records[i]);
    if (stamp > until_ns) continue;
    kept.records.push_back(std::move(stored->records[i]));
    kept.numbers.push_back(stored->numbers[i]);
  }
  stored->records = std::move(kept.records);
  stored->numbers = std::move(kept.numbers);
  core::MapServer scratch({.resolution = row.resolution, .max_sessions = 1});
  size_t frames = 0, poses = 0;
  if (auto recovered =
          recoverSession(scratch, journal_, {row.id, "", 0, row.resolution, /*read_only=*/true},
                         *stored, frames, poses, /*wait_until_fused=*/true);
      !recovered) {
    return recovered.error();
  }
  return scratch.unload(row.id);
}

common::Result<ClusterStore::Compaction> ClusterStore::compact(const std::string& id) {
  if (!core::isValidId(id)) return invalidId(id);
  if (auto begun = exec("BEGIN"); !begun) return begun.error();
  auto compacted = compactInTransaction(id);
  if (compacted) {
    if (auto committed = exec("COMMIT"); !committed) return committed.error();
    return compacted;
  }
  if (db_->connected()) (void)db_->exec("ROLLBACK");
  return compacted;
}

common::Result<ClusterStore::Compaction> ClusterStore::compactInTransaction(const std::string& id) {
  // Locked: nobody opens, revives or deletes it meanwhile.
  auto state = exec("SELECT state FROM sm_sessions WHERE id = $1 FOR UPDATE", {id});
  if (!state) return state.error();
  if (state->rows() == 0) return noSession(id);
  if (state->text(0, 0) != "closed") {
    return makeError(ErrorCode::kConflict,
                     "session '" + id + "' is " + state->text(0, 0) +
                         ": only a closed session is compacted (close it first)");
  }
  // The newest snapshot that can be read, and no correction after it (a correction fuses
  // every frame again).
  auto snapshots = exec(
      "SELECT number, map FROM sm_snapshots WHERE session = $1 AND number > 0 "
      "ORDER BY number DESC",
      {id});
  if (!snapshots) return snapshots.error();
  Compaction out;
  for (int i = 0; i < snapshots->rows() && out.up_to == 0; ++i) {
    if (unpackSnapshot(snapshots->bytes(i, 1))) {
      out.up_to = static_cast<uint64_t>(snapshots->integer(i, 0));
    }
  }
  auto correction =
      exec("SELECT coalesce(max(number), 0) FROM sm_journal WHERE session = $1 AND kind = 4", {id});
  if (!correction) return correction.error();
  if (out.up_to == 0 || static_cast<uint64_t>(correction->integer(0, 0)) > out.up_to) {
    return makeError(ErrorCode::kInvalidArgument,
                     "session '" + id +
                         "' has no readable snapshot that holds all of it (open it and close "
                         "it again: closing snapshots it)");
  }
  const char* kBytes =
      "SELECT coalesce(sum(octet_length(record)), 0) FROM sm_journal WHERE session = $1";
  auto before = exec(kBytes, {id});
  if (!before) return before.error();
  out.bytes_before = static_cast<uint64_t>(before->integer(0, 0));
  auto clouds = exec(
      "UPDATE sm_journal SET record = meta WHERE session = $1 AND kind = 1 AND number <= $2 "
      "AND meta IS NOT NULL AND record <> meta",
      {id, out.up_to});
  if (!clouds) return clouds.error();
  out.clouds = static_cast<uint64_t>(clouds->affected());
  for (const char* sql :
       {"UPDATE sm_sessions SET compacted_up_to = greatest(compacted_up_to, $2) WHERE id = $1",
        // The older snapshots needed the clouds just compacted.
        "DELETE FROM sm_snapshots WHERE session = $1 AND number < $2"}) {
    if (auto done = exec(sql, {id, out.up_to}); !done) return done.error();
  }
  auto after = exec(kBytes, {id});
  if (!after) return after.error();
  out.bytes_after = static_cast<uint64_t>(after->integer(0, 0));
  return out;
}

common::Result<ClusterStore::Check> ClusterStore::check() {
  auto rows = sessions();
  if (!rows) return rows.error();
  Check out;
  for (const auto& row : *rows) {
    ++out.sessions;
    uint64_t records = 0;
    auto scan = journal_.forEachRecord(
        row.id, [&](proto::journal::JournalRecord&&, uint64_t) { ++records; });
    if (!scan) return scan.error();
    out.records += records;
    out.unreadable += scan->unreadable;
    auto snapshots =
        exec("SELECT number, map FROM sm_snapshots WHERE session = $1 ORDER BY number", {row.id});
    if (!snapshots) return snapshots.error();
    std::vector<std::string> bad;
    for (int i = 0; i < snapshots->rows(); ++i) {
      ++out.snapshots;
      if (auto ot = unpackSnapshot(snapshots->bytes(i, 1)); !ot) {
        ++out.bad_snapshots;
        bad.push_back(std::to_string(snapshots->integer(i, 0)) + " (" + ot.error().message + ")");
      }
    }
    if (scan->unreadable > 0 || !bad.empty()) {
      std::string line = "session '" + row.id + "': ";
      if (scan->unreadable > 0) {
        line += std::to_string(scan->unreadable) + " of " +
                std::to_string(records + scan->unreadable) + " journal records unreadable";
      }
      for (const auto& snapshot : bad) {
        line += (line.back() == ' ' ? "" : "; ") + std::string("snapshot ") + snapshot;
      }
      out.problems.push_back(std::move(line));
    }
  }
  return out;
}

}  // namespace stereomap::cluster
