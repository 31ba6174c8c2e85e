#include "server/store/store_admin.hpp"

#include <fcntl.h>
#include <spdlog/spdlog.h>
#include <sys/file.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>

#include "common/files.hpp"
#include "common/time.hpp"
#include "proto/pose_fields.hpp"
#include "server/core/session_json.hpp"
#include "server/core/validate.hpp"
#include "server/fusion/occupancy_map.hpp"
#include "server/store/map_import.hpp"
#include "server/store/replay.hpp"

namespace stereomap::store {

namespace fs = std::filesystem;
using common::ErrorCode;
using common::makeError;
using nlohmann::json;

namespace {

constexpr const char* kClosedMarker = "closed";  // present: the session is closed
constexpr const char* kStatusName = "session.json";

json readJson(const fs::path& path) {
  std::ifstream in(path);
  if (!in) return nullptr;
  return json::parse(in, nullptr, /*allow_exceptions=*/false);
}

// The session's resolution: meta.json (written when its journal was created), else the
// status saved at its last stop, else the default.
double resolutionOf(const fs::path& dir, double fallback) {
  for (const char* name : {kMetaName, kStatusName}) {
    const json doc = readJson(dir / name);
    if (doc.is_object() && doc.contains("resolution") && doc["resolution"].is_number()) {
      const double r = doc["resolution"].get<double>();
      if (r > 0) return r;
    }
  }
  return fallback;
}

// What made the session when it is not a flight (SessionStatus::origin): meta.json's
// description of an import, a diff or a site; "" for a flight.
std::string originOf(const fs::path& dir) {
  json meta = readJson(dir / kMetaName);
  if (!meta.is_object()) return "";
  json origin = json::object();
  for (const char* key : {"imported_from", "diff", "site"}) {
    if (meta.contains(key)) origin[key] = meta[key];
  }
  return origin.empty() ? "" : origin.dump();
}

// Deletes a directory tree, renaming it aside first so that it vanishes from the store at
// once even if the removal is interrupted (leftovers are swept at the next start).
common::Status removeTree(const fs::path& root, const fs::path& dir) {
  const fs::path aside =
      root / (".trash-" + dir.filename().string() + "-" + std::to_string(common::nowNs()));
  std::error_code ec;
  fs::rename(dir, aside, ec);
  if (ec) return makeError(ErrorCode::kIo, "cannot delete " + dir.string() + ": " + ec.message());
  fs::remove_all(aside, ec);
  return common::Ok{};
}

}  // namespace

common::Result<std::unique_ptr<StoreAdmin>> StoreAdmin::create(const fs::path& root,
                                                               core::MapServer& server,
                                                               SessionJournals* journals,
                                                               const StoreAdminOptions& options) {
  auto admin = std::unique_ptr<StoreAdmin>(new StoreAdmin(root, server, journals, options));
  std::error_code ec;
  if (!options.writable) {
    if (!fs::is_directory(root, ec)) {
      return makeError(ErrorCode::kNotFound, "no store at " + root.string());
    }
    return admin;
  }
  if (journals == nullptr) {
    return makeError(ErrorCode::kInvalidArgument, "a writable store needs the journals");
  }
  auto files = SessionStore::open(root);
  if (!files) return files.error();
  admin->files_.emplace(std::move(files).value());
  // The lock first: on a read-only file system it cannot even be opened, which is an error
  // to say as such (a full disk, below, is a state the server serves through).
  const fs::path lock = root / "store.lock";
  admin->lock_fd_ = ::open(lock.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (admin->lock_fd_ < 0) {
    const int error = errno;
    return makeError(ErrorCode::kIo,
                     "cannot open the store's lock " + lock.string() + ": " + std::strerror(error) +
                         (error == EROFS ? " (the store's file system is mounted read-only; a "
                                           "server must write its journals: mount it writable, "
                                           "or read it with stereomap-store)"
                                         : ""));
  }
  if (::flock(admin->lock_fd_, LOCK_EX | LOCK_NB) != 0) {
    return makeError(ErrorCode::kConflict,
                     "the store " + root.string() +
                         " is in use by another stereomap-server or stereomap-store (it holds " +
                         lock.string() + "); stop it, or use the running server's REST API");
  }
  if (auto probed = admin->files_->probe(); !probed) {
    // A full disk: serve what the store holds; writes resume once one succeeds.
    server.reportStoreProblem(probed.error().message);
  }
  admin->openCatalog();
  return admin;
}

void StoreAdmin::openCatalog() {
  auto catalog = Catalog::open(root_);
  if (!catalog) {  // the journals are the truth: go on without, try again at a checkpoint
    catalog_warning_ = catalog.error().message + "; the catalog is rebuilt once it can be written";
    return;
  }
  catalog_ = std::move(catalog).value();
  catalog_warning_ = catalog_->warning();
}

StoreAdmin::~StoreAdmin() {
  if (lock_fd_ >= 0) ::close(lock_fd_);  // releases the lock
}

common::Status StoreAdmin::requireWritable(const char* what) const {
  if (options_.writable) return common::Ok{};
  return makeError(ErrorCode::kInvalidArgument,
                   std::string("cannot ") + what + ": the store is open read-only");
}

bool StoreAdmin::isClosedOnDisk(const std::string& id) const {
  std::error_code ec;
  return core::isValidId(id) && fs::exists(root_ / id / kClosedMarker, ec);
}

std::vector<std::string> StoreAdmin::storedIds() const {
  std::vector<std::string> ids;
  const auto entries = common::directoryEntries(root_);
  if (!entries) return ids;
  for (const auto& path : *entries) {
    const std::string name = path.filename().string();
    std::error_code ec;
    // Names that are not session ids are ours (.trash-*, .merge-*): never sessions.
    if (core::isValidId(name) && name[0] != '.' && fs::is_directory(path, ec) &&
        fs::exists(path / kJournalName, ec)) {
      ids.push_back(name);
    }
  }
  std::sort(ids.begin(), ids.end());
  return ids;
}

void StoreAdmin::record(const core::SessionStatus& status) {
  if (!catalog_) return;
  if (auto recorded = catalog_->record(status, journalBytes(root_ / status.id)); !recorded) {
    // Once per cause, not every few seconds while the disk stays full.
    if (catalog_error_ != recorded.error().message) spdlog::warn("{}", recorded.error().message);
    catalog_error_ = recorded.error().message;
  } else {
    catalog_error_.clear();
  }
}

std::vector<RecoveredSession> StoreAdmin::recoverAll() {
  std::lock_guard lock(mutex_);
  std::vector<RecoveredSession> recovered;
  if (options_.writable) {  // leftovers of an interrupted delete or merge
    const auto entries = common::directoryEntries(root_);
    for (const auto& path : entries ? *entries : std::vector<fs::path>{}) {
      const std::string name = path.filename().string();
      std::error_code ec;
      if (name.rfind(".trash-", 0) == 0 || name.rfind(".merge-", 0) == 0 ||
          name.rfind(".import-", 0) == 0) {
        fs::remove_all(path, ec);
      }
    }
  }
  for (const auto& id : storedIds()) {
    if (isClosedOnDisk(id)) {
      server_.markClosed(id);
      const auto status = savedStatus(id);
      record(status);
      rememberClosed(status);
      continue;
    }
    std::error_code ec;
    const auto bytes = fs::file_size(root_ / id / kJournalName, ec);
    spdlog::info("session '{}': recovering from its journal ({:.1f} MB)...", id,
                 ec ? 0.0 : static_cast<double>(bytes) / 1e6);
    const auto started = std::chrono::steady_clock::now();
    auto session = load(id, /*read_only=*/false);
    if (session) {
      session->seconds =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
    }
    if (!session) {
      recovered.push_back({.id = id, .problem = session.error().message});
      continue;
    }
    recovered.push_back(std::move(session).value());
    if (auto live = server_.find(id)) record(live->status());
  }
  return recovered;
}

void StoreAdmin::checkpoint(bool all) {
  // The periodic round never waits behind an open, merge or import (minutes for a long
  // journal): the next round, five seconds later, saves what this one skipped. The last
  // one, at shutdown, waits.
  std::unique_lock lock(mutex_, std::defer_lock);
  if (all) {
    lock.lock();
  } else if (!lock.try_lock()) {
    return;
  }
  if (!options_.writable) return;
  // Degraded with no sample refused lately (no vehicle flying, or a start on a full disk):
  // a test write tells whether there is room again. While samples are refused, only a
  // cloud that fits does.
  if (const auto health = server_.storeHealth();
      !health.ok && common::nowNs() - health.last_failure_ns > 10'000'000'000 && files_->probe()) {
    server_.reportStoreOk();
  }
  if (!catalog_ && server_.storeHealth().ok) openCatalog();
  for (const auto& session : server_.sessions()) {
    const auto status = session->status();
    record(status);
    if (status.read_only || (!all && (!status.ended || status.backlog > 0 || status.refusing))) {
      continue;
    }
    const uint64_t version = status.map_version + status.poses;
    if (saved_versions_[session->id()] == version) continue;
    if (auto saved = files_->save(*session); !saved) {
      server_.reportStoreProblem("session '" + session->id() +
                                 "' not saved: " + saved.error().message);
      // Once per cause, not every few seconds while the disk stays full.
      if (save_errors_[session->id()] != saved.error().message) {
        spdlog::error("session '{}' not saved: {}", session->id(), saved.error().message);
        save_errors_[session->id()] = saved.error().message;
      }
      continue;
    }
    save_errors_.erase(session->id());
    saved_versions_[session->id()] = version;
    spdlog::info("session '{}' saved to {} ({} frames, {} voxels)", session->id(),
                 (root_ / session->id()).string(), status.frames_fused, status.occupied_voxels);
  }
}

common::Result<RecoveredSession> StoreAdmin::load(const std::string& id, bool read_only) {
  const fs::path dir = root_ / id;
  std::error_code ec;
  if (!core::isValidId(id) || !fs::exists(dir / kJournalName, ec)) {
    return makeError(ErrorCode::kNotFound,
                     "no session '" + id + "' in the store " + root_.string());
  }
  // One pass over the journal, in the usual case. Frames the newest snapshot holds are kept
  // without their payloads (they are counted, never fused); the rest is kept whole: poses,
  // corrections and events, and the frames after the snapshot (fewer than --snapshot-every
  // per session). Reading every record whole, as it did, held a long flight's journal in
  // memory twice. A second pass reads the frames again only when the newest snapshot cannot
  // be used (damaged, older than a correction, or a format 1 label), or there is none.
  std::vector<std::pair<uint64_t, fs::path>> snapshots;
  JournalReplay kept;
  auto read = [&] {
    snapshots = snapshotsIn(dir);
    const uint64_t assumed = snapshots.empty() ? 0 : snapshots.front().first;
    kept = {};
    return visitJournal(dir / kJournalName, 0, [&](JournalRecord&& record, uint64_t number) {
      if (auto* frame = std::get_if<proto::CloudFrameMsg>(&record);
          frame != nullptr && (assumed == 0 || number <= assumed)) {
        std::vector<uint8_t>().swap(frame->payload);
      }
      kept.records.push_back(std::move(record));
      kept.numbers.push_back(number);
    });
  };
  auto replay = read();
  if (!replay) return replay.error();
  // A format 1 journal (a store from before issue 13) is upgraded before it is replayed: the
  // replay brings snapshots due, labelled with record numbers, which the upgrade would read
  // as frame counts. A store opened only for reading (stereomap-store show, beside a running
  // server) takes no snapshots and writes nothing: it reads the journal as it is.
  std::string upgrade_problem;
  uint64_t upgrade_lost = 0;
  bool snapshots_allowed = true;
  if (replay->version == 1 && options_.writable) {
    if (auto upgraded = repairJournal(dir); upgraded) {
      spdlog::info("session '{}': journal rewritten in format 2", id);
      if (!upgraded->problem.empty()) {
        upgrade_problem = "format 1 journal upgraded without its damage (" + upgraded->problem +
                          "), the original kept as " + upgraded->original.filename().string();
        upgrade_lost = upgraded->records_lost;
      }
      replay = read();
      if (!replay) return replay.error();
    } else {
      upgrade_problem = "its format 1 journal cannot be upgraded (" + upgraded.error().message +
                        "): served without snapshots until the next start";
      snapshots_allowed = false;
      spdlog::warn("session '{}': {}", id, upgrade_problem);
    }
  }
  for (const auto& name : removeLeftoverTemporaries(dir)) {
    spdlog::info("session '{}': removed {}, left by a write that did not finish", id, name);
  }
  auto created = server_.createSession(id, resolutionOf(dir, options_.default_resolution),
                                       read_only, snapshots_allowed);
  if (!created) return created.error();
  const auto& session = *created;
  session->setOrigin(originOf(dir));
  RecoveredSession result{id};
  result.problem = upgrade_problem;
  if (!replay->problem.empty()) {
    result.problem += (result.problem.empty() ? "" : "; ") + replay->problem;
  }
  result.lost_records = upgrade_lost + replay->lostRecords();
  // Poses and pose corrections first: every frame is fused with its vehicle's newest
  // correction, which needs the poses it corrects.
  const uint64_t newest_correction =
      replayPosesAndCorrections(server_, kept, std::numeric_limits<int64_t>::max(), result.poses);
  // The newest snapshot that loads: it holds every frame up to its record number, even
  // ones the journal has lost since. Else a full replay. One older than the newest
  // correction holds frames where they were before it.
  const auto frame_numbers = frameNumbers(kept);  // a format 1 journal's labels count frames
  uint64_t covered_up_to = 0;
  for (const auto& [label, path] : snapshots) {
    const uint64_t number =
        replay->version == 1 ? legacySnapshotNumber(*replay, frame_numbers, label) : label;
    if (replay->version == 1 && number == 0) continue;  // damage makes the label ambiguous
    if (number < newest_correction) continue;
    std::ifstream ot(path, std::ios::binary);
    if (auto restored = session->restore(ot, number); restored) {
      covered_up_to = number;
      break;
    } else {
      result.problem += (result.problem.empty() ? "" : "; ") + path.filename().string() +
                        " unusable (" + restored.error().message + ")";
    }
  }
  // Frames and session events, in journal order.
  auto ingest = [&](const JournalRecord& record, uint64_t number) {
    replayFrameOrEvent(server_, record, number, covered_up_to, result.frames,
                       result.snapshot_frames);
  };
  if (!snapshots.empty() && covered_up_to == snapshots.front().first && replay->version != 1) {
    for (size_t i = 0; i < kept.records.size(); ++i) ingest(kept.records[i], kept.numbers[i]);
  } else {
    kept = {};
    const auto again =
        visitJournal(dir / kJournalName, 0,
                     [&](JournalRecord&& record, uint64_t number) { ingest(record, number); });
    if (!again) {
      result.problem += (result.problem.empty() ? "" : "; ") +
                        std::string("the journal's frames could not be read again: ") +
                        again.error().message;
    }
  }
  session->waitUntilIdle();
  if (!read_only && journals_ != nullptr) {
    // Ready for appending now, from this reading: the first sample would otherwise read the
    // whole journal again, holding every session's ingest up.
    if (auto opened = journals_->openRecovered(id, *replay); !opened) {
      spdlog::warn("session '{}': its journal will be opened at the first sample: {}", id,
                   opened.error().message);
    }
  }
  return result;
}

common::Result<std::shared_ptr<core::Session>> StoreAdmin::replay(const std::string& id,
                                                                  int64_t until_ns) const {
  const fs::path dir = root_ / id;
  std::error_code ec;
  if (!core::isValidId(id) || !fs::exists(dir / kJournalName, ec)) {
    return makeError(ErrorCode::kNotFound, "no session '" + id + "' in the store");
  }
  return replayUntil(id, resolutionOf(dir, options_.default_resolution), until_ns,
                     [&](bool, const RecordVisitor& visit) -> common::Status {
                       if (auto read = visitJournal(dir / kJournalName, 0, visit); !read) {
                         return read.error();
                       }
                       return common::Ok{};
                     });
}

core::SessionStatus StoreAdmin::savedStatus(const std::string& id) const {
  auto status = core::sessionFromJson(id, readJson(root_ / id / kStatusName));
  status.closed = isClosedOnDisk(id);  // the marker decides, not the saved state
  status.read_only = false;            // not loaded
  if (status.resolution <= 0) status.resolution = resolutionOf(root_ / id, 0);
  return status;
}

std::vector<core::SessionStatus> StoreAdmin::savedSessions() const {
  std::vector<core::SessionStatus> saved;
  for (const auto& id : storedIds()) saved.push_back(savedStatus(id));
  return saved;
}

void StoreAdmin::rememberClosed(const core::SessionStatus& status) {
  std::lock_guard lock(closed_mutex_);
  closed_[status.id] = status;
}

void StoreAdmin::forgetClosed(const std::string& id) {
  std::lock_guard lock(closed_mutex_);
  closed_.erase(id);
}

std::vector<core::SessionStatus> StoreAdmin::closedSessions() const {
  std::vector<core::SessionStatus> closed;
  if (options_.writable) {
    std::lock_guard lock(closed_mutex_);
    for (const auto& [id, status] : closed_) closed.push_back(status);
  } else {  // a tool reading the store: nothing in memory, and no server beside it to wait
    closed = savedSessions();
    std::erase_if(closed, [](const auto& s) { return !s.closed; });
  }
  // By id, as storedIds(); those open read-only are listed with the loaded ones.
  std::erase_if(closed, [&](const auto& s) { return server_.find(s.id) != nullptr; });
  return closed;
}

common::Status StoreAdmin::open(const std::string& id) {
  std::lock_guard lock(mutex_);
  if (server_.find(id))
    return makeError(ErrorCode::kConflict, "session '" + id + "' is already open");
  auto loaded = load(id, /*read_only=*/true);
  if (!loaded) return loaded.error();
  if (!loaded->problem.empty()) spdlog::warn("session '{}': {}", id, loaded->problem);
  spdlog::info("session '{}' opened read-only: {} frames ({} from a snapshot), {} poses", id,
               loaded->frames, loaded->snapshot_frames, loaded->poses);
  if (auto session = server_.find(id)) record(session->status());
  return common::Ok{};
}

common::Status StoreAdmin::close(const std::string& id) {
  std::lock_guard lock(mutex_);
  return closeLocked(id);
}

common::Status StoreAdmin::closeLocked(const std::string& id) {
  if (auto writable = requireWritable("close a session"); !writable) return writable;
  const auto session = server_.find(id);
  if (!session) {
    if (isClosedOnDisk(id))
      return makeError(ErrorCode::kConflict, "session '" + id + "' is already closed");
    return makeError(ErrorCode::kNotFound, "no session '" + id + "'");
  }
  // The final snapshot makes the next open quick; then the map and trajectory files, then
  // the marker: a crash before it leaves an ordinary session that recovery loads again.
  auto snapshot = session->snapshotNow();
  common::Status saved = snapshot ? journals_->saveSnapshot(id, snapshot->first, snapshot->second)
                                  : common::Status(snapshot.error());
  if (!saved) {
    spdlog::warn("session '{}': final snapshot not kept ({}); its next open replays the journal",
                 id, saved.error().message);
  }
  if (auto saved = files_->save(*session, /*closed=*/true); !saved) return saved;
  if (auto marked = common::writeFileAtomically(root_ / id / kClosedMarker, ""); !marked)
    return marked;
  auto status = session->status();
  status.closed = true;
  status.read_only = false;
  record(status);
  rememberClosed(status);
  server_.unload(id);
  journals_->release(id);
  spdlog::info("session '{}' closed into the store ({} frames, {} occupied voxels)", id,
               status.frames_fused, status.occupied_voxels);
  return common::Ok{};
}

common::Status StoreAdmin::remove(const std::string& id) {
  std::lock_guard lock(mutex_);
  if (auto writable = requireWritable("delete a session"); !writable) return writable;
  if (!core::isValidId(id)) return makeError(ErrorCode::kNotFound, "no session '" + id + "'");
  const fs::path dir = root_ / id;
  std::error_code ec;
  const auto session = server_.find(id);
  if (session) {
    const auto status = session->status();
    if (!status.ended && !status.read_only) {
      return makeError(ErrorCode::kConflict,
                       "session '" + id +
                           "' is live (a vehicle of it has not ended its flight): "
                           "close it first");
    }
  } else if (!fs::is_directory(dir, ec)) {
    return makeError(ErrorCode::kNotFound, "no session '" + id + "'");
  }
  journals_->retire(id);  // before the unload: a sample let in now is refused, not reopened
  if (session) {
    session->waitUntilIdle();
    server_.unload(id);
  }
  auto removed = removeTree(root_, dir);
  journals_->readmit(id);
  if (!removed) {
    server_.markClosed(id);  // unloaded, still on disk: it stays closed, and listed so
    auto status = savedStatus(id);
    status.closed = true;
    rememberClosed(status);
    return removed;
  }
  if (catalog_) {
    if (auto erased = catalog_->remove(id); !erased) spdlog::warn("{}", erased.error().message);
  }
  server_.forget(id);
  forgetClosed(id);
  spdlog::info("session '{}' deleted", id);
  return common::Ok{};
}

common::Status StoreAdmin::merge(const core::MergeRequest& request) {
  std::lock_guard lock(mutex_);
  if (auto writable = requireWritable("merge sessions"); !writable) return writable;
  if (const auto problem = request.problem(); !problem.empty()) {
    return makeError(ErrorCode::kInvalidArgument, problem);
  }
  std::error_code ec;
  if (server_.find(request.into) || fs::exists(root_ / request.into, ec)) {
    return makeError(ErrorCode::kConflict, "session '" + request.into + "' already exists");
  }
  // Read twice, a record at a time (a site of many long flights never sits in memory whole):
  // once for each source's vehicles and damage, once to write.
  std::vector<SourceVehicles> vehicles;
  for (const auto& source : request.sources) {
    const std::string& id = source.id;
    if (!fs::exists(root_ / id / kJournalName, ec)) {
      return makeError(ErrorCode::kNotFound, "no session '" + id + "' in the store");
    }
    // Merging re-fuses journaled frames; an imported map has none.
    if (fs::exists(snapshotPath(root_ / id, 0), ec)) {
      return makeError(ErrorCode::kInvalidArgument,
                       "session '" + id + "' is an imported map: it has no frames to merge");
    }
    SourceVehicles named;
    auto replay = visitJournal(root_ / id / kJournalName, 0,
                               [&](JournalRecord&& record, uint64_t) { named.note(record); });
    if (!replay) return replay.error();
    if (!replay->problem.empty()) spdlog::warn("merging session '{}': {}", id, replay->problem);
    vehicles.push_back(std::move(named));
  }
  const MergedRecords merged(request, vehicles);
  const fs::path staging =
      root_ / (".merge-" + request.into + "-" + std::to_string(common::nowNs()));
  fs::create_directories(staging, ec);
  const double resolution =
      resolutionOf(root_ / request.sources.front().id, options_.default_resolution);
  // Born closed: it is opened read-only below, and stays in the store (not loaded at start).
  json meta = json::parse(request.origin.empty() ? "{}" : request.origin, nullptr, false);
  if (!meta.is_object()) meta = json::object();
  meta["resolution"] = resolution;
  common::Status written = common::writeFileAtomically(staging / kMetaName, meta.dump() + "\n");
  if (written) written = common::writeFileAtomically(staging / kClosedMarker, "");
  if (written) {
    auto journal = Journal::open(staging / kJournalName);
    if (!journal) written = journal.error();
    for (size_t source = 0; source < request.sources.size() && written; ++source) {
      auto read = visitJournal(root_ / request.sources[source].id / kJournalName, 0,
                               [&](JournalRecord&& record, uint64_t) {
                                 if (!written) return;
                                 merged.apply(record, source);
                                 if (auto appended = (*journal)->append(record); !appended) {
                                   written = appended.error();
                                 }
                               });
      if (!read && written) written = read.error();
    }
  }
  if (written) {
    fs::rename(staging, root_ / request.into, ec);
    if (ec)
      written = makeError(ErrorCode::kIo,
                          "cannot create session '" + request.into + "': " + ec.message());
  }
  if (!written) {
    fs::remove_all(staging, ec);
    return written;
  }
  server_.markClosed(request.into);  // in the store, closed, whether or not it opens below
  rememberClosed(savedStatus(request.into));
  auto loaded = load(request.into, /*read_only=*/true);
  if (!loaded) return loaded.error();
  spdlog::info("{} sessions merged into '{}': {} frames, {} poses", request.sources.size(),
               request.into, loaded->frames, loaded->poses);
  if (auto session = server_.find(request.into)) record(session->status());
  return common::Ok{};
}

}  // namespace stereomap::store

namespace stereomap::store {

common::Result<RecoveredSession> StoreAdmin::importMap(const fs::path& file,
                                                       const std::string& id) {
  if (auto refused = refuseImport(id); !refused) return refused.error();
  // The whole file is read and checked before anything is written.
  auto map = readImportableMap(file);
  if (!map) return map.error();
  auto imported = importMap(*map, id, {{"imported_from", file.filename().string()}});
  if (imported) spdlog::info("{} imported as session '{}'", file.string(), id);
  return imported;
}

common::Status StoreAdmin::refuseImport(const std::string& id) const {
  if (auto writable = requireWritable("import a map"); !writable) return writable;
  if (!core::isValidId(id)) {
    return makeError(ErrorCode::kInvalidArgument,
                     "session id '" + id.substr(0, 80) + "' is not 1-64 of [A-Za-z0-9._-]");
  }
  std::error_code ec;
  if (server_.find(id) || fs::exists(root_ / id, ec)) {
    return makeError(ErrorCode::kConflict, "session '" + id + "' already exists");
  }
  return common::Ok{};
}

common::Result<RecoveredSession> StoreAdmin::importMap(const ImportableMap& map,
                                                       const std::string& id, const json& about) {
  std::lock_guard lock(mutex_);
  if (auto refused = refuseImport(id); !refused) return refused.error();
  const double resolution = map.resolution;
  std::error_code ec;
  const fs::path staging = root_ / (".import-" + id + "-" + std::to_string(common::nowNs()));
  fs::create_directories(staging, ec);
  json meta = about;
  meta["resolution"] = resolution;
  common::Status written =
      ec ? common::Status(
               makeError(ErrorCode::kIo, "cannot create " + staging.string() + ": " + ec.message()))
         : common::writeFileAtomically(staging / kMetaName, meta.dump() + "\n");
  if (written) written = common::writeFileAtomically(staging / kClosedMarker, "");
  if (written) written = common::writeFileAtomically(snapshotPath(staging, 0), map.ot);
  if (written) {
    auto journal = Journal::open(staging / kJournalName);  // empty: no frames, no poses
    if (!journal) written = journal.error();
  }
  if (written) {
    fs::rename(staging, root_ / id, ec);
    if (ec)
      written = makeError(ErrorCode::kIo, "cannot create session '" + id + "': " + ec.message());
  }
  if (!written) {
    fs::remove_all(staging, ec);
    return written.error();
  }
  server_.markClosed(id);  // in the store, closed, whether or not it opens below (as merge)
  rememberClosed(savedStatus(id));
  auto loaded = load(id, /*read_only=*/true);
  if (!loaded) return loaded.error();
  if (auto session = server_.find(id)) {
    if (auto saved = files_->save(*session, /*closed=*/true); !saved) {
      spdlog::warn("session '{}': map.bt and session.json not written: {}", id,
                   saved.error().message);
    }
    auto status = session->status();
    status.closed = true;
    status.read_only = false;
    record(status);
    rememberClosed(status);
  }
  return loaded;
}

}  // namespace stereomap::store
