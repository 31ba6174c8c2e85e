// stereomap-store --cluster URL: the same commands against a cluster's database, beside its
// running servers (cluster_store.hpp: every change is one transaction, and a session's owner
// learns of it through its epoch). Sessions are read whole from the database into this tool's
// own server for show and export.
#include <spdlog/spdlog.h>

#include <chrono>
#include <cstdio>
#include <iostream>
#include <limits>
#include <nlohmann/json.hpp>
#include <sstream>

#include "server/app/store_tool.hpp"
#include "server/cluster/cluster_journal.hpp"
#include "server/cluster/cluster_store.hpp"
#include "server/cluster/pg.hpp"
#include "server/core/session_json.hpp"
#include "server/core/validate.hpp"
#include "server/store/map_import.hpp"

namespace stereomap::app {

namespace {

int importMap(const Args& a) {
  std::printf("reading and checking %s...\n", a.map_file.c_str());
  std::fflush(stdout);
  auto map = store::readImportableMap(a.map_file);
  if (!map) return fail(map.error().message);
  // A whole map goes up in one statement: tens of MB on a slow link.
  auto db = cluster::PgConnection::connect(a.cluster_url, {.deadline = std::chrono::minutes(2)});
  if (!db) return fail(db.error().message);
  if (auto imported = cluster::importSession(**db, a.id, map->resolution, map->ot); !imported) {
    return fail(imported.error().message);
  }
  std::printf(
      "imported %s as session '%s' of the cluster at %s: %g m, %.1f MB; a live server serves it "
      "within a second\n",
      a.map_file.c_str(), a.id.c_str(), (*db)->redactedUrl().c_str(), map->resolution,
      static_cast<double>(map->ot.size()) / 1e6);
  return 0;
}

int list(cluster::ClusterStore& store, bool as_json) {
  auto rows = store.sessions();
  if (!rows) return fail(rows.error().message);
  if (as_json) {
    nlohmann::json out = nlohmann::json::array();
    for (const auto& row : *rows) {
      auto object = core::sessionObject(row.status(), core::SessionFields::kCatalog);
      object["state"] = row.state;
      object["server"] = row.http;
      out.push_back(std::move(object));
    }
    std::cout << out.dump(2) << "\n";
    return 0;
  }
  std::printf("%-28s %-7s %-16s %7s %6s %9s %s\n", "SESSION", "STATE", "VEHICLES", "FRAMES",
              "RES_M", "VOXELS", "SERVER");
  for (const auto& row : *rows) {
    // Counts as the session last left a server's memory (none while it never has).
    const auto status = row.status();
    std::string vehicles;
    for (const auto& v : status.vehicles) vehicles += (vehicles.empty() ? "" : ",") + v;
    std::printf("%-28s %-7s %-16s %7llu %6.3f %9zu %s\n", row.id.c_str(), row.state.c_str(),
                vehicles.c_str(), static_cast<unsigned long long>(status.frames_fused),
                row.resolution, status.occupied_voxels, row.http.empty() ? "-" : row.http.c_str());
  }
  if (rows->empty()) std::printf("(no sessions in the cluster)\n");
  return 0;
}

int check(cluster::ClusterStore& store) {
  auto checked = store.check();
  if (!checked) return fail(checked.error().message);
  for (const auto& problem : checked->problems) std::printf("DAMAGED %s\n", problem.c_str());
  std::printf(
      "%zu sessions: %llu journal records (%llu unreadable), %zu snapshots (%zu unusable)\n",
      checked->sessions, static_cast<unsigned long long>(checked->records),
      static_cast<unsigned long long>(checked->unreadable), checked->snapshots,
      checked->bad_snapshots);
  return checked->problems.empty() ? 0 : 1;
}

// show and export: the session loaded into this tool's own server.
int readSession(const std::string& command, cluster::ClusterStore& store,
                cluster::ClusterJournal& journal, Args& a) {
  if (command == "export" && a.mcap_out.empty() && a.request.format.empty()) {
    return fail("export needs --format FORMAT or --mcap FILE");
  }
  auto row = store.session(a.id);
  if (!row) return fail(row.error().message);
  core::MapServer server({.resolution = row->resolution, .max_sessions = 1});
  auto session = store.load(a.id, server);
  if (!session) return fail(session.error().message);
  if (command == "show") {
    auto status = (*session)->status();
    const auto stored = row->status();  // the state in the cluster, not this tool's copy's
    status.read_only = stored.read_only;
    status.closed = stored.closed;
    status.ended = status.ended || stored.ended;
    status.server = row->http;
    std::cout << core::sessionJson(status) << "\n";
    return 0;
  }
  if (a.mcap_out.empty()) return exportSessionFile(**session, a);
  return exportSessionMcap(
      **session,
      [&journal, id = a.id](const std::function<void(proto::journal::JournalRecord &&)>& visit) {
        auto read = journal.forEachRecord(id, [&](proto::journal::JournalRecord&& record,
                                                  uint64_t) { visit(std::move(record)); });
        if (!read) return common::Status(read.error());
        return common::Status(common::Ok{});
      },
      a);
}

// A session's map, replayed from the cluster's journal.
core::SessionMapSource mapsOf(cluster::ClusterStore& store) {
  return [&store](const std::string& id) -> common::Result<std::unique_ptr<fusion::OccupancyMap>> {
    auto session = store.replay(id, std::numeric_limits<int64_t>::max());
    if (!session) return session.error();
    (*session)->waitUntilIdle();
    auto bytes = (*session)->mapFull();
    if (!bytes) return bytes.error();
    std::istringstream in(*bytes);
    return fusion::OccupancyMap::load(in);
  };
}

// Merges in one transaction, then replays the merged session for its counts.
MergeSessions mergeInCluster(cluster::ClusterStore& store) {
  return [&store](const core::MergeRequest& request) -> common::Result<core::SessionStatus> {
    if (auto merged = store.merge(request); !merged) return merged.error();
    auto replayed = store.replay(request.into, std::numeric_limits<int64_t>::max());
    if (!replayed) return replayed.error();
    return (*replayed)->status();
  };
}

int merge(cluster::ClusterStore& store, const Args& a) {
  int code = 0;
  const auto request = mergeRequestAligned(mapsOf(store), a, code);
  if (!request) return code;
  const auto merged = mergeInCluster(store)(*request);
  if (!merged) return fail(merged.error().message);
  const auto& status = *merged;
  std::printf(
      "merged '%s' and '%s' into '%s' (closed): %llu frames, %zu poses, %zu occupied voxels\n",
      a.first.c_str(), a.second.c_str(), a.into.c_str(),
      static_cast<unsigned long long>(status.frames_fused), status.poses, status.occupied_voxels);
  return 0;
}

int compact(cluster::ClusterStore& store, const Args& a) {
  std::vector<std::string> ids = a.compact_ids;
  if (a.compact_all) {
    auto rows = store.sessions();
    if (!rows) return fail(rows.error().message);
    for (const auto& row : *rows) {
      if (row.state == "closed") ids.push_back(row.id);
    }
  } else if (ids.empty()) {
    return fail("compact needs session ids, or --all-closed");
  }
  int failed = 0;
  for (const auto& id : ids) {
    auto done = store.compact(id);
    if (!done && a.compact_all && done.error().code == common::ErrorCode::kInvalidArgument) {
      std::printf("session '%s': skipped (%s)\n", id.c_str(), done.error().message.c_str());
      continue;
    }
    if (!done) {
      failed += fail(done.error().message);
      continue;
    }
    std::printf(
        "session '%s': %llu clouds compacted up to record %llu; its journal %s MB -> %s MB "
        "(the trajectory and the map kept; the space is reused after PostgreSQL's vacuum)\n",
        id.c_str(), static_cast<unsigned long long>(done->clouds),
        static_cast<unsigned long long>(done->up_to), megabytes(done->bytes_before).c_str(),
        megabytes(done->bytes_after).c_str());
  }
  return failed > 0 ? 1 : 0;
}

}  // namespace

int runInCluster(const std::string& command, Args& a) {
  if (command == "import") return importMap(a);
  if (command == "repair") {
    return fail(
        "repair rewrites a store folder's journal files; a cluster's journal is PostgreSQL's "
        "own (check reads it whole)");
  }
  auto journal = cluster::ClusterJournal::open(a.cluster_url);
  if (!journal) return fail(journal.error().message);
  auto store = cluster::ClusterStore::open(a.cluster_url, **journal);
  if (!store) return fail(store.error().message);
  if (command == "list") return list(**store, a.as_json);
  if (command == "check") return check(**store);
  if (command == "show" || command == "export") return readSession(command, **store, **journal, a);
  if (command == "merge") return merge(**store, a);
  if (command == "compact") return compact(**store, a);
  if (command == "align") return alignCommand(mapsOf(**store), a);
  if (command == "site") {
    if (core::isValidId(a.into) && (*store)->session(a.into)) {
      return fail("session '" + a.into + "' already exists");  // before minutes of aligning
    }
    return siteCommand(mapsOf(**store), mergeInCluster(**store), a);
  }
  if (command == "diff") {
    const auto keep = [&](const std::string& id, double resolution, const std::string& ot,
                          const std::string& about) -> common::Status {
      auto db =
          cluster::PgConnection::connect(a.cluster_url, {.deadline = std::chrono::minutes(2)});
      if (!db) return db.error();
      return cluster::importSession(**db, id, resolution, ot, about);
    };
    return diffCommand(mapsOf(**store), keep, a);
  }
  if (command != "close" && command != "delete") return fail(command + ": not on a cluster");
  const auto done = command == "close" ? (*store)->close(a.id) : (*store)->remove(a.id);
  if (!done) return fail(done.error().message);
  // Its server (if any) lets it go at its next round (a second): fenced by the raised epoch.
  std::printf("session '%s' %s\n", a.id.c_str(), command == "close" ? "closed" : "deleted");
  return 0;
}

}  // namespace stereomap::app
