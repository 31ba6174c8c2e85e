// stereomap-store: the session store, offline. Lists, checks and exports sessions (beside a
// running server too: reading takes no lock), and closes, deletes and merges them (only
// when no server holds the store; use the server's REST API otherwise).
#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <nlohmann/json.hpp>

#include "common/cli.hpp"
#include "common/files.hpp"
#include "common/transform_args.hpp"
#include "proto/journal/journal.hpp"
#include "server/align/map_diff.hpp"
#include "server/app/store_tool.hpp"
#include "server/core/exports.hpp"
#include "server/core/map_server.hpp"
#include "server/core/session_align.hpp"
#include "server/core/session_json.hpp"
#include "server/core/validate.hpp"
#include "server/fusion/occupancy_map.hpp"
#include "server/fusion/octomap_log.hpp"
#include "server/interop/session_mcap.hpp"
#include "server/store/map_import.hpp"
#include "server/store/store_admin.hpp"

namespace {

using namespace stereomap;
namespace fs = std::filesystem;
using stereomap::app::Args;
using stereomap::app::fail;

struct Store {
  std::unique_ptr<store::SessionJournals> journals;
  std::unique_ptr<core::MapServer> server;
  std::unique_ptr<store::StoreAdmin> admin;
};

// A private MapServer over the store: nothing is loaded until a command opens a session.
common::Result<Store> openStore(const fs::path& root, double resolution, bool writable) {
  Store store;
  core::MapServerOptions options;
  options.resolution = resolution;
  if (writable) {
    store.journals = std::make_unique<store::SessionJournals>(root, resolution);
    options.log = store.journals.get();
    options.snapshots = store.journals.get();
  }
  store.server = std::make_unique<core::MapServer>(options);
  auto admin = store::StoreAdmin::create(root, *store.server, store.journals.get(),
                                         {.default_resolution = resolution, .writable = writable});
  if (!admin) return admin.error();
  store.admin = std::move(admin).value();
  return store;
}

// The catalog's rows; without a catalog (a store no server has run on since it was added),
// what the session directories say.
common::Result<std::vector<store::CatalogRow>> catalogRows(Store& store) {
  auto catalog = store::Catalog::openReadOnly(store.admin->root());
  if (catalog) return (*catalog)->list();
  spdlog::warn("{}; listing the session directories instead", catalog.error().message);
  std::vector<store::CatalogRow> rows;
  for (const auto& s : store.admin->savedSessions()) {
    rows.push_back(store::catalogRow(s, store::journalBytes(store.admin->root() / s.id)));
  }
  return rows;
}

int list(Store& store, bool as_json) {
  auto rows = catalogRows(store);
  if (!rows) return fail(rows.error().message);
  if (as_json) {
    nlohmann::json out = nlohmann::json::array();
    for (const auto& r : *rows) {
      // The server's session object, with what the catalog keeps, and the store's own facts.
      auto object = core::sessionObject(store::catalogStatus(r), core::SessionFields::kCatalog);
      object["journal_bytes"] = r.journal_bytes;
      object["updated_ns"] = r.updated_ns;
      out.push_back(std::move(object));
    }
    std::cout << out.dump(2) << "\n";
    return 0;
  }
  std::printf("%-28s %-7s %-16s %7s %6s %9s %10s\n", "SESSION", "STATE", "VEHICLES", "FRAMES",
              "RES_M", "VOXELS", "JOURNAL_MB");
  for (const auto& r : *rows) {
    std::printf("%-28s %-7s %-16s %7llu %6.3f %9llu %10s\n", r.id.c_str(), r.state.c_str(),
                r.vehicles.c_str(), static_cast<unsigned long long>(r.frames), r.resolution,
                static_cast<unsigned long long>(r.occupied_voxels),
                stereomap::app::megabytes(r.journal_bytes).c_str());
  }
  if (rows->empty()) std::printf("(no sessions in %s)\n", store.admin->root().string().c_str());
  return 0;
}

// Whether a snapshot file reads back as a map (a .ot the server could start from).
std::string snapshotProblem(const fs::path& path, double resolution) {
  std::ifstream in(path, std::ios::binary);
  fusion::OccupancyMap map({.resolution = resolution});
  auto read = map.readFull(in);
  return read ? "" : read.error().message;
}

// Reads every session's journal and snapshots; exit code 1 when anything is damaged.
int check(Store& store) {
  int damaged = 0;
  const auto ids = store.admin->storedIds();
  const auto saved = store.admin->savedSessions();
  for (size_t i = 0; i < ids.size(); ++i) {
    const auto& id = ids[i];
    const fs::path dir = store.admin->root() / id;
    auto replay = store::readJournal(dir / store::kJournalName);
    if (!replay) {
      std::printf("%-24s UNREADABLE %s\n", id.c_str(), replay.error().message.c_str());
      ++damaged;
      continue;
    }
    size_t frames = 0;
    for (const auto& r : replay->records) frames += std::holds_alternative<proto::CloudFrameMsg>(r);
    const auto snapshots = store::snapshotsIn(dir);
    bool bad = !replay->problem.empty();
    std::printf("%-24s %-9s %zu records, %zu frames, %s MB (format %d), %zu snapshot(s)\n",
                id.c_str(), bad ? "DAMAGED" : "ok", replay->records.size(), frames,
                stereomap::app::megabytes(replay->file_bytes).c_str(), replay->version,
                snapshots.size());
    if (replay->header_damaged) std::printf("  journal: file header damaged (records kept)\n");
    for (const auto& damage : replay->damage) {
      std::printf("  journal: %s\n", damage.describe().c_str());
    }
    if (replay->good_bytes < replay->file_bytes) {
      std::printf(
          "  journal: torn tail at byte %llu (%llu bytes; cut when the session is next "
          "written)\n",
          static_cast<unsigned long long>(replay->good_bytes),
          static_cast<unsigned long long>(replay->file_bytes - replay->good_bytes));
    }
    for (const auto& [label, path] : snapshots) {
      const std::string problem =
          snapshotProblem(path, saved[i].resolution > 0 ? saved[i].resolution : 0.1);
      if (problem.empty()) continue;
      std::printf("  %s: unusable (%s)\n", path.filename().string().c_str(), problem.c_str());
      bad = true;
    }
    damaged += bad;
  }
  if (ids.empty()) std::printf("(no sessions in %s)\n", store.admin->root().string().c_str());
  if (damaged > 0) {
    std::printf(
        "%d damaged: the server skips damaged records and keeps every intact one; "
        "`stereomap-store repair ID` rewrites a journal without them\n",
        damaged);
  }
  return damaged > 0 ? 1 : 0;
}

// Rewrites damaged (or format 1) journals without their unreadable records.
int repair(Store& store, const std::vector<std::string>& ids) {
  int failed = 0;
  for (const auto& id : ids) {
    std::error_code ec;
    if (!core::isValidId(id) || !fs::exists(store.admin->root() / id / store::kJournalName, ec)) {
      std::printf("%s: no such session\n", id.c_str());
      ++failed;
      continue;
    }
    auto report = store::repairJournal(store.admin->root() / id);
    if (!report) {
      std::printf("%s: not repaired: %s\n", id.c_str(), report.error().message.c_str());
      ++failed;
    } else if (report->problem.empty()) {
      std::printf("%s: intact, nothing to do\n", id.c_str());
    } else {
      std::printf("%s: rewritten with %llu records (%llu lost: %s)%s%s\n", id.c_str(),
                  static_cast<unsigned long long>(report->records_kept),
                  static_cast<unsigned long long>(report->records_lost), report->problem.c_str(),
                  report->original.empty() ? "" : "; the damaged original is kept as ",
                  report->original.string().c_str());
    }
  }
  return failed > 0 ? 1 : 0;
}

// Every flag and argument of every subcommand.
// A subcommand: whether it writes (it needs the store to itself) and what it does.
struct Command {
  CLI::App* app;
  bool writes;
  std::function<int(Store&, Args&)> run;
};

int importMap(Store& store, Args& a) {
  std::printf("reading and checking %s...\n", a.map_file.c_str());
  std::fflush(stdout);
  auto imported = store.admin->importMap(a.map_file, a.id);
  if (!imported) return fail(imported.error().message);
  const auto session = store.server->find(a.id);
  const auto status = session->status();
  std::printf("imported %s as session '%s': %zu occupied voxels at %g m, %zu tiles\n",
              a.map_file.c_str(), a.id.c_str(), status.occupied_voxels, status.resolution,
              session->tiles().summary().tiles);
  return 0;
}

// The named sessions, or every one whose journal is damaged or of format 1.
int repairJournals(Store& store, Args& a) {
  auto& admin = *store.admin;
  if (a.repair_ids.empty()) {
    for (const auto& stored : admin.storedIds()) {
      auto replay = store::readJournal(admin.root() / stored / store::kJournalName);
      if (!replay || !replay->problem.empty() || replay->version == 1) {
        a.repair_ids.push_back(stored);
      }
    }
    if (a.repair_ids.empty()) std::printf("every journal is intact\n");
  }
  return repair(store, a.repair_ids);
}

// The session as the store holds it, replayed into this tool's private server.
common::Result<std::shared_ptr<core::Session>> replayed(Store& store, const std::string& id) {
  if (auto opened = store.admin->open(id); !opened) return opened.error();
  return store.server->find(id);
}

int showSession(Store& store, Args& a) {
  const bool was_closed = store.admin->isClosedOnDisk(a.id);
  auto session = replayed(store, a.id);
  if (!session) return fail(session.error().message);
  auto status = (*session)->status();  // the state in the store, not this tool's copy's
  status.read_only = false;
  status.closed = was_closed;
  std::cout << core::sessionJson(status) << "\n";
  return 0;
}

int exportFile(Store& store, Args& a) {
  if (a.mcap_out.empty() && a.request.format.empty()) {
    return fail("export needs --format FORMAT or --mcap FILE");
  }
  auto session = replayed(store, a.id);
  if (!session) return fail(session.error().message);
  if (a.mcap_out.empty()) return stereomap::app::exportSessionFile(**session, a);
  return stereomap::app::exportSessionMcap(
      **session, interop::journalFile(store.admin->root() / a.id / store::kJournalName), a);
}

int closeSession(Store& store, Args& a) {
  if (store.admin->isClosedOnDisk(a.id)) return fail("session '" + a.id + "' is already closed");
  if (auto opened = store.admin->open(a.id); !opened) return fail(opened.error().message);
  if (auto closed = store.admin->close(a.id); !closed) return fail(closed.error().message);
  std::printf("session '%s' closed\n", a.id.c_str());
  return 0;
}

int deleteSession(Store& store, Args& a) {
  if (auto removed = store.admin->remove(a.id); !removed) return fail(removed.error().message);
  std::printf("session '%s' deleted\n", a.id.c_str());
  return 0;
}

// A session's map, replayed into this tool's private server (opened read-only).
core::SessionMapSource mapsOf(Store& store) {
  return [&store](const std::string& id) {
    return core::sessionMap(*store.server, store.admin.get(), id);
  };
}

int alignSessions(Store& store, Args& a) { return stereomap::app::alignCommand(mapsOf(store), a); }

int diffSessions(Store& store, Args& a) {
  const auto keep = [&](const std::string& id, double resolution, const std::string& ot,
                        const std::string& about) -> common::Status {
    if (!store.admin) {
      return common::makeError(common::ErrorCode::kUnavailable, "the store is open read-only");
    }
    auto imported = store.admin->importMap({resolution, ot}, id, nlohmann::json::parse(about));
    if (!imported) return imported.error();
    return common::Ok{};
  };
  return stereomap::app::diffCommand(mapsOf(store), keep, a);
}

// Merges, then closes the merged session (it was opened read-only): its status.
stereomap::app::MergeSessions mergeInStore(Store& store) {
  return [&store](const core::MergeRequest& request) -> common::Result<core::SessionStatus> {
    if (auto merged = store.admin->merge(request); !merged) return merged.error();
    const auto status = store.server->find(request.into)->status();
    if (auto closed = store.admin->close(request.into); !closed) return closed.error();
    return status;
  };
}

int siteSessions(Store& store, Args& a) {
  std::error_code ec;
  if (core::isValidId(a.into) && fs::exists(fs::path(a.root) / a.into, ec)) {
    return fail("session '" + a.into + "' already exists");  // before minutes of aligning
  }
  return stereomap::app::siteCommand(mapsOf(store), mergeInStore(store), a);
}

int mergeSessions(Store& store, Args& a) {
  int code = 0;
  const auto request = stereomap::app::mergeRequestAligned(mapsOf(store), a, code);
  if (!request) return code;
  const auto merged = mergeInStore(store)(*request);
  if (!merged) return fail(merged.error().message);
  const auto& status = *merged;
  std::printf(
      "merged '%s' and '%s' into '%s' (closed): %llu frames, %zu poses, %zu occupied voxels\n",
      a.first.c_str(), a.second.c_str(), a.into.c_str(),
      static_cast<unsigned long long>(status.frames_fused), status.poses, status.occupied_voxels);
  return 0;
}

std::vector<Command> addCommands(CLI::App& app, Args& a) {
  app.require_subcommand(1);
  app.add_option("--store", a.root, "The store directory")->capture_default_str();
  app.add_option("--cluster", a.cluster_url,
                 "A cluster's PostgreSQL database (libpq URL, as stereomap-server --cluster) "
                 "instead of a store directory: every command but repair");
  app.add_option("--resolution", a.resolution,
                 "Voxel edge (m) for sessions whose directory does not record one")
      ->check(CLI::Range(0.01, 2.0))
      ->capture_default_str();
  std::vector<Command> commands;

  auto* list_cmd =
      app.add_subcommand("list", "Sessions in the catalog (as the server last saw them)");
  list_cmd->add_flag("--json", a.as_json,
                     "JSON: GET /api/sessions' objects with what the catalog keeps");
  commands.push_back({list_cmd, false, [](Store& s, Args& a) { return list(s, a.as_json); }});

  commands.push_back({app.add_subcommand("check",
                                         "Read every journal and snapshot; name each damaged "
                                         "record; exit 1 if any is damaged"),
                      false, [](Store& s, Args&) { return check(s); }});

  auto* repair_cmd = app.add_subcommand(
      "repair",
      "Rewrite damaged journals without their unreadable records (the original is kept beside "
      "it as journal.smj.damaged-TIME); needs the store to itself");
  repair_cmd->add_option("session", a.repair_ids, "Session ids (default: every damaged one)");
  commands.push_back({repair_cmd, true, repairJournals});

  auto* show_cmd = app.add_subcommand("show", "Replay one session and print its status (JSON)");
  show_cmd->add_option("session", a.id, "Session id")->required();
  commands.push_back({show_cmd, false, showSession});

  auto* export_cmd = app.add_subcommand("export", "Replay one session and write a file");
  export_cmd->add_option("session", a.id, "Session id")->required();
  auto* format =
      export_cmd
          ->add_option("--format", a.request.format,
                       "bt | ot | ply | png | tum | grid (map_server's PGM + YAML of the "
                       "--zmin..--zmax band: free, occupied and unknown cells) | pgm | yaml")
          ->check(CLI::IsMember({"bt", "ot", "ply", "png", "tum", "grid", "pgm", "yaml"}));
  export_cmd
      ->add_option("--mcap", a.mcap_out,
                   "Write the whole session as MCAP for Foxglove: poses, trajectories, clouds, "
                   "the map and map.bt (instead of --format)")
      ->excludes(format);
  export_cmd->add_option("--out", a.out,
                         "Output file (default: SESSION.FORMAT; grid: the files' prefix)");
  export_cmd->add_option("--zmin", a.request.z_min, "png, grid: lowest voxel centre height, m");
  export_cmd->add_option("--zmax", a.request.z_max, "png, grid: highest voxel centre height, m");
  export_cmd->add_option("--scale", a.request.scale, "png: pixels per voxel")
      ->check(CLI::Range(1, 16));
  export_cmd->add_option("--vehicle", a.request.vehicle, "tum: the vehicle (default: the first)");
  commands.push_back({export_cmd, false, exportFile});

  auto* close_cmd = app.add_subcommand(
      "close", "Save a session's map and trajectory and mark it closed (not loaded at start)");
  close_cmd->add_option("session", a.id, "Session id")->required();
  commands.push_back({close_cmd, true, closeSession});

  auto* delete_cmd = app.add_subcommand("delete", "Delete a session and its files");
  delete_cmd->add_option("session", a.id, "Session id")->required();
  delete_cmd->add_flag("--yes", a.yes, "Confirm: the session's journal and maps are removed");
  commands.push_back({delete_cmd, true, deleteSession});

  auto* import_cmd = app.add_subcommand(
      "import",
      "Make an OctoMap file (.bt or .ot) a closed session of the store, at the file's own "
      "resolution and without a trajectory (nothing is written if the file is damaged)");
  import_cmd->add_option("file", a.map_file, "The .bt or .ot file")->required();
  import_cmd->add_option("--session", a.id, "The new session's id")->required();
  commands.push_back({import_cmd, true, importMap});

  auto* compact_cmd = app.add_subcommand(
      "compact",
      "With --cluster: drop the points of a closed session's clouds below its newest snapshot "
      "(poses, the trajectory and the map kept; no replay before the snapshot, no merge)");
  auto* compact_ids =
      compact_cmd->add_option("session", a.compact_ids, "Closed sessions to compact");
  compact_cmd
      ->add_flag("--all-closed", a.compact_all,
                 "Every closed session whose clouds below its snapshot still have their points "
                 "(for a periodic job)")
      ->excludes(compact_ids);
  commands.push_back({compact_cmd, true, [](Store&, Args&) {
                        return fail(
                            "compact works on a cluster's database (--cluster URL); a store "
                            "folder's journals are kept whole");
                      }});

  auto* merge_cmd = app.add_subcommand(
      "merge", "Merge two sessions into a new, closed one (the second moved by --transform)");
  merge_cmd->add_option("first", a.first, "First session (its map frame is the result's)")
      ->required();
  merge_cmd->add_option("second", a.second, "Second session")->required();
  merge_cmd->add_option("--into", a.into, "The new session's id")->required();
  merge_cmd
      ->add_option("--transform", a.transform,
                   "T_first_second as tx,ty,tz,qx,qy,qz,qw (default: identity)")
      ->delimiter(',')
      ->expected(7);
  merge_cmd
      ->add_option("--align", a.align,
                   "auto: find the transform from the maps (as `align`); refused: exit 3, "
                   "nothing merged")
      ->check(CLI::IsMember({"auto"}))
      ->excludes("--transform");
  commands.push_back({merge_cmd, true, mergeSessions});

  auto* align_cmd = app.add_subcommand(
      "align",
      "Find the rigid transform that puts the second session's map onto the first's, with no "
      "hint (x_first = R x_second + t); exit 3 when the maps do not overlap enough or the "
      "match is ambiguous. Last line: align A B: t tx ty tz q qx qy qz qw, overlap O%, rmse "
      "E m, S s (or: align A B: none (reason))");
  align_cmd->add_option("first", a.first, "The session whose frame is kept")->required();
  align_cmd->add_option("second", a.second, "The session to move onto it")->required();
  commands.push_back({align_cmd, false, alignSessions});

  auto* diff_cmd = app.add_subcommand(
      "diff",
      "What changed from the first session to the second (aligned first, or by --transform): "
      "voxels that appeared or disappeared where the other flight saw free space (unknown is "
      "not free), as a coloured PLY and/or a session in the first's frame");
  diff_cmd->add_option("first", a.first, "The earlier session")->required();
  diff_cmd->add_option("second", a.second, "The later session")->required();
  diff_cmd->add_option("--out", a.out,
                       "The PLY file (default: FIRST-SECOND.diff.ply, unless --into is given)");
  diff_cmd->add_option("--into", a.into,
                       "Keep the diff as a new, closed session of this id too: appeared, "
                       "disappeared and unchanged voxels, coloured by the viewer's 'change' mode");
  diff_cmd
      ->add_option("--transform", a.transform,
                   "T_first_second as tx,ty,tz,qx,qy,qz,qw (default: found by aligning)")
      ->delimiter(',')
      ->expected(7);
  commands.push_back({diff_cmd, false, diffSessions});

  auto* site_cmd = app.add_subcommand(
      "site",
      "Register flights of one place into the first one's frame with no hint (each aligned "
      "onto one already registered) and merge them into a new, closed session that keeps each "
      "session's transform (its origin, shown by the viewer). A session that aligns onto none "
      "is left out and named; exit 3 (nothing made) when none aligns");
  site_cmd->add_option("site", a.into, "The new session's id")->required();
  site_cmd->add_option("sessions", a.sessions, "Two or more sessions; the first gives the frame")
      ->required()
      ->expected(2, static_cast<int>(core::MergeRequest::kMaxSources));
  commands.push_back({site_cmd, true, siteSessions});
  return commands;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "stereomap-store: list, check, export, close, delete, merge, align, diff and site the "
      "sessions of a "
      "stereomap store (the directory given to stereomap-server --store)"};
  Args args;
  const auto commands = addCommands(app, args);
  if (auto exit_code = common::parseCommandLine(app, argc, argv)) return *exit_code;
  fusion::OctomapLogRoute octomap_log;  // after parsing: CLI11's errors stay on stderr
  spdlog::set_pattern("%^%l%$: %v");
  spdlog::set_level(spdlog::level::warn);

  const auto& command = *std::find_if(commands.begin(), commands.end(),
                                      [](const Command& c) { return c.app->parsed(); });
  if (command.app->get_name() == "delete" && !args.yes) {
    return fail("delete is permanent: add --yes to delete '" + args.id + "'");
  }
  if (!args.cluster_url.empty()) return stereomap::app::runInCluster(command.app->get_name(), args);
  // diff writes only when it keeps its result as a session.
  const bool writes = command.writes || (command.app->get_name() == "diff" && !args.into.empty());
  auto store = openStore(args.root, args.resolution, writes);
  if (!store) return fail(store.error().message);
  return command.run(*store, args);
}
