#include "server/cluster/cluster_node.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <limits>
#include <random>
#include <sstream>

#include "common/time.hpp"
#include "server/cluster/cluster_recovery.hpp"
#include "server/core/session_json.hpp"
#include "server/core/validate.hpp"

namespace stereomap::cluster {

using Clock = std::chrono::steady_clock;

namespace {

constexpr const char* kCommitSeconds = "stereomap_cluster_commit_seconds";
constexpr const char* kCommitted = "stereomap_cluster_committed_samples_total";
constexpr const char* kCommitGroups = "stereomap_cluster_commit_groups_total";
constexpr const char* kServed = "stereomap_cluster_sessions_served";
constexpr const char* kStatements = "stereomap_cluster_control_statements_total";

}  // namespace

common::Result<std::unique_ptr<ClusterNode>> ClusterNode::start(
    const ClusterNodeOptions& options, ClusterDb& db, ClusterJournal& journal,
    core::MapServer& server, const std::shared_ptr<proto::Participant>& participant) {
  auto node =
      std::unique_ptr<ClusterNode>(new ClusterNode(options, db, journal, server, participant));
  // Bound to their writers, as the owners' readers are: a vehicle announces only as itself.
  auto events = proto::Reader<proto::SessionEventMsg>::create(
      participant, {proto::kEverySessionPartition}, /*bind_to_writer=*/true);
  if (!events) return events.error();
  node->events_ = std::move(events).value();
  journal.onFenced([raw = node.get()](const std::string& session, const std::string& why) {
    std::lock_guard lock(raw->mutex_);
    raw->fenced_[session] = why;
    raw->wake_.notify_all();
  });
  auto& metrics = server.metrics();
  metrics.describe(kCommitSeconds, "gauge",
                   "Seconds from a sample's append to its commit in the cluster's database, "
                   "over the newest 32768 commits");
  metrics.describe(kCommitted, "counter", "Samples committed to the cluster's database");
  metrics.describe(kCommitGroups, "counter", "Commits (groups of samples) to the database");
  metrics.describe(kServed, "gauge", "Sessions this server serves in the cluster");
  metrics.describe(kStatements, "counter",
                   "Statements this server sent to the database to keep its lease and to see "
                   "and change who owns what (the control plane; not the journal's)");
  for (int i = 0; i < std::max(1, options.recovery_threads); ++i) {
    node->recoverers_.emplace_back([raw = node.get()] { raw->recoveryLoop(); });
  }
  node->reconcile();  // what this server owns already (a restart), queued at once
  node->lease_thread_ = std::thread([raw = node.get()] { raw->leaseLoop(); });
  node->control_ = std::thread([raw = node.get()] { raw->controlLoop(); });
  node->events_thread_ = std::thread([raw = node.get()] { raw->eventLoop(); });
  node->acks_thread_ = std::thread([raw = node.get()] {
    ingest::sendAcksUntil(
        raw->server_,
        [raw](const proto::AckMsg& ack) -> common::Status {
          // A closed session's answer goes out though no server reads its partition.
          if (ack.status != proto::AckStatus::kSessionClosed) {
            std::lock_guard lock(raw->mutex_);
            const auto served = raw->served_.find(ack.session_id);
            if (served == raw->served_.end() || served->second.read_only) {
              return common::Ok{};  // lost meanwhile, or opened read-only
            }
          }
          return raw->acks_.send(ack);
        },
        [raw](std::chrono::milliseconds period) { return !raw->sleepFor(period); });
  });
  return node;
}

ClusterNode::ClusterNode(const ClusterNodeOptions& options, ClusterDb& db, ClusterJournal& journal,
                         core::MapServer& server, std::shared_ptr<proto::Participant> participant)
    : options_(options),
      db_(db),
      journal_(journal),
      server_(server),
      participant_(participant),
      acks_(std::move(participant)) {}

ClusterNode::~ClusterNode() { stop(); }

bool ClusterNode::sleepFor(std::chrono::milliseconds period) {
  std::unique_lock lock(mutex_);
  wake_.wait_for(lock, period, [&] { return stopping_; });
  return !stopping_;
}

void ClusterNode::stop() {
  {
    std::lock_guard lock(mutex_);
    if (stopping_) return;
    stopping_ = true;
  }
  wake_.notify_all();
  recover_wake_.notify_all();
  if (events_) events_->wake();
  for (auto* thread : {&lease_thread_, &control_, &events_thread_, &acks_thread_}) {
    if (thread->joinable()) thread->join();
  }
  for (auto& thread : recoverers_) {
    if (thread.joinable()) thread.join();
  }
  if (superseded()) return;  // nothing here is this process's to hand back
  std::vector<std::string> ids;
  {
    std::lock_guard lock(mutex_);
    for (const auto& [id, served] : served_) ids.push_back(id);
  }
  for (const auto& id : ids) {
    int64_t epoch = 0;
    {
      std::lock_guard lock(mutex_);
      epoch = served_[id].epoch;
    }
    unserve(id, "this server is stopping");
    if (auto released = db_.release({id, db_.serverId(), epoch, 0}, ClusterDb::Leaving::kHandBack);
        !released) {
      spdlog::warn("session '{}': cannot hand it back to the cluster: {}", id,
                   released.error().message);
    }
  }
  if (auto left = db_.leave(); !left) {
    spdlog::warn("cannot leave the cluster cleanly: {}", left.error().message);
  }
}

std::map<std::string, int64_t> ClusterNode::served() const {
  std::lock_guard lock(mutex_);
  std::map<std::string, int64_t> out;
  for (const auto& [id, served] : served_) out[id] = served.epoch;
  return out;
}

bool ClusterNode::superseded() const {
  std::lock_guard lock(mutex_);
  return superseded_;
}

void ClusterNode::controlLoop() {
  // Jittered, so that servers started together do not poll the database in step.
  std::minstd_rand random(std::random_device{}());
  std::uniform_real_distribution<double> jitter(0.8, 1.2);
  const auto period = [&] {
    return std::chrono::milliseconds(
        static_cast<int64_t>(static_cast<double>(options_.poll.count()) * jitter(random)));
  };
  while (sleepFor(period())) reconcile();
}

void ClusterNode::recoveryLoop() {
  for (;;) {
    std::optional<Ownership> next;
    std::string retiring;
    {
      std::unique_lock lock(mutex_);
      recover_wake_.wait(lock,
                         [&] { return stopping_ || !to_recover_.empty() || !to_retire_.empty(); });
      if (stopping_) return;
      if (!to_retire_.empty()) {
        retiring = std::move(to_retire_.front());
        to_retire_.pop_front();
      } else {
        next = std::move(to_recover_.front());
        to_recover_.pop_front();
      }
    }
    if (next) {
      serve(*next);
    } else if (auto retired = retire(retiring, ClusterDb::Leaving::kEnded); !retired) {
      spdlog::warn("session '{}': cannot retire it: {}", retiring, retired.error().message);
    }
    std::lock_guard lock(mutex_);
    recovering_.erase(next ? next->session : retiring);
  }
}

void ClusterNode::queueRetirements() {
  const int64_t now = common::nowNs();
  const int64_t quiet_ns = static_cast<int64_t>(options_.retire_after.count()) * 1'000'000;
  std::vector<std::string> candidates;
  {
    std::lock_guard lock(mutex_);
    for (const auto& [id, served] : served_) {
      if (!served.read_only && !recovering_.contains(id)) candidates.push_back(id);
    }
  }
  for (const auto& id : candidates) {
    const auto session = server_.find(id);
    if (!session || !session->status().ended || now - session->lastLiveNs() < quiet_ns) continue;
    std::lock_guard lock(mutex_);
    if (stopping_ || !served_.contains(id) || !recovering_.insert(id).second) continue;
    to_retire_.push_back(id);
    recover_wake_.notify_one();
  }
}

common::Status ClusterNode::serveNow(const Ownership& session) {
  const auto deadline = Clock::now() + std::chrono::minutes(2);
  for (;;) {
    {
      std::lock_guard lock(mutex_);
      if (served_.contains(session.session)) return common::Ok{};
      if (stopping_ || superseded_) {
        return common::makeError(common::ErrorCode::kUnavailable, "this server is stopping");
      }
      // Not queued or under way on a recovery thread: this thread serves it.
      if (recovering_.insert(session.session).second) break;
    }
    if (Clock::now() > deadline) {
      return common::makeError(common::ErrorCode::kUnavailable,
                               "session '" + session.session + "' is still being loaded");
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  serve(session);
  std::lock_guard lock(mutex_);
  recovering_.erase(session.session);
  if (served_.contains(session.session)) return common::Ok{};
  return common::makeError(
      common::ErrorCode::kUnavailable,
      "session '" + session.session + "' could not be loaded here (the server's log says why)");
}

common::Status ClusterNode::retire(const std::string& id, ClusterDb::Leaving how) {
  Served served;
  {
    std::lock_guard lock(mutex_);
    const auto it = served_.find(id);
    if (it == served_.end()) {
      return common::makeError(common::ErrorCode::kNotFound,
                               "session '" + id + "' is not served here");
    }
    served = std::move(it->second);
    served_.erase(it);
  }
  // No sample is taken from here on: what vehicles send meanwhile stays in their spools, and a
  // vehicle that holds some announces the session again.
  if (served.ingest) {
    served.ingest->stop();
    served.ingest->join();
  }
  std::string summary;
  if (const auto session = server_.find(id)) {
    session->waitUntilIdle();
    // Served again later from this snapshot, not from its whole journal.
    if (!served.read_only) {
      auto snapshot = session->snapshotNow();
      auto saved = snapshot ? journal_.saveSnapshot(id, snapshot->first, snapshot->second)
                            : common::Status(snapshot.error());
      if (!saved) {
        spdlog::warn("session '{}': no snapshot on leaving memory ({}); its journal has it all", id,
                     saved.error().message);
      }
    }
    auto status = session->status();
    status.read_only = false;
    status.closed = how == ClusterDb::Leaving::kClosed;
    status.ended = true;
    summary = core::sessionJson(status);
  }
  auto released = db_.release(
      {id, db_.serverId(), served.epoch, served.resolution, served.read_only}, how, summary);
  journal_.drop(id);
  server_.unload(id);
  server_.forget(id);
  if (!released) {
    // Fenced meanwhile (another owner), or the database is away: the next round reads who owns
    // it and serves it again if it is still this server's.
    reread_ = true;
    return released.error();
  }
  if (options_.admin != nullptr) options_.admin->refresh();  // listed as it is now
  spdlog::info("session '{}' (epoch {}) {}: out of this server's memory", id, served.epoch,
               how == ClusterDb::Leaving::kClosed ? "closed"
                                                  : "ended (served again when a vehicle returns)");
  return common::Ok{};
}

void ClusterNode::leaseLoop() {
  const auto period =
      std::max<std::chrono::milliseconds>(std::chrono::milliseconds(100), db_.options().lease / 4);
  bool down = false;
  do {
    auto renewed = db_.renewLease();
    if (!renewed) {
      if (!down) {
        spdlog::error("cluster: cannot renew this server's lease: {}", renewed.error().message);
      }
      down = true;
      // Samples are refused meanwhile (their vehicles keep them); viewers are served from
      // memory. /healthz says so until the database answers again.
      server_.reportStoreProblem("the cluster's database does not answer: " +
                                 renewed.error().message);
      std::lock_guard lock(mutex_);
      database_down_ = true;
      continue;
    }
    if (*renewed == ClusterDb::Lease::kSuperseded) {
      spdlog::error(
          "cluster: another process has registered as server '{}' since this one started (it "
          "was restarted while this one was paused or cut off); this process serves nothing "
          "more and stops",
          db_.serverId());
      server_.reportStoreProblem("superseded by a newer process with this server id");
      stepDown();
      if (options_.on_superseded) options_.on_superseded();
      return;
    }
    if (down) spdlog::info("cluster: the database answers again");
    if (*renewed == ClusterDb::Lease::kRenewedAfterExpiry) {
      spdlog::error(
          "cluster: this server's lease had run out (it was paused, or the database did not "
          "answer); its sessions may have been taken by others");
    }
    {
      std::lock_guard lock(mutex_);
      database_down_ = false;
      if (down || *renewed == ClusterDb::Lease::kRenewedAfterExpiry) {
        take_orphans_after_ = Clock::now() + db_.options().lease;
      }
    }
    down = false;
    // The store is the database: it answers, so it can be written (a sample refused while it
    // did not would otherwise keep /healthz degraded until the next cloud).
    server_.reportStoreOk();
    wake_.notify_all();
  } while (sleepFor(period));
}

void ClusterNode::stepDown() {
  std::map<std::string, Served> all;
  {
    std::lock_guard lock(mutex_);
    superseded_ = true;
    all.swap(served_);
  }
  for (auto& [id, served] : all) {
    if (served.ingest) {
      served.ingest->stop();
      served.ingest->join();
    }
    journal_.drop(id);
    server_.unload(id);
    server_.forget(id);
    spdlog::warn("session '{}' (epoch {}) no longer served here: superseded", id, served.epoch);
  }
}

void ClusterNode::eventLoop() {
  std::vector<proto::SessionEventMsg> batch;
  std::vector<proto::RefusedSample> refused;
  for (;;) {
    {
      std::lock_guard lock(mutex_);
      if (stopping_) return;
    }
    batch.clear();
    refused.clear();
    events_->take(batch, std::chrono::milliseconds(500), &refused);
    for (const auto& event : batch) {
      bool mine = false;
      {
        std::lock_guard lock(mutex_);
        mine = served_.contains(event.session_id);
        if (!mine && core::isValidId(event.session_id)) {
          announced_.emplace(event.session_id, event.resolution_hint > 0
                                                   ? event.resolution_hint
                                                   : options_.default_resolution);
          auto& who = announcers_[event.session_id];
          if (who.size() < kMaxAnnouncers) who.emplace(event.vehicle_id, event.stream);
          wake_.notify_all();
        }
      }
      // A session this server does not own is another's to journal; its owner's vehicle
      // sends the event again until it is acknowledged, so nothing waits on it here. One it
      // holds read-only refuses it, and its vehicle is told (MapServer::answerClosed).
      if (mine) server_.ingest(event);
    }
    for (const auto& sample : refused) server_.refuse(sample);
  }
}

void ClusterNode::reconcile() {
  // 1. Sessions the database fenced since the last round.
  std::map<std::string, std::string> fenced;
  std::map<std::string, double> to_place;
  std::map<std::string, std::set<std::pair<std::string, uint64_t>>> announcers;
  {
    std::lock_guard lock(mutex_);
    fenced.swap(fenced_);
    to_place.swap(announced_);
    announcers.swap(announcers_);
  }
  for (const auto& [id, why] : fenced) unserve(id, "fenced: another server owns it now");

  // 2. Nothing without the database (the lease thread says when it answers again), nor
  // once superseded.
  bool take_orphans = false;
  {
    std::lock_guard lock(mutex_);
    if (superseded_ || database_down_) {
      for (auto& [id, resolution] : to_place) announced_.emplace(id, resolution);
      return;
    }
    take_orphans = Clock::now() >= take_orphans_after_;
  }

  // 3. Sessions whose vehicles ended them and fell quiet leave memory; sessions vehicles
  // announced are placed (on whichever server is least loaded).
  queueRetirements();
  for (const auto& [id, resolution] : to_place) {
    {
      std::lock_guard lock(mutex_);
      if (served_.contains(id)) continue;
    }
    auto placed = db_.placeSession(id, resolution);
    if (placed && placed->read_only) {
      answerClosed(id, announcers[id], "session '" + id + "' was opened read-only from the store");
    }
    if (!placed) {
      // Closed by an operator: its vehicles are told; or an orphan, which a server takes.
      if (placed.error().code == common::ErrorCode::kConflict) {
        if (auto state = db_.sessionState(id); state && *state == "closed") {
          answerClosed(id, announcers[id],
                       "session '" + id +
                           "' was closed by an operator; a new flight needs a new session id");
        }
        continue;
      }
      spdlog::warn("cluster: cannot place session '{}': {}", id, placed.error().message);
      std::lock_guard lock(mutex_);
      announced_.emplace(id, resolution);  // again next round
    }
  }

  // 4. One cheap statement says whether anything changed (the cluster's version) and whether
  // any session waits for an owner; the scans below run only then, and once a minute in any
  // case (a server row an operator deleted changes no version).
  auto round = db_.poll();
  if (!round) {
    noteRoundFailed(round.error().message);
    return;
  }
  const bool full_round = Clock::now() >= next_full_round_;
  if (full_round) next_full_round_ = Clock::now() + std::chrono::seconds(60);
  if (take_orphans && (round->orphans || full_round)) {
    if (auto taken = db_.takeOrphans(); taken) {
      for (const auto& session : *taken) {
        spdlog::info("cluster: took session '{}' (epoch {}) from a server whose lease ran out",
                     session.session, session.epoch);
      }
    }
  }

  publishMetrics();
  // A recovery that failed (read again: it may have raised no version) counts as a change.
  const bool retry = reread_.exchange(false);
  if (round->version == seen_version_ && !full_round && fenced.empty() && !retry) return;

  // 5. What this server owns now: serve the new ones, drop the ones gone or re-epoched.
  if (options_.admin != nullptr) options_.admin->refresh();
  auto owned = db_.owned();
  if (!owned) {
    noteRoundFailed(owned.error().message);
    return;
  }
  round_failures_ = 0;
  // Read after the version: a change meanwhile raised it again, and the next round reads.
  seen_version_ = round->version;
  std::map<std::string, Ownership> wanted;
  for (const auto& session : *owned) wanted[session.session] = session;
  std::vector<std::pair<std::string, std::string>> gone;
  {
    std::lock_guard lock(mutex_);
    for (const auto& [id, served] : served_) {
      const auto it = wanted.find(id);
      if (it == wanted.end()) {
        gone.emplace_back(id, "fenced: another server owns it now (or it was closed)");
      } else if (it->second.epoch != served.epoch) {
        gone.emplace_back(id, "fenced: its epoch moved on (taken and given back meanwhile)");
      }
    }
  }
  for (const auto& [id, why] : gone) unserve(id, why);
  // The new ones to the recovery threads (each at most once in the queue).
  std::lock_guard lock(mutex_);
  if (stopping_ || superseded_) return;
  for (const auto& [id, session] : wanted) {
    if (served_.contains(id) || recovering_.contains(id)) continue;
    recovering_.insert(id);
    to_recover_.push_back(session);
    recover_wake_.notify_one();
  }
}

void ClusterNode::noteRoundFailed(const std::string& why) {
  // The lease thread says when the database is away; a round that fails while the lease is
  // renewed is worth saying (once, then every 40 rounds: about every 10 s).
  if (round_failures_++ % 40 == 0) {
    spdlog::warn("cluster: a control round failed ({} in a row): {}", round_failures_, why);
  }
}

void ClusterNode::publishMetrics() {
  auto latencies = journal_.commitLatencies();
  auto& metrics = server_.metrics();
  if (!latencies.empty()) {
    for (const auto& [label, q] : {std::pair{"0.5", 0.5}, {"0.99", 0.99}, {"1", 1.0}}) {
      const auto at = latencies.begin() +
                      static_cast<std::ptrdiff_t>(q * static_cast<double>(latencies.size() - 1));
      std::nth_element(latencies.begin(), at, latencies.end());
      metrics.set(kCommitSeconds, {{"quantile", label}}, *at);
    }
  }
  metrics.set(kCommitted, {}, static_cast<double>(journal_.committedSamples()));
  metrics.set(kCommitGroups, {}, static_cast<double>(journal_.committedGroups()));
  metrics.set(kStatements, {}, static_cast<double>(db_.statements()));
  std::lock_guard lock(mutex_);
  metrics.set(kServed, {}, static_cast<double>(served_.size()));
}

void ClusterNode::serve(const Ownership& placed) {
  const auto started = Clock::now();
  // This process's own epoch first: from here on no other (an earlier process under this
  // server id included) commits a row, so what is read next is the whole session.
  auto adopted = db_.adopt(placed);
  if (!adopted) {
    spdlog::warn("session '{}': not adopted: {}", placed.session, adopted.error().message);
    reread_ = true;  // the next round looks again
    return;
  }
  const Ownership& owned = *adopted;
  auto stored = journal_.read(owned.session);
  if (!stored) {
    spdlog::error("session '{}': cannot read it from the database: {}", owned.session,
                  stored.error().message);
    reread_ = true;  // the next round tries again
    return;
  }
  const uint64_t last_number = stored->last_number;
  const uint64_t unreadable = stored->unreadable;
  const uint64_t snapshot_number = stored->snapshot_number;
  const bool has_snapshot = !stored->snapshot.empty();
  size_t frames = 0, poses = 0;
  if (server_.find(owned.session)) server_.unload(owned.session);  // a stale copy
  server_.forget(owned.session);
  // Written at this epoch from here on: the snapshots that fusing the recovered frames makes
  // due are kept (no sample comes before the readers below exist). An opened session is
  // read-only: nothing of it is written.
  if (!owned.read_only) journal_.adopt(owned.session, owned.epoch, last_number);
  if (auto recovered = recoverSession(server_, journal_, owned, *stored, frames, poses,
                                      /*wait_until_fused=*/owned.read_only);
      !recovered) {
    spdlog::error("session '{}': cannot recover it here ({}); handing it back to the cluster",
                  owned.session, recovered.error().message);
    journal_.drop(owned.session);
    server_.unload(owned.session);
    // Another server (or this one, later) takes it: a server that cannot hold it must not keep
    // it ownerless in name only.
    if (auto released = db_.release(owned, ClusterDb::Leaving::kHandBack); !released) {
      spdlog::warn("session '{}': cannot hand it back: {}", owned.session,
                   released.error().message);
    }
    reread_ = true;
    return;
  }
  if (owned.read_only) {
    std::lock_guard lock(mutex_);
    if (stopping_ || superseded_) {
      server_.unload(owned.session);
      server_.forget(owned.session);
      return;
    }
    served_[owned.session] = {owned.epoch, owned.resolution, true, nullptr};
    spdlog::info("session '{}' opened read-only here (epoch {}): {} frames and {} poses",
                 owned.session, owned.epoch, frames, poses);
    return;
  }
  auto ingest =
      ingest::DdsIngest::create(participant_, {proto::sessionPartitions(owned.session)}, false);
  if (!ingest) {
    spdlog::error("session '{}': cannot read it from DDS: {}", owned.session,
                  ingest.error().message);
    journal_.drop(owned.session);
    server_.unload(owned.session);
    reread_ = true;
    return;
  }
  (*ingest)->start(server_);
  {
    std::lock_guard lock(mutex_);
    if (!stopping_ && !superseded_) {
      served_[owned.session] = {owned.epoch, owned.resolution, false, std::move(*ingest)};
    }
  }
  if (*ingest) {  // stopped or superseded meanwhile: not this process's to serve after all
    (*ingest)->stop();
    (*ingest)->join();
    journal_.drop(owned.session);
    server_.unload(owned.session);
    server_.forget(owned.session);
    return;
  }
  spdlog::info(
      "session '{}' served here (epoch {}): {} frames and {} poses recovered{} in {:.2f} s{}",
      owned.session, owned.epoch, frames, poses,
      has_snapshot ? fmt::format(" on its snapshot of record {}", snapshot_number) : "",
      common::msSince(started) / 1000,
      unreadable > 0 ? fmt::format("; {} unreadable records skipped", unreadable) : "");
}

void ClusterNode::answerClosed(const std::string& session,
                               const std::set<std::pair<std::string, uint64_t>>& announcers,
                               const std::string& reason) {
  for (const auto& [vehicle, stream] : announcers) {
    server_.answerClosed(session, vehicle, stream, reason);
  }
}

void ClusterNode::unserve(const std::string& session, const std::string& why) {
  Served served;
  {
    std::lock_guard lock(mutex_);
    const auto it = served_.find(session);
    if (it == served_.end()) return;
    served = std::move(it->second);
    served_.erase(it);
  }
  if (served.ingest) {
    served.ingest->stop();
    served.ingest->join();
  }
  journal_.drop(session);
  server_.unload(session);
  server_.forget(session);
  spdlog::warn("session '{}' (epoch {}) no longer served here: {}", session, served.epoch, why);
}

}  // namespace stereomap::cluster
