#include "server/core/session.hpp"

#include "common/worker_pool.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>

#include <spdlog/spdlog.h>

#include "common/forked_write.hpp"
#include "common/time.hpp"
#include "proto/pose_fields.hpp"

namespace stereomap::core {

namespace {

// serialiseForked's answer when a snapshot would claim a deferred frame.
constexpr const char* kFramesDeferred = "frames are deferred";

// The vehicle's index in `vehicles` (added when new; never removed, so indices hold).
uint32_t noteVehicle(std::vector<std::string>& vehicles, const std::string& vehicle) {
  const auto found = std::find(vehicles.begin(), vehicles.end(), vehicle);
  if (found != vehicles.end()) return static_cast<uint32_t>(found - vehicles.begin());
  vehicles.push_back(vehicle);
  return static_cast<uint32_t>(vehicles.size() - 1);
}

// Fuses one frame into `map`, placed by its vehicle's entry in `placements` if any; a held
// vehicle's frame is not (false).
bool fuse(fusion::OccupancyMap& map, const FusionJob& job,
          const std::map<std::string, Placement>& placements, fusion::MapChanges* changes) {
  const auto placement = placements.find(job.vehicle_id);
  if (placement != placements.end() && placement->second.held) return false;
  const common::Rigid3 T_map_camera = placement == placements.end()
                                          ? job.T_map_camera
                                          : placement->second.place(job.stamp_ns, job.T_map_camera);
  map.insertCloud(job.cloud_camera, T_map_camera, job.max_range_m, changes);
  return true;
}

}  // namespace

common::Rigid3 Placement::place(int64_t stamp_ns, const common::Rigid3& T_sent) const {
  common::Rigid3 T = correction ? correction->delta(stamp_ns) * T_sent : T_sent;
  if (T_session_own) T = *T_session_own * T;
  return T;
}

const char* stateName(const SessionStatus& status) {
  if (status.closed) return "closed";
  if (status.read_only) return "opened";
  return status.ended ? "ended" : "live";
}

Session::Session(std::string id, const Options& options)
    : id_(std::move(id)),
      options_(options),
      map_(std::make_unique<fusion::OccupancyMap>(fusion::OccupancyMap::Options{
          .resolution = options.resolution, .pool = options.pool.get()})),
      tiles_(id_, options.resolution),
      snapshot_due_(options.snapshot_every),
      last_live_ns_(common::nowNs()) {
  worker_ = std::thread([this] { run(); });
  if (options_.snapshot_every > 0 && options_.on_snapshot) {
    snapshot_writer_ = std::thread([this] { writeSnapshots(); });
  }
}

Session::~Session() {
  {
    std::lock_guard lock(queue_mutex_);
    stopping_ = true;
  }
  queue_changed_.notify_all();
  refuse_changed_.notify_all();
  if (refuser_.joinable()) refuser_.join();
  worker_.join();
  if (snapshot_writer_.joinable()) {
    {
      std::lock_guard lock(snapshot_mutex_);
      snapshot_stopping_ = true;
    }
    snapshot_changed_.notify_one();
    snapshot_writer_.join();
  }
}

Claim Session::claim(ReceiptTopic topic, const SampleId& sample) {
  std::lock_guard state(state_mutex_);
  return receipts_.claim(topic, sample);
}

Claim Session::check(ReceiptTopic topic, const SampleId& sample) {
  std::lock_guard state(state_mutex_);
  return receipts_.check(topic, sample);
}

uint64_t Session::takeGivenUp(ReceiptTopic topic) {
  std::lock_guard state(state_mutex_);
  return receipts_.takeGivenUp(topic);
}

std::vector<proto::AckMsg> Session::takeAcks() {
  std::vector<proto::AckMsg> acks;
  {
    std::lock_guard state(state_mutex_);
    acks = receipts_.takeAcks();
  }
  for (auto& ack : acks) {
    ack.session_id = id_;
    common::Rigid3 T = common::Rigid3::identity();
    ack.frame_state = frameState(ack.vehicle_id, &T);
    if (ack.frame_state == proto::FrameState::kAligned) {
      proto::fieldsFromRigid(T, ack.frame_position, ack.frame_orientation);
    }
  }
  return acks;
}

void Session::noteStoreError(const std::string& error) {
  std::lock_guard state(state_mutex_);
  if (!error.empty()) ++samples_refused_;
  store_error_ = error;
}

bool Session::enqueue(FusionJob job, bool wait_for_room) {
  {
    std::lock_guard state(state_mutex_);
    ++frames_received_;
    if (job.journal_number == 0) job.journal_number = frames_received_;
    noteVehicle(vehicles_, job.vehicle_id);
  }
  {
    std::unique_lock lock(queue_mutex_);
    if (wait_for_room) {
      queue_changed_.wait(lock, [this] { return queue_.size() < options_.queue_capacity; });
    }
    if (queue_.size() >= options_.queue_capacity) {
      if (options_.reread_frames) {
        if (deferred_.empty()) {
          spdlog::warn(
              "session '{}': fusion is behind ({} frames queued); frames are deferred and "
              "fused from the journal once the queue drains",
              id_, queue_.size());
        }
        deferred_.insert(job.journal_number);
        std::lock_guard state(state_mutex_);
        ++frames_deferred_;
        return true;
      }
      std::lock_guard state(state_mutex_);
      ++frames_dropped_;
      return false;
    }
    queue_.push_back(std::move(job));
  }
  queue_changed_.notify_all();
  return true;
}

common::Status Session::restore(std::istream& ot, uint64_t journal_number) {
  {
    std::lock_guard lock(map_mutex_);
    if (auto status = map_->readFull(ot); !status) return status;
    last_fused_number_ = journal_number;
    tiles_.rebuild(*map_);
  }
  return common::Ok{};
}

void Session::countCovered(const std::string& vehicle_id) {
  std::lock_guard state(state_mutex_);
  noteVehicle(vehicles_, vehicle_id);
  if (frames_.count(vehicle_id) == 0) in_map_.insert(vehicle_id);
  ++frames_received_;
  ++frames_fused_;
}

void Session::addPose(const PoseRecord& pose) {
  std::lock_guard lock(state_mutex_);
  const auto& q = pose.T_map_body.rotation;
  const auto& t = pose.T_map_body.translation;
  const StoredPose stored{pose.stamp_ns,
                          {t.x(), t.y(), t.z()},
                          {q.x(), q.y(), q.z(), q.w()},
                          noteVehicle(vehicles_, pose.vehicle_id)};
  if (newest_pose_ns_.size() <= stored.vehicle)
    newest_pose_ns_.resize(stored.vehicle + 1, INT64_MIN);
  int64_t& newest = newest_pose_ns_[stored.vehicle];
  if (pose.stamp_ns >= newest) {
    newest = pose.stamp_ns;
    trajectory_.push_back(stored);
    return;
  }
  // Older than the vehicle's newest: it is catching up after an outage. Its poses stay in
  // stamp order (after its last older one), and viewers fetch the trajectory again, as after
  // a correction.
  auto at = trajectory_.end();
  while (at != trajectory_.begin()) {
    const auto& before = *std::prev(at);
    if (before.vehicle == stored.vehicle && before.stamp_ns <= pose.stamp_ns) break;
    --at;
  }
  trajectory_.insert(at, stored);
  ++trajectory_version_;
}

common::Rigid3 Session::StoredPose::body() const {
  const auto& [x, y, z, w] = rotation;
  return {common::Quat(w, x, y, z), common::Vec3(translation[0], translation[1], translation[2])};
}

PoseRecord Session::poseRecord(const StoredPose& stored) const {
  return {vehicles_[stored.vehicle], stored.stamp_ns, stored.body()};
}

void Session::announceCorrection() {
  std::lock_guard lock(state_mutex_);
  ++corrections_announced_;
}

void Session::withdrawCorrection() {
  std::lock_guard lock(state_mutex_);
  if (corrections_announced_ > 0) --corrections_announced_;
}

common::Result<std::shared_ptr<const PoseCorrection>> Session::correctionFor(
    const std::string& vehicle, std::vector<StampedBodyPose> keyframes) const {
  std::vector<StampedBodyPose> sent;
  {
    std::lock_guard lock(state_mutex_);
    const auto index = static_cast<uint32_t>(
        std::find(vehicles_.begin(), vehicles_.end(), vehicle) - vehicles_.begin());
    for (const auto& stored : trajectory_) {
      if (stored.vehicle == index) {
        sent.push_back({stored.stamp_ns, stored.body()});
      }
    }
  }
  auto correction = PoseCorrection::create(std::move(sent), std::move(keyframes));
  if (!correction) return correction.error();
  return std::make_shared<const PoseCorrection>(std::move(*correction));
}

void Session::correct(const std::string& vehicle, std::shared_ptr<const PoseCorrection> correction,
                      bool refuse) {
  {
    std::lock_guard lock(state_mutex_);
    if (refuse && corrections_announced_ > 0) --corrections_announced_;
    corrections_[vehicle] = std::move(correction);
    ++corrections_set_;
    ++pose_corrections_;
    ++trajectory_version_;
    if (!refuse || !options_.reread_frames) corrections_in_map_ = corrections_set_;
  }
  if (refuse && options_.reread_frames) requestRefusion();
}

void Session::requestRefusion() {
  {
    std::lock_guard lock(queue_mutex_);
    refuse_wanted_ = true;
    if (!refuser_.joinable()) refuser_ = std::thread([this] { refuseLoop(); });
  }
  refuse_changed_.notify_all();
}

Session::Corrections Session::corrections() const {
  std::lock_guard lock(state_mutex_);
  Corrections placements;
  for (const auto& [vehicle, correction] : corrections_)
    placements[vehicle].correction = correction;
  for (const auto& [vehicle, held] : frames_) {
    auto& placement = placements[vehicle];
    placement.held = !held.status.aligned;
    if (held.status.aligned) placement.T_session_own = held.status.T_session_own;
  }
  return placements;
}

bool Session::holdApart(const std::string& vehicle, bool live) {
  bool refuse = false, reference = false;
  {
    std::lock_guard lock(state_mutex_);
    if (frames_.count(vehicle) != 0) return false;  // known (a restart, or recovery joined it)
    auto& held = frames_[vehicle];
    held.status.vehicle_id = vehicle;
    reference = live && (in_map_.empty() || (in_map_.size() == 1 && in_map_.count(vehicle)));
    // Frames it sent before this announcement arrived are in the map, in the wrong frame.
    refuse = live && !reference && in_map_.count(vehicle) != 0 && options_.reread_frames;
    if (refuse) ++corrections_set_;
    in_map_.erase(vehicle);
  }
  if (refuse) requestRefusion();
  return reference;
}

std::vector<std::string> Session::alignmentsDue() const {
  std::vector<std::pair<std::string, bool>> held;  // (vehicle, a pose found waits confirming)
  {
    std::lock_guard lock(state_mutex_);
    if (options_.read_only) return {};
    for (const auto& [vehicle, state] : frames_) {
      const size_t new_frames = state.candidate ? kMinNewConfirmingFrames : kMinNewHeldFrames;
      if (!state.status.aligned &&
          state.status.held_frames >= state.frames_at_attempt + new_frames) {
        held.emplace_back(vehicle, state.candidate.has_value());
      }
    }
  }
  // Confirmations first: one attempt from a join, they need not wait behind a vehicle that
  // overlaps nothing (whose refusals take longest).
  std::stable_partition(held.begin(), held.end(), [](const auto& h) { return h.second; });
  std::vector<std::string> due;
  std::lock_guard lock(map_mutex_);
  for (const auto& [vehicle, confirming] : held) {
    const auto map = held_maps_.find(vehicle);
    if (map != held_maps_.end() && map->second->occupiedCount() >= kMinHeldVoxels) {
      due.push_back(vehicle);
    }
  }
  return due;
}

std::unique_ptr<fusion::OccupancyMap> Session::heldMap(const std::string& vehicle) const {
  std::stringstream bytes;
  {
    std::lock_guard lock(map_mutex_);
    const auto map = held_maps_.find(vehicle);
    if (map == held_maps_.end() || !map->second->writeFull(bytes)) return nullptr;
  }
  auto copy = fusion::OccupancyMap::load(bytes);
  return copy ? std::move(*copy) : nullptr;
}

Session::AttemptNoted Session::noteAttempt(const std::string& vehicle,
                                           const std::optional<common::Rigid3>& T_session_own,
                                           const std::string& reason, double max_step_m,
                                           double max_step_deg) {
  std::lock_guard lock(state_mutex_);
  const auto found = frames_.find(vehicle);
  if (found == frames_.end() || found->second.status.aligned) return {};
  auto& held = found->second;
  ++held.status.attempts;
  held.frames_at_attempt = held.status.held_frames;
  held.status.reason = T_session_own ? "" : reason;
  bool agrees = false;
  if (T_session_own && held.candidate) {
    const common::Rigid3 step = held.candidate->inverse() * *T_session_own;
    const double angle_deg = Eigen::AngleAxisd(step.rotation.normalized()).angle() * 180.0 / M_PI;
    agrees = step.translation.norm() <= max_step_m && angle_deg <= max_step_deg;
    if (!agrees) held.status.reason = "two attempts disagree: waiting for a third";
  }
  held.candidate = T_session_own;
  return {agrees, held.status.attempts};
}

void Session::join(const std::string& vehicle, const common::Rigid3& T_session_own, double overlap,
                   double rmse_m, bool refuse) {
  bool refusion = false;
  {
    std::lock_guard lock(state_mutex_);
    auto& held = frames_[vehicle];
    held.status.vehicle_id = vehicle;
    held.status.aligned = true;
    held.status.T_session_own = T_session_own;
    held.status.overlap = overlap;
    held.status.rmse_m = rmse_m;
    held.status.reason.clear();
    if (held.first_held != std::chrono::steady_clock::time_point{}) {
      held.status.aligned_s =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - held.first_held).count();
    }
    if (refuse && corrections_announced_ > 0) --corrections_announced_;
    ++corrections_set_;
    ++trajectory_version_;
    // Only frames held so far need fusing again (a reference joins before it has any), or a
    // re-fusion still to come, whose swap must count this join too.
    refusion = refuse && options_.reread_frames &&
               (held.status.held_frames > 0 || corrections_in_map_ + 1 < corrections_set_);
    if (!refusion) corrections_in_map_ = corrections_set_;
  }
  {
    std::lock_guard lock(map_mutex_);
    held_maps_.erase(vehicle);
  }
  if (refusion) requestRefusion();
}

proto::FrameState Session::frameState(const std::string& vehicle,
                                      common::Rigid3* T_session_own) const {
  std::lock_guard lock(state_mutex_);
  const auto found = frames_.find(vehicle);
  if (found == frames_.end()) return proto::FrameState::kNone;
  if (!found->second.status.aligned) return proto::FrameState::kAligning;
  if (T_session_own != nullptr) *T_session_own = found->second.status.T_session_own;
  return proto::FrameState::kAligned;
}

bool Session::stopping() const {
  std::lock_guard lock(queue_mutex_);
  return stopping_;
}

uint64_t Session::fusedUpTo() const {
  std::lock_guard lock(map_mutex_);
  return last_fused_number_;
}

// Fuses every journaled frame again into a new map with the corrections as they are now, in
// rounds that catch up with the frames fused live meanwhile, and hands the map to the worker
// when the frames still missing from it are in the worker's tail.
void Session::refuseLoop() {
  for (;;) {
    {
      std::unique_lock lock(queue_mutex_);
      refuse_changed_.wait(lock, [this] { return stopping_ || refuse_wanted_; });
      if (stopping_) return;
      refuse_wanted_ = false;
      refusing_ = true;
      keep_tail_ = true;
      tail_bounded_ = true;
      tail_.clear();
      tail_floor_ = last_fused_number_;
    }
    const auto start = std::chrono::steady_clock::now();
    uint64_t corrections_set;
    {
      std::lock_guard lock(state_mutex_);
      corrections_set = corrections_set_;
    }
    const auto corrections = this->corrections();
    auto map = std::make_unique<fusion::OccupancyMap>(fusion::OccupancyMap::Options{
        .resolution = options_.resolution, .pool = options_.pool.get()});
    uint64_t up_to = 0;
    common::Status read = common::Ok{};
    for (int round = 0; read; ++round) {
      const uint64_t fused = fusedUpTo();
      {
        std::lock_guard lock(queue_mutex_);
        if (stopping_) break;
        if (tail_floor_ <= up_to && (fused - up_to <= 10 || round >= 4)) {
          refused_ = Refused{std::move(map), up_to, corrections, corrections_set};
          break;
        }
        // Frames come faster than the journal is read: the tail keeps all from now on, so
        // that the next read or the one after ends the chase.
        if (round >= 3) tail_bounded_ = false;
      }
      read = options_.reread_frames(up_to, fused, [&](FusionJob&& job) {
        if (!stopping()) fuse(*map, job, corrections, nullptr);
      });
      up_to = fused;
    }
    if (!read) {
      // The map stays as it is (and unsnapshotted: recovery fuses the journal again).
      spdlog::error("session '{}': cannot fuse the journal again with corrected poses: {}", id_,
                    read.error().message);
      std::lock_guard state(state_mutex_);
      refusion_error_ = read.error().message;
    }
    queue_changed_.notify_all();  // the worker takes the map between two frames
    std::unique_lock lock(queue_mutex_);
    queue_changed_.wait(lock, [this] { return stopping_ || !refused_; });
    keep_tail_ = false;
    tail_.clear();
    refusing_ = false;
    queue_changed_.notify_all();
    if (read && !stopping_) {
      std::lock_guard state(state_mutex_);
      refusion_error_.clear();
      refusion_seconds_ =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    }
    // At most half the time re-fusing: corrections that come meanwhile wait (the newest of
    // them is taken) for as long as the last re-fusion took, up to a minute.
    const auto took = std::min<std::chrono::steady_clock::duration>(
        std::chrono::steady_clock::now() - start, std::chrono::minutes(1));
    refuse_changed_.wait_for(lock, took, [this] { return stopping_; });
  }
}

void Session::swapInRefused() {
  Refused refused;
  std::deque<FusionJob> tail;
  {
    std::lock_guard lock(queue_mutex_);
    refused = std::move(*refused_);
    refused_.reset();
    tail.swap(tail_);
    // The re-fused map read every journaled frame up to its last one, deferred ones included.
    const auto held = deferred_.upper_bound(refused.up_to);
    const auto taken = static_cast<uint64_t>(std::distance(deferred_.begin(), held));
    deferred_.erase(deferred_.begin(), held);
    std::lock_guard state(state_mutex_);
    frames_fused_ += taken;
  }
  for (const auto& job : tail) {
    if (job.journal_number > refused.up_to) fuse(*refused.map, job, corrections(), nullptr);
  }
  {
    std::lock_guard lock(map_mutex_);
    map_.swap(refused.map);
    tiles_.rebuild(*map_);
  }
  {
    std::lock_guard state(state_mutex_);
    corrections_in_map_ = refused.corrections_set;
    ++refusions_;
  }
  spdlog::info("session '{}': map fused again with corrected poses", id_);
  refused.map.reset();  // the old map, freed off every lock
  queue_changed_.notify_all();
}

void Session::markStarted(const std::string& vehicle) {
  std::lock_guard lock(state_mutex_);
  flying_.insert(vehicle);
  if (ended_by_ == "vehicle") ended_ = false, ended_by_.clear();
}

void Session::markEnded(const std::string& vehicle) {
  std::lock_guard lock(state_mutex_);
  flying_.erase(vehicle);
  // A vehicle whose start was never heard (lost, or before the journal's start) ends the
  // session only when no other is known to fly; one that never ends is caught by silence
  // (endIfSilent).
  if (!flying_.empty()) return;
  ended_ = true;
  ended_by_ = "vehicle";
}

void Session::noteLive(int64_t now_ns, size_t bytes) {
  std::lock_guard lock(state_mutex_);
  last_live_ns_ = std::max(last_live_ns_, now_ns);
  bytes_received_ += bytes;
  if (ended_by_ == "silence") ended_ = false, ended_by_.clear();
}

int64_t Session::lastLiveNs() const {
  std::lock_guard lock(state_mutex_);
  return last_live_ns_;
}

bool Session::endIfSilent(int64_t now_ns, int64_t timeout_ns) {
  std::lock_guard lock(state_mutex_);
  if (ended_ || options_.read_only || now_ns - last_live_ns_ < timeout_ns) return false;
  ended_ = true;
  ended_by_ = "silence";
  return true;
}

void Session::run() {
  // Fusion can wait (its queue, frames deferred to the journal); the ingest path cannot.
  common::runAsBackgroundWork();
  for (;;) {
    FusionJob job;
    {
      std::unique_lock lock(queue_mutex_);
      busy_ = false;
      queue_changed_.notify_all();
      const auto refill = [this] {
        return queue_.empty() && !deferred_.empty() && !refuse_wanted_ && !refusing_;
      };
      queue_changed_.wait(
          lock, [&] { return stopping_ || !queue_.empty() || refused_.has_value() || refill(); });
      if (refused_) {
        busy_ = true;
        lock.unlock();
        swapInRefused();
        continue;
      }
      if (refill()) {
        busy_ = true;
        std::set<uint64_t> numbers = deferred_;  // each stays deferred until it is in the map
        lock.unlock();
        fuseDeferred(std::move(numbers));
        continue;
      }
      // Stopping with everything queued fused (frames deferred behind a re-fusion stay in
      // the journal: recovery fuses them, as no snapshot claims them).
      if (queue_.empty()) return;
      job = std::move(queue_.front());
      queue_.pop_front();
      busy_ = true;
    }
    snapshotIfDue(fuseIntoMap(std::move(job), corrections()));
  }
}

uint64_t Session::fuseIntoMap(FusionJob&& job, const Corrections& corrections) {
  const auto start = std::chrono::steady_clock::now();
  bool in_map = true;
  {
    std::lock_guard lock(map_mutex_);
    in_map = fuse(*map_, job, corrections, &changes_);
    if (!in_map) {
      // Held apart: into the vehicle's own map, in its own frame (its pose graph's corrections
      // applied), which aligning it reads.
      auto& held = held_maps_[job.vehicle_id];
      if (!held) {
        held = std::make_unique<fusion::OccupancyMap>(fusion::OccupancyMap::Options{
            .resolution = options_.resolution, .pool = options_.pool.get()});
      }
      Placement own = corrections.at(job.vehicle_id);
      own.held = false;
      held->insertCloud(job.cloud_camera, own.place(job.stamp_ns, job.T_map_camera),
                        job.max_range_m, nullptr);
      changes_ = {.complete = true, .voxels = {}};
    }
    // Deferred frames come after newer ones: the map holds every frame up to here once
    // nothing is deferred (snapshots wait until then).
    last_fused_number_ = std::max<uint64_t>(last_fused_number_, job.journal_number);
  }
  // The tiles follow the frame's changes without the map; only changes they cannot take
  // (a block larger than a tile) need a walk of the map.
  if (!tiles_.apply(changes_)) {
    std::lock_guard lock(map_mutex_);
    tiles_.rebuild(*map_);
  }
  {
    // A re-fusion begun meanwhile takes this frame from the tail.
    std::lock_guard lock(queue_mutex_);
    if (keep_tail_) {
      tail_.push_back(std::move(job));
      // Bounded while nobody waits to take it: the re-fusion reads further instead.
      while (tail_.size() > kMaxTail && tail_bounded_ && !refused_) {
        tail_floor_ = tail_.front().journal_number;
        tail_.pop_front();
      }
    }
  }
  const auto published = std::chrono::steady_clock::now();
  const double seconds = std::chrono::duration<double>(published - start).count();
  std::lock_guard state(state_mutex_);
  fusion_seconds_ += seconds;
  if (in_map) {
    in_map_.insert(job.vehicle_id);
  } else if (auto held = frames_.find(job.vehicle_id); held != frames_.end()) {
    if (held->second.status.held_frames++ == 0) held->second.first_held = start;
  }
  if (job.arrived != std::chrono::steady_clock::time_point{}) {
    publish_lag_.add(std::chrono::duration<double>(published - job.arrived).count());
  }
  return ++frames_fused_;
}

void Session::fuseDeferred(std::set<uint64_t> numbers) {
  const uint64_t first = *numbers.begin(), last = *numbers.rbegin();
  spdlog::info("session '{}': fusing {} deferred frames from the journal", id_, numbers.size());
  const auto corrections = this->corrections();
  uint64_t fused = 0;
  const auto read = options_.reread_frames(first - 1, last, [&](FusionJob&& job) {
    const uint64_t number = job.journal_number;
    if (numbers.erase(number) == 0) return;
    fused = fuseIntoMap(std::move(job), corrections);
    // Only now: a snapshot taken while a deferred frame is on its way into the map would
    // claim it (its label is the newest frame fused, which queued frames have passed).
    std::lock_guard lock(queue_mutex_);
    deferred_.erase(number);
  });
  if (!read || !numbers.empty()) {
    // Not in the journal after all (damage): the map goes without them.
    spdlog::error("session '{}': {} deferred frames could not be read from the journal{}", id_,
                  numbers.size(), read ? "" : ": " + read.error().message);
    {
      std::lock_guard lock(queue_mutex_);
      for (const uint64_t number : numbers) deferred_.erase(number);
    }
    std::lock_guard state(state_mutex_);
    frames_dropped_ += numbers.size();
  }
  if (fused > 0) snapshotIfDue(fused);
}

void Session::snapshotIfDue(uint64_t fused) {
  if (!snapshot_writer_.joinable() || fused < snapshot_due_) return;
  const auto now = std::chrono::steady_clock::now();
  if (options_.snapshot_interval.count() > 0 && last_snapshot_.time_since_epoch().count() != 0 &&
      now - last_snapshot_ < options_.snapshot_interval) {
    return;
  }
  {
    // Deferred frames are not in the map yet: a snapshot now would claim to hold them.
    std::lock_guard lock(queue_mutex_);
    if (!deferred_.empty()) return;
  }
  {
    // A correction not yet in the map: a snapshot now would not hold it (see
    // announceCorrection()); the next frame after the swap takes it.
    std::lock_guard state(state_mutex_);
    if (corrections_announced_ > 0 || corrections_in_map_ < corrections_set_) return;
  }
  {
    std::lock_guard lock(snapshot_mutex_);
    if (snapshot_wanted_ || snapshot_writing_) return;  // one at a time: next frame again
    snapshot_wanted_ = true;
  }
  snapshot_due_ = fused + options_.snapshot_every;
  last_snapshot_ = now;
  snapshot_changed_.notify_one();
}

// The writer forks (so the child dies with this thread, which outlives every snapshot it
// starts) and waits for the child while fusion goes on.
void Session::writeSnapshots() {
  for (;;) {
    {
      std::unique_lock lock(snapshot_mutex_);
      snapshot_changed_.wait(lock, [this] { return snapshot_stopping_ || snapshot_wanted_; });
      if (!snapshot_wanted_) return;
      snapshot_wanted_ = false;
      snapshot_writing_ = true;
    }
    uint64_t journal_number = 0;
    double stall_seconds = 0;
    auto ot = serialiseForked(/*full=*/true, &journal_number, &stall_seconds);
    if (!ot && ot.error().code == common::ErrorCode::kUnavailable &&
        ot.error().message == kFramesDeferred) {
      std::lock_guard lock(snapshot_mutex_);
      snapshot_writing_ = false;
      continue;
    }
    common::Status saved =
        ot ? options_.on_snapshot(journal_number, *ot) : common::Status(ot.error());
    {
      std::lock_guard state(state_mutex_);
      snapshot_stall_max_seconds_ = std::max(snapshot_stall_max_seconds_, stall_seconds);
      if (saved) ++snapshots_;
    }
    if (!saved) {
      // The journal still holds every frame: only the next recovery gets slower.
      spdlog::warn("session '{}': snapshot not kept: {}", id_, saved.error().message);
    }
    std::lock_guard lock(snapshot_mutex_);
    snapshot_writing_ = false;
  }
}

common::Result<std::string> Session::serialiseForked(bool full, uint64_t* journal_number,
                                                     double* locked_seconds) const {
  std::optional<common::ForkedWrite> job;
  {
    std::lock_guard lock(map_mutex_);  // the map and its journal place, as of one frame
    if (journal_number != nullptr) {
      // A frame deferred since the snapshot was asked for is not in the map: the label would
      // claim it (recovery would then never fuse it). The next snapshot is taken instead.
      std::lock_guard queue(queue_mutex_);
      if (!deferred_.empty()) {
        return common::makeError(common::ErrorCode::kUnavailable, kFramesDeferred);
      }
    }
    const auto locked = std::chrono::steady_clock::now();
    auto started = common::ForkedWrite::start([this, full](std::ostream& out) {
      return full ? map_->writeFull(out) : map_->writeBinary(out);
    });
    if (!started) return started.error();
    job.emplace(std::move(*started));
    if (journal_number != nullptr) *journal_number = last_fused_number_;
    if (locked_seconds != nullptr) {
      *locked_seconds =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - locked).count();
    }
  }
  return job->finish();
}

common::Result<std::pair<uint64_t, std::string>> Session::snapshotNow() const {
  for (;;) {
    waitUntilIdle();
    uint64_t journal_number = 0;
    auto ot = serialiseForked(/*full=*/true, &journal_number, nullptr);
    if (!ot && ot.error().code == common::ErrorCode::kUnavailable &&
        ot.error().message == kFramesDeferred) {
      continue;  // deferred since it was idle: fused next, then the snapshot
    }
    if (!ot) return ot.error();
    return std::pair{journal_number, std::move(*ot)};
  }
}

void Session::setOrigin(std::string origin) {
  std::lock_guard state(state_mutex_);
  origin_ = std::move(origin);
}

SessionStatus Session::status() const {
  SessionStatus status;
  status.id = id_;
  status.resolution = options_.resolution;
  {
    std::lock_guard lock(queue_mutex_);
    status.backlog = queue_.size() + deferred_.size() + (busy_ ? 1 : 0);
  }
  std::lock_guard state(state_mutex_);
  status.vehicles = vehicles_;
  status.origin = origin_;
  for (const auto& [vehicle, kept] : vehicle_status_) {
    status.vehicle_status.push_back({kept.first, kept.second});
  }
  status.frames_received = frames_received_;
  status.frames_fused = frames_fused_;
  status.frames_dropped = frames_dropped_;
  status.frames_deferred = frames_deferred_;
  const auto map = tiles_.summary();
  status.occupied_voxels = map.occupied_voxels;
  status.bounds = map.bounds;
  status.map_version = map.version;
  status.snapshots = snapshots_;
  status.snapshot_stall_max_seconds = snapshot_stall_max_seconds_;
  status.poses = trajectory_.size();
  status.bytes_received = bytes_received_;
  status.ended = ended_;
  status.ended_by = ended_by_;
  status.read_only = options_.read_only;
  status.fusion_seconds = fusion_seconds_;
  status.publish_lag = publish_lag_;
  status.store_error = store_error_;
  status.samples_refused = samples_refused_;
  status.corrections = pose_corrections_;
  status.refusions = refusions_;
  status.refusing = corrections_in_map_ < corrections_set_ && refusion_error_.empty();
  status.refusion_error = refusion_error_;
  status.refusion_seconds = refusion_seconds_;
  status.trajectory_version = trajectory_version_;
  for (const auto& [vehicle, held] : frames_) status.vehicle_frames.push_back(held.status);
  return status;
}

uint64_t Session::trajectoryVersion() const {
  std::lock_guard state(state_mutex_);
  return trajectory_version_;
}

void Session::setLandingTarget(const proto::LandingTargetMsg& target) {
  std::lock_guard state(state_mutex_);
  auto& kept = landing_[target.vehicle_id];
  if (target.stamp_ns >= kept.stamp_ns) kept = target;
}

bool Session::setVehicleStatus(const proto::VehicleStatusMsg& status) {
  std::lock_guard state(state_mutex_);
  auto found = vehicle_status_.find(status.vehicle_id);
  if (found == vehicle_status_.end()) {
    if (vehicle_status_.size() >= kMaxVehicleStatuses) return false;
    found = vehicle_status_.emplace(status.vehicle_id, std::make_pair(status, int64_t{0})).first;
  } else if (status.stamp_ns < found->second.first.stamp_ns) {
    return true;  // an older one, delivered late
  }
  found->second = {status, common::nowNs()};
  return true;
}

std::vector<proto::LandingTargetMsg> Session::landingTargets() const {
  std::lock_guard state(state_mutex_);
  std::vector<proto::LandingTargetMsg> out;
  for (const auto& [vehicle, target] : landing_) out.push_back(target);
  return out;
}

void Session::setLiveCloud(std::shared_ptr<const proto::CloudFrameMsg> frame) {
  std::lock_guard state(state_mutex_);
  const std::string vehicle = frame->vehicle_id;
  live_cloud_[vehicle] = {++live_clouds_, std::move(frame)};
}

std::vector<std::pair<uint64_t, std::shared_ptr<const proto::CloudFrameMsg>>> Session::liveClouds(
    uint64_t after) const {
  std::lock_guard state(state_mutex_);
  std::vector<std::pair<uint64_t, std::shared_ptr<const proto::CloudFrameMsg>>> out;
  for (const auto& [vehicle, cloud] : live_cloud_) {
    if (cloud.first > after) out.push_back(cloud);
  }
  std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  return out;
}

std::vector<fusion::VoxelIndex> Session::occupiedVoxels() const {
  std::vector<fusion::VoxelIndex> voxels;
  for (const auto& tile : tiles_.all()) {
    const auto in_tile = tile->voxels();
    voxels.insert(voxels.end(), in_tile.begin(), in_tile.end());
  }
  std::sort(voxels.begin(), voxels.end());
  return voxels;
}

size_t Session::poseCount() const {
  std::lock_guard state(state_mutex_);
  return trajectory_.size();
}

std::vector<PoseRecord> Session::trajectory(size_t from, size_t until) const {
  std::lock_guard state(state_mutex_);
  until = std::min(until, trajectory_.size());
  if (from >= until) return {};
  std::vector<PoseRecord> poses;
  poses.reserve(until - from);
  for (auto stored = trajectory_.begin() + static_cast<long>(from);
       stored != trajectory_.begin() + static_cast<long>(until); ++stored) {
    poses.push_back(poseRecord(*stored));
  }
  for (auto& pose : poses) {
    const auto correction = corrections_.find(pose.vehicle_id);
    if (correction != corrections_.end()) {
      pose.T_map_body = correction->second->delta(pose.stamp_ns) * pose.T_map_body;
    }
    // A held vehicle's poses stay in its own frame, marked.
    if (const auto held = frames_.find(pose.vehicle_id); held != frames_.end()) {
      pose.held = !held->second.status.aligned;
      if (!pose.held) pose.T_map_body = held->second.status.T_session_own * pose.T_map_body;
    }
    pose.T_map_body.rotation.normalize();
  }
  return poses;
}

common::Result<std::string> Session::mapBinary() const {
  return serialiseForked(/*full=*/false, nullptr, nullptr);
}

common::Result<std::string> Session::mapFull() const {
  return serialiseForked(/*full=*/true, nullptr, nullptr);
}

void Session::waitUntilFused() const {
  std::unique_lock lock(queue_mutex_);
  // Frames deferred behind a re-fusion stay in the journal (no snapshot claims them): a
  // shutdown does not wait for the re-fusion.
  queue_changed_.wait(lock, [this] {
    return queue_.empty() && !busy_ &&
           (deferred_.empty() || refuse_wanted_ || refusing_ || refused_.has_value());
  });
}

void Session::waitUntilIdle() const {
  for (;;) {
    {
      std::unique_lock lock(queue_mutex_);
      queue_changed_.wait(lock, [this] {
        return queue_.empty() && deferred_.empty() && !busy_ && !refuse_wanted_ && !refusing_ &&
               !refused_;
      });
    }
    {
      // A correction set whose re-fusion has not started yet (or one that failed).
      std::lock_guard state(state_mutex_);
      if (corrections_in_map_ >= corrections_set_ || !refusion_error_.empty()) return;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
}

}  // namespace stereomap::core
