#include "server/core/map_server.hpp"

#include <thread>

#include <spdlog/spdlog.h>

#include <algorithm>

#include "common/heap.hpp"
#include "common/time.hpp"
#include "proto/pose_fields.hpp"
#include "proto/wire_size.hpp"

namespace stereomap::core {

namespace {
constexpr const char* kReceived = "stereomap_samples_received_total";
constexpr const char* kAccepted = "stereomap_samples_accepted_total";
constexpr const char* kRejected = "stereomap_samples_rejected_total";
constexpr const char* kDropped = "stereomap_fusion_dropped_frames_total";
constexpr const char* kDuplicates = "stereomap_samples_duplicate_total";
constexpr const char* kGivenUp = "stereomap_samples_given_up_total";
constexpr const char* kStoreHealthy = "stereomap_store_healthy";
constexpr const char* kStoreErrors = "stereomap_store_write_errors_total";
constexpr const char* kVehicleBytes = "stereomap_vehicle_received_bytes_total";
constexpr const char* kPoseLatency = "stereomap_vehicle_pose_latency_seconds";
constexpr const char* kPublishLag = "stereomap_session_publish_lag_seconds";
constexpr size_t kMaxVehicleLinks = 1024;
constexpr size_t kMaxVehicleLinksPerSession = 64;
constexpr const char* kOtherVehicles = "(other)";  // no valid id: no vehicle is taken for it
constexpr size_t kLatencyWindow = 100;             // poses: 10 s at 10 Hz
constexpr double kMaxPlausibleLatencyS = 30.0;
}  // namespace

MapServer::MapServer(const MapServerOptions& options)
    : options_(options),
      // Fusion is background work: on a busy machine samples' journaling goes first.
      pool_(std::make_shared<common::WorkerPool>(
          std::max(1u, std::thread::hardware_concurrency()) - 1, /*background=*/true)) {
  metrics_.describe(kReceived, "counter", "DDS samples received, by topic");
  metrics_.describe(kAccepted, "counter", "DDS samples that passed validation, by topic");
  metrics_.describe(kRejected, "counter", "DDS samples rejected, by topic and reason");
  metrics_.describe(kDropped, "counter", "Frames dropped because fusion fell behind");
  metrics_.describe(kDuplicates, "counter",
                    "Samples received again (DDS history after a restart), skipped, by topic");
  metrics_.describe(kGivenUp, "counter",
                    "Samples vehicles gave up before the server had them (a full spool: "
                    "onboard/link/spool.hpp), by topic");
  metrics_.describe(kStoreHealthy, "gauge",
                    "1 when the store can be written, 0 when degraded (a full or failing disk)");
  metrics_.describe(kStoreErrors, "counter", "Failed writes to the store's journals, by topic");
  metrics_.set(kStoreHealthy, {}, 1);
  metrics_.describe(kVehicleBytes, "counter",
                    "Bytes a vehicle's accepted samples took on the link (CDR and packet "
                    "headers, proto/wire_size.hpp), by session, vehicle and topic; vehicles "
                    "past a session's 64th (or the server's 1024th) share vehicle=\"(other)\"");
  metrics_.describe(kPoseLatency, "gauge",
                    "Age of a vehicle's poses on arrival (now - stamp), median and 95th "
                    "percentile of the last 100, by session and vehicle; needs the vehicle's "
                    "clock in step with the server's (one host, NTP or PTP)");
  metrics_.describe("stereomap_sessions", "gauge", "Sessions known to this server");
  metrics_.describe("stereomap_session_frames_fused", "gauge", "Frames fused, by session");
  metrics_.describe("stereomap_session_occupied_voxels", "gauge", "Occupied voxels, by session");
  metrics_.describe(kPublishLag, "gauge",
                    "Seconds from a live frame's arrival to its tiles' publication, by session "
                    "(p50, p95 since the session was loaded)");
  metrics_.describe("stereomap_session_fusion_backlog", "gauge",
                    "Frames waiting for fusion, by session");
  metrics_.describe("stereomap_session_fusion_seconds", "gauge",
                    "Total seconds spent fusing clouds, by session");
  if (common::heapStats()) {  // only when the server runs on jemalloc
    metrics_.describe("stereomap_heap_allocated_bytes", "gauge",
                      "Bytes the allocator has handed out and not got back: live data");
    metrics_.describe("stereomap_heap_resident_bytes", "gauge",
                      "Bytes of the allocator's pages in memory: live data and pages kept "
                      "for reuse");
  }
}

void MapServer::reject(const char* topic, const Rejection& rejection, const std::string& from) {
  metrics_.add(kRejected, {{"topic", topic}, {"reason", rejection.reason}});
  uint64_t count;
  {
    std::lock_guard lock(mutex_);
    count = ++rejections_by_reason_[std::string(topic) + "/" + rejection.reason];
  }
  // The first few of each kind in full, then one in a thousand, so a flood cannot fill logs.
  if (count <= 5 || count % 1000 == 0) {
    spdlog::warn("rejected {} sample from {}: {} ({}; {} of this kind so far)", topic, from,
                 rejection.detail, rejection.reason, count);
  }
}

Session::Options MapServer::sessionOptions(const std::string& id, double resolution, bool read_only,
                                           bool snapshots) const {
  Session::Options session_options{resolution, options_.queue_capacity, read_only};
  session_options.pool = pool_;
  if (options_.archive != nullptr) {
    session_options.reread_frames = [archive = options_.archive, limits = options_.limits, id](
                                        uint64_t after, uint64_t up_to,
                                        const std::function<void(FusionJob &&)>& fuse) {
      return archive->forEachFrame(id, after, up_to,
                                   [&](const proto::CloudFrameMsg& frame, uint64_t number) {
                                     FusionJob job;
                                     if (!fusionJobFrom(frame, limits, number, job))
                                       fuse(std::move(job));
                                   });
    };
  }
  if (options_.snapshots != nullptr && snapshots) {
    session_options.snapshot_every = options_.snapshot_every;
    session_options.snapshot_interval = options_.snapshot_interval;
    session_options.on_snapshot = [sink = options_.snapshots, id](uint64_t journal_number,
                                                                  const std::string& ot) {
      return sink->saveSnapshot(id, journal_number, ot);
    };
  }
  return session_options;
}

std::shared_ptr<Session> MapServer::sessionFor(const std::string& id, const char* topic,
                                               std::optional<Rejection>& refusal) {
  std::lock_guard lock(mutex_);
  if (auto found = sessions_.find(id); found != sessions_.end()) return found->second;
  if (closed_.count(id) != 0) {
    refusal = Rejection{"session_closed", "session '" + id +
                                              "' was closed into the store; a new flight "
                                              "needs a new session id"};
    return nullptr;
  }
  if (sessions_.size() >= options_.max_sessions) {
    refusal = Rejection{"session_limit", std::to_string(options_.max_sessions) +
                                             " sessions is the limit; session '" + id +
                                             "' not started (close old sessions)"};
    return nullptr;
  }
  auto session = std::make_shared<Session>(id, sessionOptions(id, options_.resolution, false));
  sessions_.emplace(id, session);
  order_.push_back(id);
  spdlog::info("session '{}' started (resolution {} m) by a {} sample", id, options_.resolution,
               topic);
  return session;
}

common::Result<std::shared_ptr<Session>> MapServer::createSession(const std::string& id,
                                                                  double resolution, bool read_only,
                                                                  bool snapshots) {
  using common::ErrorCode;
  if (!isValidId(id))
    return common::makeError(ErrorCode::kInvalidArgument, "bad session id '" + id + "'");
  std::lock_guard lock(mutex_);
  if (sessions_.count(id) != 0) {
    return common::makeError(ErrorCode::kConflict, "session '" + id + "' is already loaded");
  }
  if (sessions_.size() >= options_.max_sessions) {
    return common::makeError(ErrorCode::kUnavailable,
                             std::to_string(options_.max_sessions) + " sessions is the limit");
  }
  closed_.erase(id);
  std::erase_if(closed_answers_, [&](const auto& entry) { return std::get<0>(entry.first) == id; });
  auto session =
      std::make_shared<Session>(id, sessionOptions(id, resolution, read_only, snapshots));
  sessions_.emplace(id, session);
  order_.push_back(id);
  return session;
}

std::shared_ptr<Session> MapServer::unload(const std::string& id) {
  std::lock_guard lock(mutex_);
  const auto found = sessions_.find(id);
  if (found == sessions_.end()) return nullptr;
  auto session = std::move(found->second);
  sessions_.erase(found);
  order_.erase(std::find(order_.begin(), order_.end(), id));
  closed_.insert(id);
  forgetLinks(id);
  return session;
}

void MapServer::markClosed(const std::string& id) {
  std::lock_guard lock(mutex_);
  closed_.insert(id);
}

void MapServer::forget(const std::string& id) {
  std::lock_guard lock(mutex_);
  closed_.erase(id);
}

size_t MapServer::vehicleLinks(const std::string& session_id) const {
  size_t count = 0;
  for (auto it = links_.lower_bound({session_id, ""});
       it != links_.end() && it->first.first == session_id; ++it) {
    ++count;
  }
  return count;
}

void MapServer::forgetLinks(const std::string& session_id) {
  std::erase_if(links_, [&](const auto& entry) { return entry.first.first == session_id; });
  metrics_.removeSeries("session", session_id);
}

void MapServer::noteTraffic(const char* topic, const std::string& session_id,
                            const std::string& vehicle_id, size_t bytes,
                            std::optional<int64_t> pose_stamp_ns) {
  std::string vehicle = vehicle_id;
  {
    std::lock_guard lock(mutex_);
    auto found = links_.find({session_id, vehicle_id});
    if (found == links_.end() && links_.size() < kMaxVehicleLinks &&
        vehicleLinks(session_id) < kMaxVehicleLinksPerSession) {
      found = links_.try_emplace({session_id, vehicle_id}).first;
    }
    if (found == links_.end()) {
      vehicle = kOtherVehicles;
    } else if (pose_stamp_ns && *pose_stamp_ns > found->second.newest_pose_ns) {
      // Only stamps from a clock in step with ours tell the link's delay; a vehicle on its
      // own time base (a data set's stamps), and poses older than its newest (history or a
      // spool catching up: their age is the outage's, not the link's) are not counted.
      found->second.newest_pose_ns = *pose_stamp_ns;
      const double age_s = static_cast<double>(common::nowNs() - *pose_stamp_ns) * 1e-9;
      if (age_s > -1.0 && age_s < kMaxPlausibleLatencyS) {
        auto& ring = found->second;
        if (ring.pose_latency_s.size() < kLatencyWindow) {
          ring.pose_latency_s.push_back(age_s);
        } else {
          ring.pose_latency_s[ring.next] = age_s;
          ring.next = (ring.next + 1) % kLatencyWindow;
        }
      }
    }
  }
  metrics_.add(kVehicleBytes, {{"session", session_id}, {"vehicle", vehicle}, {"topic", topic}},
               static_cast<double>(bytes));
}

template <typename Message>
std::shared_ptr<Session> MapServer::admit(const char* topic, const Message& message,
                                          std::optional<Rejection> rejection, Origin origin) {
  const std::string& vehicle_id = message.vehicle_id;
  const std::string& session_id = message.session_id;
  metrics_.add(kReceived, {{"topic", topic}});
  std::shared_ptr<Session> session;
  // The sample itself is bad (the checks of validate.hpp): sending it again cannot help, so its
  // session, when there is one, takes it as received (its stream's acknowledgement passes it).
  // A correction of poses not received yet may be good once they are (a vehicle catching up).
  if constexpr (requires { message.unacked_from; }) {
    if (rejection && rejection->reason != "unknown_poses" && origin == Origin::kLive) {
      if (auto known = find(session_id); known && !known->readOnly()) {
        known->claim(receiptTopicOf(message), SampleId::of(message));
      }
    }
  }
  if (!rejection) session = sessionFor(session_id, topic, rejection);
  if (session && session->readOnly() && origin == Origin::kLive) {
    rejection =
        Rejection{"read_only", "session '" + session_id + "' was opened read-only from the store"};
  }
  if (rejection) {
    reject(topic, *rejection, vehicle_id + "/" + session_id);
    if constexpr (requires { message.unacked_from; }) {
      if (origin == Origin::kLive &&
          (rejection->reason == "session_closed" || rejection->reason == "read_only")) {
        answerClosed(session_id, vehicle_id, message.stream, rejection->detail);
      }
    }
    return nullptr;
  }
  metrics_.add(kAccepted, {{"topic", topic}});
  if (origin == Origin::kLive) {
    std::optional<int64_t> pose_stamp_ns;
    if constexpr (std::is_same_v<Message, proto::PoseMsg>) pose_stamp_ns = message.stamp_ns;
    const size_t bytes = proto::wireBytes(message);
    noteTraffic(topic, session_id, vehicle_id, bytes, pose_stamp_ns);
    session->noteLive(common::nowNs(), bytes);
  }
  return session;
}

template <typename Message>
std::optional<uint64_t> MapServer::record(const char* topic, const Message& message,
                                          Session& session, Origin origin) {
  const ReceiptTopic receipt_topic = receiptTopicOf(message);
  const SampleId sample = SampleId::of(message);
  // A sample already taken, or one too far ahead of its stream's gaps (its sender keeps it).
  auto refused = [&](Claim claim) {
    if (claim == Claim::kDuplicate) {
      metrics_.add(kDuplicates, {{"topic", topic}});
    } else {
      reject(topic,
             {"out_of_window", "seq " + std::to_string(message.seq) +
                                   " lies too far "
                                   "ahead of the stream's missing samples; sent again later"},
             message.vehicle_id + "/" + message.session_id);
    }
    return std::nullopt;
  };
  if (origin != Origin::kLive || options_.log == nullptr) {
    if (const Claim claim = session.claim(receipt_topic, sample); claim != Claim::kNew) {
      return refused(claim);
    }
    return 0;
  }
  // Durable first: a sample the journal could not keep was not received, and is not
  // claimed, so that a vehicle sending it again later is not taken for a duplicate.
  if (const Claim claim = session.check(receipt_topic, sample); claim != Claim::kNew) {
    return refused(claim);
  }
  auto logged = options_.log->append(message);
  if (!logged && logged.error().code == common::ErrorCode::kConflict) {
    // The session is not this server's to record: being deleted, or (in a cluster) owned by
    // another server now. Not the store's fault: it is not degraded for it.
    reject(topic, {"not_recorded", logged.error().message},
           message.vehicle_id + "/" + message.session_id);
    return std::nullopt;
  }
  if (!logged) {
    metrics_.add(kStoreErrors, {{"topic", topic}});
    session.noteStoreError(logged.error().message);
    reportStoreProblem("journal write failed: " + logged.error().message);
    reject(topic, {"journal_failed", logged.error().message},
           message.vehicle_id + "/" + message.session_id);
    return std::nullopt;
  }
  session.claim(receipt_topic, sample);
  if (const uint64_t given_up = session.takeGivenUp(receipt_topic)) {
    metrics_.add(kGivenUp, {{"topic", topic}}, static_cast<double>(given_up));
  }
  session.noteStoreError("");
  // A small pose may still fit where a cloud did not: only a cloud tells there is room again.
  if constexpr (std::is_same_v<Message, proto::CloudFrameMsg>) reportStoreOk();
  return *logged;
}

void MapServer::reportStoreProblem(const std::string& reason) {
  std::lock_guard lock(mutex_);
  const bool was_ok = store_health_.ok;
  const int64_t now = common::nowNs();
  store_health_ = {false, reason, was_ok ? now : store_health_.since_ns, now};
  store_ok_ = false;
  metrics_.set(kStoreHealthy, {}, 0);
  if (was_ok) {
    spdlog::error(
        "store degraded: {}; serving what it has, refusing new samples until a write "
        "succeeds",
        reason);
  }
}

void MapServer::reportStoreOk() {
  if (store_ok_) return;
  std::lock_guard lock(mutex_);
  if (store_health_.ok) return;
  spdlog::info("store writable again (degraded for {:.1f} s: {})",
               (common::nowNs() - store_health_.since_ns) * 1e-9, store_health_.reason);
  store_health_ = {};
  store_ok_ = true;
  metrics_.set(kStoreHealthy, {}, 1);
}

StoreHealth MapServer::storeHealth() const {
  std::lock_guard lock(mutex_);
  return store_health_;
}

std::optional<Rejection> fusionJobFrom(const proto::CloudFrameMsg& frame,
                                       const IngestLimits& limits, uint64_t journal_number,
                                       FusionJob& job) {
  ValidCloud valid;
  if (auto rejection = validateCloudFrame(frame, limits, valid)) return rejection;
  job = {frame.vehicle_id,   frame.seq,         frame.stamp_ns, std::move(valid.cloud_camera),
         valid.T_map_camera, valid.max_range_m, journal_number};
  return std::nullopt;
}

bool MapServer::ingest(const proto::CloudFrameMsg& frame, Origin origin, uint64_t journal_number,
                       std::chrono::steady_clock::time_point arrived) {
  if (arrived == std::chrono::steady_clock::time_point{})
    arrived = std::chrono::steady_clock::now();
  FusionJob job;
  // A covered frame (in the restored snapshot) is counted and claimed, not fused: its payload
  // is not decoded, which was most of a restart's time (measured: docs/BENCHMARKS.md).
  const auto rejection = origin == Origin::kCovered
                             ? validateCloudFrameFields(frame, options_.limits, job.T_map_camera)
                             : fusionJobFrom(frame, options_.limits, journal_number, job);
  auto session = admit("CloudFrame", frame, rejection, origin);
  if (!session) return false;
  const auto logged = record("CloudFrame", frame, *session, origin);
  if (!logged) return false;
  if (origin == Origin::kCovered) {
    session->countCovered(frame.vehicle_id);
    return true;
  }
  if (origin == Origin::kLive) {
    job.journal_number = *logged;
    job.arrived = arrived;
    // A copy of its payload (a few kB as Draco) for live clients (the Foxglove server).
    session->setLiveCloud(std::make_shared<const proto::CloudFrameMsg>(frame));
  }
  const bool queued = session->enqueue(std::move(job), /*wait_for_room=*/origin == Origin::kReplay);
  if (!queued) {
    metrics_.add(kDropped, {{"session", frame.session_id}});
    spdlog::warn("session '{}': fusion is behind ({} frames queued); frame {} dropped",
                 frame.session_id, options_.queue_capacity, frame.seq);
  }
  return true;
}

bool MapServer::ingest(const proto::PoseMsg& pose, Origin origin) {
  ValidPose valid;
  const auto rejection = validatePose(pose, valid);
  auto session = admit("Pose", pose, rejection, origin);
  if (!session || !record("Pose", pose, *session, origin)) return false;
  session->addPose({pose.vehicle_id, valid.stamp_ns, valid.T_map_body});
  return true;
}

bool MapServer::ingest(const proto::SessionEventMsg& event, Origin origin) {
  auto session = admit("SessionEvent", event, validateSessionEvent(event), origin);
  if (!session || !record("SessionEvent", event, *session, origin)) return false;
  if (const double mapped = session->status().resolution;
      event.kind == proto::SessionEventKind::kStarted && origin == Origin::kLive &&
      event.resolution_hint > mapped * 1.001) {
    // The vehicle thins its clouds to coarser voxels than this map's: most of its voxels
    // would get no point (stereomap-onboard --map-resolution).
    spdlog::warn(
        "session '{}': vehicle '{}' thins its clouds to {} m voxels, coarser than this map's {} "
        "m: the map will have holes (start it with --map-resolution {})",
        event.session_id, event.vehicle_id, event.resolution_hint, mapped, mapped);
  }
  if (event.kind == proto::SessionEventKind::kStarted && event.frame == proto::VehicleFrame::kOwn &&
      session->holdApart(event.vehicle_id, origin == Origin::kLive)) {
    // The first vehicle of an empty session: the session's frame is its own.
    proto::FrameAlignmentMsg reference;
    reference.vehicle_id = event.vehicle_id;
    reference.session_id = event.session_id;
    reference.stamp_ns = common::nowNs();
    reference.overlap = 1.0;
    ingest(reference, origin);
  } else if (event.kind == proto::SessionEventKind::kStarted &&
             event.frame == proto::VehicleFrame::kOwn && origin == Origin::kLive) {
    spdlog::info(
        "session '{}': vehicle '{}' flies in its own frame: its clouds are held apart until "
        "its map is aligned with the session's",
        event.session_id, event.vehicle_id);
  }
  if (event.kind == proto::SessionEventKind::kStarted) session->markStarted(event.vehicle_id);
  if (event.kind == proto::SessionEventKind::kEnded) {
    session->markEnded(event.vehicle_id);
    spdlog::info("session '{}': vehicle '{}' ended its flight", event.session_id, event.vehicle_id);
  }
  return true;
}

bool MapServer::ingest(const proto::FrameAlignmentMsg& alignment, Origin origin) {
  auto session = find(alignment.session_id);
  const common::Rigid3 T = proto::rigidFromFields(alignment.position, alignment.orientation);
  const bool finite = T.translation.allFinite() && std::isfinite(alignment.overlap) &&
                      std::isfinite(alignment.rmse_m);
  if (!session || (origin == Origin::kLive && session->readOnly()) ||
      !isValidId(alignment.vehicle_id) || !finite ||
      !common::isUnitQuaternion(common::Quat(alignment.orientation[3], alignment.orientation[0],
                                             alignment.orientation[1], alignment.orientation[2]))) {
    spdlog::warn(
        "session '{}': frame alignment of vehicle '{}' not taken (no such session, or "
        "not a valid transform)",
        alignment.session_id, alignment.vehicle_id);
    return false;
  }
  if (origin == Origin::kLive && options_.log != nullptr) {
    // No snapshot from here until the re-fusion has swapped in: one would claim the journal's
    // alignment without holding the vehicle's frames where it puts them.
    session->announceCorrection();
    if (auto logged = options_.log->append(alignment); !logged) {
      session->withdrawCorrection();
      spdlog::error(
          "session '{}': vehicle '{}' aligned, but the journal cannot keep it ({}): "
          "it stays held apart and is aligned again",
          alignment.session_id, alignment.vehicle_id, logged.error().message);
      return false;
    }
  }
  session->join(alignment.vehicle_id, T, alignment.overlap, alignment.rmse_m,
                origin == Origin::kLive);
  if (origin == Origin::kLive) {
    const auto& t = alignment.position;
    spdlog::info(
        "session '{}': vehicle '{}' aligned into the session's frame: t {:.3f} {:.3f} "
        "{:.3f}, overlap {:.0f}%, rmse {:.3f} m",
        alignment.session_id, alignment.vehicle_id, t[0], t[1], t[2], 100 * alignment.overlap,
        alignment.rmse_m);
  }
  return true;
}

void MapServer::refuse(const proto::RefusedSample& sample) {
  metrics_.add(kReceived, {{"topic", sample.type}});
  reject(sample.type.c_str(), Rejection{sample.reason, sample.detail},
         sample.vehicle_id + "/" + sample.session_id);
}

template <typename Message>
std::shared_ptr<Session> MapServer::admitToLoaded(const char* topic, const Message& message,
                                                  std::optional<Rejection> rejection) {
  if (!rejection && !find(message.session_id)) {
    rejection = Rejection{"unknown_session", "no session '" + message.session_id + "': a " + topic +
                                                 " sample belongs to a loaded one"};
  }
  return admit(topic, message, rejection, Origin::kLive);
}

bool MapServer::ingest(const proto::LandingTargetMsg& target) {
  auto session = admitToLoaded("LandingTarget", target, validateLandingTarget(target));
  if (!session) return false;
  session->setLandingTarget(target);
  return true;
}

bool MapServer::ingest(const proto::VehicleStatusMsg& status) {
  auto session = admitToLoaded("VehicleStatus", status, validateVehicleStatus(status));
  if (!session) return false;
  if (!session->setVehicleStatus(status)) {
    reject("VehicleStatus",
           Rejection{"vehicle_limit", std::to_string(Session::kMaxVehicleStatuses) +
                                          " vehicles' counters are kept per session"},
           status.vehicle_id + "/" + status.session_id);
    return false;
  }
  return true;
}

bool MapServer::ingest(const proto::PoseCorrectionMsg& correction, Origin origin) {
  std::vector<ValidPose> keyframes;
  auto rejection = validatePoseCorrection(correction, keyframes);
  // Made before anything is journaled: one that corrects no pose the server has is refused,
  // not kept.
  std::shared_ptr<const PoseCorrection> made;
  if (!rejection) {
    std::vector<StampedBodyPose> poses;
    poses.reserve(keyframes.size());
    for (const auto& k : keyframes) poses.push_back({k.stamp_ns, k.T_map_body});
    const auto existing = find(correction.session_id);
    auto built =
        existing
            ? existing->correctionFor(correction.vehicle_id, std::move(poses))
            : common::Result<std::shared_ptr<const PoseCorrection>>(common::makeError(
                  common::ErrorCode::kNotFound, "no session '" + correction.session_id +
                                                    "': a correction needs the poses it corrects"));
    if (built) {
      made = std::move(*built);
    } else {
      rejection = Rejection{"unknown_poses", built.error().message};
    }
  }
  auto session = admit("PoseCorrection", correction, rejection, origin);
  if (!session) return false;
  const bool live = origin == Origin::kLive;
  // Announced before it is journaled: no snapshot numbered after it may miss it.
  if (live) session->announceCorrection();
  if (!record("PoseCorrection", correction, *session, origin)) {
    if (live) session->withdrawCorrection();
    return false;
  }
  session->correct(correction.vehicle_id, std::move(made), live);
  if (live) {
    spdlog::info("session '{}': vehicle '{}' corrected {} keyframe poses; fusing its map again",
                 correction.session_id, correction.vehicle_id, correction.keyframes.size());
  }
  return true;
}

void MapServer::endSilentSessions(std::chrono::milliseconds timeout) {
  const int64_t now = common::nowNs();
  for (const auto& session : sessions()) {
    if (session->endIfSilent(now, static_cast<int64_t>(timeout.count()) * 1'000'000)) {
      spdlog::info(
          "session '{}': no samples for {} s: marked ended (its vehicle stopped unseen, "
          "or its link is down; it goes on if samples come again)",
          session->id(), timeout.count() / 1000.0);
    }
  }
}

std::vector<proto::AckMsg> MapServer::takeAcks() {
  std::vector<proto::AckMsg> acks;
  for (const auto& session : sessions()) {
    if (session->readOnly()) continue;
    auto due = session->takeAcks();
    for (auto& ack : due) ack.stamp_ns = common::nowNs();
    acks.insert(acks.end(), std::make_move_iterator(due.begin()),
                std::make_move_iterator(due.end()));
  }
  const int64_t now_ns = common::steadyNs();
  const int64_t every_ns = std::chrono::nanoseconds(kClosedAnswerEvery).count();
  std::lock_guard lock(mutex_);
  for (auto it = closed_answers_.begin(); it != closed_answers_.end();) {
    auto& [key, answer] = *it;
    if (!answer.asked) {
      // Quiet for a minute: the vehicle heard, or is gone.
      it = now_ns - answer.told_ns > 60 * every_ns ? closed_answers_.erase(it) : std::next(it);
      continue;
    }
    if (answer.told_ns == 0 || now_ns - answer.told_ns >= every_ns) {
      proto::AckMsg ack;
      std::tie(ack.session_id, ack.vehicle_id, ack.stream) = key;
      ack.stamp_ns = common::nowNs();
      ack.status = proto::AckStatus::kSessionClosed;
      ack.reason = answer.reason.substr(0, proto::kMaxAckReason);
      acks.push_back(std::move(ack));
      answer.told_ns = now_ns;
      answer.asked = false;
    }
    ++it;
  }
  return acks;
}

void MapServer::answerClosed(const std::string& session_id, const std::string& vehicle_id,
                             uint64_t stream, const std::string& reason) {
  std::lock_guard lock(mutex_);
  const auto key = std::make_tuple(session_id, vehicle_id, stream);
  auto found = closed_answers_.find(key);
  if (found == closed_answers_.end()) {
    if (closed_answers_.size() >= kMaxClosedAnswers) return;
    found = closed_answers_.emplace(key, ClosedAnswer{reason}).first;
  }
  found->second.reason = reason;
  found->second.asked = true;
}

std::vector<std::shared_ptr<Session>> MapServer::sessions() const {
  std::lock_guard lock(mutex_);
  std::vector<std::shared_ptr<Session>> list;
  for (const auto& id : order_) list.push_back(sessions_.at(id));
  return list;
}

std::shared_ptr<Session> MapServer::find(const std::string& id) const {
  std::lock_guard lock(mutex_);
  const auto found = sessions_.find(id);
  return found == sessions_.end() ? nullptr : found->second;
}

std::string MapServer::metricsText() const {
  const auto all = sessions();
  metrics_.set("stereomap_sessions", {}, static_cast<double>(all.size()));
  for (const auto& session : all) {
    const auto status = session->status();
    const Labels labels{{"session", status.id}};
    metrics_.set("stereomap_session_frames_fused", labels,
                 static_cast<double>(status.frames_fused));
    metrics_.set("stereomap_session_occupied_voxels", labels,
                 static_cast<double>(status.occupied_voxels));
    metrics_.set("stereomap_session_fusion_backlog", labels, static_cast<double>(status.backlog));
    metrics_.set("stereomap_session_fusion_seconds", labels, status.fusion_seconds);
    for (const double quantile : {0.5, 0.95}) {
      Labels with_quantile = labels;
      with_quantile.emplace_back("quantile", quantile == 0.5 ? "0.5" : "0.95");
      metrics_.set(kPublishLag, with_quantile, status.publish_lag.quantile(quantile));
    }
  }
  if (const auto heap = common::heapStats()) {
    metrics_.set("stereomap_heap_allocated_bytes", {}, static_cast<double>(heap->allocated));
    metrics_.set("stereomap_heap_resident_bytes", {}, static_cast<double>(heap->resident));
  }
  std::unique_lock lock(mutex_);
  for (const auto& [key, link] : links_) {
    if (link.pose_latency_s.empty()) continue;
    for (const double quantile : {0.5, 0.95}) {
      auto ages = link.pose_latency_s;
      const auto at = ages.begin() + static_cast<std::ptrdiff_t>(quantile * (ages.size() - 1));
      std::nth_element(ages.begin(), at, ages.end());
      metrics_.set(kPoseLatency,
                   {{"session", key.first},
                    {"vehicle", key.second},
                    {"quantile", quantile == 0.5 ? "0.5" : "0.95"}},
                   *at);
    }
  }
  lock.unlock();
  return metrics_.render();
}

}  // namespace stereomap::core
