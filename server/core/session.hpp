// One mapping session on the server: its occupancy map, fed by a fusion worker thread
// through a bounded queue (so DDS reading never blocks), its vehicles' trajectory, and the
// map's tiles (server/tiles), which the worker keeps current from what each frame changed:
// viewers, counts and exports read the tiles, never the live map. Snapshots and map exports
// are serialised by a forked child (common/forked_write), so fusion stops only for the fork.
//
// A vehicle's pose graph may correct poses it sent (correct()): its frames are fused and its
// trajectory shown corrected from then on, and a thread of the session's own fuses the frames
// it already holds again from the journal with the corrected poses, while the live map goes on;
// the worker swaps the new map in once it has caught up (re-fusion).
//
// Threads: enqueue()/addPose()/correct() from ingest threads; status()/tiles()/trajectory()/
// mapBinary() from any thread; the fusion worker and the re-fusion thread are the session's.
#pragma once

#include <array>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <istream>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "common/geometry.hpp"
#include "common/point_cloud.hpp"
#include "common/result.hpp"
#include "common/worker_pool.hpp"
#include "proto/messages.hpp"
#include "server/core/latency.hpp"
#include "server/core/pose_correction.hpp"
#include "server/core/receipts.hpp"
#include "server/fusion/occupancy_map.hpp"
#include "server/tiles/tile_set.hpp"

namespace stereomap::core {

struct PoseRecord {
  std::string vehicle_id;
  int64_t stamp_ns = 0;
  common::Rigid3 T_map_body;
  // Its vehicle flies in its own frame and is not aligned yet: T_map_body is in that frame, not
  // the session's (viewers leave it out until the join, which bumps the trajectory's version).
  bool held = false;
};

struct FusionJob {
  std::string vehicle_id;
  uint64_t seq = 0;
  int64_t stamp_ns = 0;
  common::PointCloud cloud_camera;
  common::Rigid3 T_map_camera;  // as the vehicle sent it (a correction is applied at fusion)
  double max_range_m = 0;
  // The frame's journal record number; 0: none (no journal), enqueue() numbers it by arrival.
  uint64_t journal_number = 0;
  // When the server got it (live frames only): the lag to its tiles' publication is kept.
  std::chrono::steady_clock::time_point arrived{};
};

// A vehicle in its own frame (its start event said so; proto::VehicleFrame::kOwn): its frames
// are held apart, in a map of their own, until the server has aligned that map with the
// session's (FrameAligner) and joined it.
struct VehicleFrameStatus {
  std::string vehicle_id;
  bool aligned = false;
  uint64_t attempts = 0;  // alignments tried
  std::string reason;     // why the last one was not taken ("" none yet, or taken)
  common::Rigid3 T_session_own = common::Rigid3::identity();  // when aligned
  double overlap = 0, rmse_m = 0;                             // the alignment's fit
  // From its first held frame to the join, on this server (0: joined by recovery).
  double aligned_s = 0;
  size_t held_frames = 0;  // frames in its held map
};

// How one vehicle's frames go into the map: moved by its pose graph's correction, and, for a
// vehicle in its own frame, by its alignment into the session's frame; held apart while it
// has none.
struct Placement {
  std::shared_ptr<const PoseCorrection> correction;
  bool held = false;
  std::optional<common::Rigid3> T_session_own;
  // T_map_x (a body or sensor pose the vehicle sent at `stamp_ns`) in the session's frame.
  common::Rigid3 place(int64_t stamp_ns, const common::Rigid3& T_sent) const;
};

struct SessionStatus {
  std::string id;
  std::vector<std::string> vehicles;  // in order of first appearance
  double resolution = 0;
  uint64_t frames_received = 0;  // clouds taken: fused, waiting, deferred or dropped
  uint64_t frames_fused = 0;
  uint64_t frames_dropped = 0;  // queue full: fusion fell behind (without a journal: lost)
  // Queue full, with a journal: fused later from the journal once the queue drains.
  uint64_t frames_deferred = 0;
  size_t backlog = 0;
  size_t occupied_voxels = 0;
  common::Box3 bounds;
  size_t poses = 0;  // poses taken (the trajectory's length)
  // What the live samples taken for it (every topic, duplicates too) took on the link from its
  // vehicles, as this server counted them since it loaded the session (proto/wire_size.hpp).
  uint64_t bytes_received = 0;
  bool ended = false;
  // Who ended it: "vehicle" (the end events of every vehicle that started) or "silence" (no
  // samples for the server's --vehicle-timeout: the vehicles stopped unseen, e.g. while the
  // server was down).
  std::string ended_by;
  bool read_only = false;     // opened from the store: takes no new samples
  bool closed = false;        // kept in the store only (not loaded)
  double fusion_seconds = 0;  // total time spent inserting clouds and updating tiles
  // From a live frame's arrival (before its journal write) to its tiles' publication.
  LatencyHistogram publish_lag;
  uint64_t map_version = 0;  // the tiles' version: bumps with every change of the map
  uint64_t snapshots = 0;    // snapshots handed to the store
  // The longest time fusion stopped for a snapshot (the fork of the writer).
  double snapshot_stall_max_seconds = 0;
  // Why the last sample could not be journaled ("" once one could again): it was refused.
  std::string store_error;
  uint64_t samples_refused = 0;     // samples the journal could not keep
  uint64_t corrections = 0;         // pose corrections taken (every vehicle's)
  uint64_t refusions = 0;           // maps fused again with corrected poses and swapped in
  bool refusing = false;            // a re-fusion is under way (or waits to start)
  double refusion_seconds = 0;      // the last re-fusion, from its start to the swap
  std::string refusion_error;       // why the last re-fusion failed ("" when it did not)
  uint64_t trajectory_version = 0;  // bumps when poses already shown change (a correction)
  std::string server;  // in a cluster: the address of the server that serves it ("": this one)
  // What made a session that is not a flight, as a JSON object's text ("" for a flight):
  // {"imported_from": FILE}, {"diff": {...}} or {"site": [...]} (docs/PROTOCOL.md).
  std::string origin;
  // Each vehicle's newest own counters (VehicleStatus), and when they arrived (this server's
  // wall clock: a time, not an age, so that a status unchanged reads the same).
  struct VehicleCounters {
    proto::VehicleStatusMsg status;
    int64_t received_ns = 0;
  };
  std::vector<VehicleCounters> vehicle_status;
  std::vector<VehicleFrameStatus> vehicle_frames;  // vehicles in their own frame only
};

// "live", "ended" (its vehicles said so, or fell silent), "opened" (read-only from the store) or
// "closed".
const char* stateName(const SessionStatus& status);

class Session {
 public:
  struct Options {
    double resolution = 0.1;
    size_t queue_capacity = 200;  // frames waiting for fusion before new ones are dropped
    bool read_only = false;       // opened from the store (the MapServer refuses live samples)
    // Every this many fused frames the worker hands a .ot of the map to on_snapshot, with
    // the journal record number of the last frame in it. 0: off.
    // on_snapshot runs on a thread of its own while fusion goes on; a snapshot still being
    // written when the next one is due delays that one to the next frame.
    size_t snapshot_every = 0;
    // And at least this long after the previous one (a cluster's snapshots are megabytes of
    // database writes that commits wait behind; docs/BENCHMARKS.md). 0: no floor.
    std::chrono::milliseconds snapshot_interval{0};
    std::function<common::Status(uint64_t journal_number, const std::string& ot)> on_snapshot;
    std::shared_ptr<common::WorkerPool> pool;  // fusion's helper threads; null: its own
    // Reads the session's journaled frames numbered in (after, up_to] again, in order, as
    // fusion jobs (poses as sent): what re-fusion after a pose correction fuses. Unset (no
    // journal): a correction applies to later frames and the trajectory only.
    std::function<common::Status(uint64_t after, uint64_t up_to,
                                 const std::function<void(FusionJob&&)>& fuse)>
        reread_frames;
  };

  Session(std::string id, const Options& options);
  ~Session();  // finishes the queued frames, then stops the worker
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;

  const std::string& id() const { return id_; }
  bool readOnly() const { return options_.read_only; }
  // Starts from a snapshot (a .ot of the journal's frames up to record `journal_number`);
  // before any enqueue. Fails when the snapshot is damaged or its resolution is not the
  // session's.
  common::Status restore(std::istream& ot, uint64_t journal_number);
  // Counts a frame that the restored snapshot already holds (replayed, not fused again).
  void countCovered(const std::string& vehicle_id);
  // Hands a frame to fusion. When the queue is full: with a journal (reread_frames), the
  // frame is deferred, and fused from the journal once the queue has drained (no snapshot is
  // taken meanwhile, since it would claim to hold the frame); without one, false (counted,
  // dropped). `wait_for_room` blocks until the worker makes room instead (replay at start-up).
  bool enqueue(FusionJob job, bool wait_for_room = false);
  // The session's receipts of its vehicles' streams (receipts.hpp): claim() takes a sample the
  // first time it is seen; check() says what claim() would.
  Claim claim(ReceiptTopic topic, const SampleId& sample);
  Claim check(ReceiptTopic topic, const SampleId& sample);
  // The acknowledgements due (Receipts::takeAcks), with this session's id.
  std::vector<proto::AckMsg> takeAcks();
  uint64_t takeGivenUp(ReceiptTopic topic);  // Receipts::takeGivenUp
  // Why a sample could not be journaled; "" when one was journaled again.
  void noteStoreError(const std::string& error);
  void addPose(const PoseRecord& pose);
  // Before a correction is journaled: from now until the re-fusion that takes it has swapped
  // its map in, no snapshot is taken (so a snapshot numbered after a correction always holds
  // it). withdrawCorrection() when it could not be journaled.
  void announceCorrection();
  void withdrawCorrection();
  // Vehicle `vehicle`'s pose graph corrected these keyframes (stamps of poses it sent,
  // T_map_body as it now believes): the correction of its poses so far. kInvalidArgument when
  // none of the stamps is a pose the vehicle sent.
  common::Result<std::shared_ptr<const PoseCorrection>> correctionFor(
      const std::string& vehicle, std::vector<StampedBodyPose> keyframes) const;
  // Takes it (replacing the vehicle's earlier one): later frames and the trajectory are
  // corrected; with `refuse` the map so far is fused again (live corrections; recovery sets
  // corrections before it fuses).
  void correct(const std::string& vehicle, std::shared_ptr<const PoseCorrection> correction,
               bool refuse);
  // A vehicle's start and end events: the session has ended (by its vehicles) once every
  // vehicle that started has ended, and is live again when one starts.
  void markStarted(const std::string& vehicle);
  void markEnded(const std::string& vehicle);

  // Vehicles in their own frame (VehicleFrameStatus). holdApart: vehicle `vehicle` announced
  // its own frame; from now its frames go to its held map. `live`: a frame of it already in the
  // session's map (sent before the announcement arrived) is taken out by a re-fusion. Returns
  // true when the vehicle is the session's reference: no other vehicle's frames are in the
  // map, so the session's frame is its own (the caller joins it at identity).
  bool holdApart(const std::string& vehicle, bool live);
  // The held vehicles whose map is due for an alignment attempt: at least kMinHeldVoxels
  // occupied and kMinNewHeldFrames frames since the last attempt (kMinNewConfirmingFrames
  // when that attempt found a pose that the next must confirm: a vehicle waits held apart,
  // and may land soon).
  static constexpr size_t kMinHeldVoxels = 1000;
  static constexpr size_t kMinNewHeldFrames = 10;
  static constexpr size_t kMinNewConfirmingFrames = 3;
  std::vector<std::string> alignmentsDue() const;
  // A copy of a held vehicle's map (its own frame); nullptr when it has none.
  std::unique_ptr<fusion::OccupancyMap> heldMap(const std::string& vehicle) const;
  // An attempt's outcome: `T_session_own` found, or not (`reason`). True when it agrees with
  // the previous attempt's (within `max_step_m` and `max_step_deg`), made on a smaller map:
  // two attempts that agree are what a join takes.
  // `attempts`: the vehicle's so far, this one included.
  struct AttemptNoted {
    bool agrees = false;
    uint64_t attempts = 0;
  };
  AttemptNoted noteAttempt(const std::string& vehicle,
                           const std::optional<common::Rigid3>& T_session_own,
                           const std::string& reason, double max_step_m, double max_step_deg);
  // The vehicle's frames go into the map moved by T_session_own from now on, and (`refuse`,
  // live joins) those held so far are fused again into the map by a re-fusion; recovery joins
  // before it fuses. Announce it first (announceCorrection()) when it is journaled.
  void join(const std::string& vehicle, const common::Rigid3& T_session_own, double overlap,
            double rmse_m, bool refuse);
  // The vehicle's state for its acknowledgements (proto::FrameState, T_session_own).
  proto::FrameState frameState(const std::string& vehicle, common::Rigid3* T_session_own) const;
  // A live sample of `bytes` on the link arrived (a new one or DDS history): the vehicle is
  // there. Revives a session that silence had ended.
  void noteLive(int64_t now_ns, size_t bytes);
  // Ends a live session whose vehicles sent nothing for `timeout_ns`; true when it did now.
  bool endIfSilent(int64_t now_ns, int64_t timeout_ns);
  // When a live sample last arrived (its creation when none has).
  int64_t lastLiveNs() const;

  SessionStatus status() const;
  // Says what made this session (SessionStatus::origin), from its store's record of it.
  void setOrigin(std::string origin);
  // SessionStatus::trajectory_version alone (viewers poll it).
  uint64_t trajectoryVersion() const;
  // The newest landing target per vehicle (kept in memory, not journaled: a sighting of the
  // pad is only worth its moment). An older stamp than the one kept is ignored.
  void setLandingTarget(const proto::LandingTargetMsg& target);
  // A vehicle's newest counters (VehicleStatus), kept in memory for status(); at most
  // kMaxVehicleStatuses vehicles (later ones are not kept: false).
  static constexpr size_t kMaxVehicleStatuses = 256;
  bool setVehicleStatus(const proto::VehicleStatusMsg& status);
  std::vector<proto::LandingTargetMsg> landingTargets() const;
  // Each vehicle's newest live cloud as it came, numbered in order of arrival (kept in memory:
  // what the Foxglove server streams). liveClouds(after): those numbered after `after`.
  void setLiveCloud(std::shared_ptr<const proto::CloudFrameMsg> frame);
  std::vector<std::pair<uint64_t, std::shared_ptr<const proto::CloudFrameMsg>>> liveClouds(
      uint64_t after) const;
  // The map as tiles: what viewers and tile requests read.
  const tiles::TileSet& tiles() const { return tiles_; }
  // Occupied voxels (finest), sorted by (x, y, z): read from the tiles (exports, tests).
  std::vector<fusion::VoxelIndex> occupiedVoxels() const;
  // Poses [from, until) in arrival order, except that a vehicle's pose older than its newest
  // (one catching up) goes after its last older one (as corrected); poseCount() in all.
  std::vector<PoseRecord> trajectory(size_t from = 0, size_t until = SIZE_MAX) const;
  size_t poseCount() const;
  // OctoMap binary of the map as it is now (after the frame being fused, if any), written by a
  // forked child; an error when the fork or the child failed.
  common::Result<std::string> mapBinary() const;
  // OctoMap full format (.ot, log-odds kept), likewise.
  common::Result<std::string> mapFull() const;
  // Blocks until every queued frame is fused and no re-fusion is under way (for tests and
  // closing: the map then holds every correction).
  void waitUntilIdle() const;
  // Blocks until every queued frame is fused; a re-fusion may still be under way (shutdown:
  // it is left to recovery, which fuses corrected from the journal).
  void waitUntilFused() const;
  // A .ot of the map and the journal record number it covers up to, once idle (close()).
  common::Result<std::pair<uint64_t, std::string>> snapshotNow() const;

 private:
  void run();
  // On the worker, with the queue drained: the deferred frames, read from the journal.
  void fuseDeferred(std::set<uint64_t> numbers);
  using Corrections = std::map<std::string, Placement>;
  // One frame into the map, the tiles and a re-fusion's tail: the frames fused so far.
  uint64_t fuseIntoMap(FusionJob&& job, const Corrections& corrections);
  Corrections corrections() const;
  // Asks the re-fusion thread for a new map (with the placements as they are now).
  void requestRefusion();
  void refuseLoop();  // the re-fusion thread
  // On the worker, between frames: the re-fused map takes the frames fused since it was read
  // from the journal (the tail) and replaces the live one.
  void swapInRefused();
  uint64_t fusedUpTo() const;
  bool stopping() const;
  // After a fused frame: asks the snapshot writer for a snapshot when one is due.
  void snapshotIfDue(uint64_t fused);
  void writeSnapshots();  // the snapshot writer thread
  // The map serialised by a forked child; the map lock is held only for the fork (its
  // duration goes to `locked_seconds`).
  common::Result<std::string> serialiseForked(bool full, uint64_t* journal_number,
                                              double* locked_seconds) const;

  const std::string id_;
  const Options options_;

  mutable std::mutex queue_mutex_;
  mutable std::condition_variable queue_changed_;
  std::deque<FusionJob> queue_;
  // Journal numbers of frames a full queue deferred (enqueue()); fused by the worker once the
  // queue is empty and no re-fusion is under way (a re-fused map holds those it read). Each
  // leaves the set once it is in the map: snapshots wait while any is here.
  std::set<uint64_t> deferred_;
  bool busy_ = false;
  bool stopping_ = false;

  mutable std::mutex map_mutex_;               // the worker holds it while inserting
  std::unique_ptr<fusion::OccupancyMap> map_;  // replaced (under map_mutex_) by a re-fusion
  // Journal record number of the last frame in map_: written under map_mutex_ with the map,
  // read under queue_mutex_ when a re-fusion starts (hence atomic; found by ThreadSanitizer).
  std::atomic<uint64_t> last_fused_number_{0};
  tiles::TileSet tiles_;        // written by the worker only
  fusion::MapChanges changes_;  // the worker's scratch
  uint64_t snapshot_due_ = 0;   // fused-frame count at which the next snapshot is due (worker)
  std::chrono::steady_clock::time_point last_snapshot_{};  // when one was last asked (worker)
  std::mutex snapshot_mutex_;
  std::condition_variable snapshot_changed_;
  bool snapshot_wanted_ = false, snapshot_writing_ = false, snapshot_stopping_ = false;
  std::thread snapshot_writer_;  // runs while snapshots are on

  mutable std::mutex state_mutex_;
  std::vector<std::string> vehicles_;
  std::string origin_;
  Receipts receipts_;
  // A pose as the session keeps it, for as long as it is loaded: 72 bytes (a PoseRecord,
  // with its id string and padded Eigen types, is 112), in a deque, which grows by blocks
  // where a vector would double and copy (the soak's RSS after warm-up: docs/BENCHMARKS.md).
  struct StoredPose {
    int64_t stamp_ns;
    std::array<double, 3> translation;
    std::array<double, 4> rotation;  // x, y, z, w
    uint32_t vehicle;                // index in vehicles_
    common::Rigid3 body() const;     // T_map_body, exactly as it came
  };
  static_assert(sizeof(StoredPose) == 72);
  uint64_t live_clouds_ = 0;  // numbers them
  std::map<std::string, std::pair<uint64_t, std::shared_ptr<const proto::CloudFrameMsg>>>
      live_cloud_;                                        // by vehicle
  PoseRecord poseRecord(const StoredPose& stored) const;  // under state_mutex_
  std::deque<StoredPose> trajectory_;                     // each vehicle's poses in stamp order
  std::vector<int64_t> newest_pose_ns_;                   // by vehicle index
  uint64_t frames_received_ = 0, frames_fused_ = 0, frames_dropped_ = 0, frames_deferred_ = 0;
  double fusion_seconds_ = 0;
  LatencyHistogram publish_lag_;
  uint64_t snapshots_ = 0;
  double snapshot_stall_max_seconds_ = 0;
  bool ended_ = false;
  std::string ended_by_;
  std::set<std::string> flying_;  // vehicles started and not ended
  int64_t last_live_ns_ = 0;      // the last live sample (or the session's creation)
  uint64_t bytes_received_ = 0;
  std::string store_error_;
  uint64_t samples_refused_ = 0;
  std::map<std::string, std::shared_ptr<const PoseCorrection>> corrections_;  // by vehicle
  // Vehicles in their own frame, and what aligning them found (by vehicle).
  struct HeldVehicle {
    VehicleFrameStatus status;
    std::optional<common::Rigid3> candidate;  // the last attempt's pose, to be confirmed
    size_t frames_at_attempt = 0;
    std::chrono::steady_clock::time_point first_held{};
  };
  std::map<std::string, HeldVehicle> frames_;
  std::set<std::string> in_map_;  // vehicles with frames in the session's map (not held)
  // Held vehicles' maps (their own frames), by vehicle: under map_mutex_, written by the
  // worker.
  std::map<std::string, std::unique_ptr<fusion::OccupancyMap>> held_maps_;
  uint64_t corrections_announced_ = 0;  // announced, not yet set (or withdrawn)
  uint64_t corrections_set_ = 0;        // correct() and join() calls, and holdApart()'s re-fusions
  uint64_t pose_corrections_ = 0;       // correct() calls (the status's count)
  uint64_t corrections_in_map_ = 0;     // correct() calls the map reflects (swapped in)
  uint64_t refusions_ = 0;
  double refusion_seconds_ = 0;
  std::string refusion_error_;  // the last re-fusion failed: why ("" once one succeeds)
  uint64_t trajectory_version_ = 0;
  std::map<std::string, proto::LandingTargetMsg> landing_;  // by vehicle
  // By vehicle: the newest counters and when they arrived (wall clock, ns).
  std::map<std::string, std::pair<proto::VehicleStatusMsg, int64_t>> vehicle_status_;

  // Re-fusion. Under queue_mutex_: the map handed over for the swap and the frames the worker
  // fused since the re-fusion began (poses as sent; the oldest dropped beyond kMaxTail until
  // the re-fusion's last rounds).
  struct Refused {
    std::unique_ptr<fusion::OccupancyMap> map;
    uint64_t up_to = 0;  // journal number of its last frame
    Corrections corrections;
    uint64_t corrections_set = 0;  // how many correct() and join() calls it reflects
  };
  static constexpr size_t kMaxTail = 100;
  std::optional<Refused> refused_;
  bool keep_tail_ = false, tail_bounded_ = true;
  std::deque<FusionJob> tail_;
  uint64_t tail_floor_ = 0;                 // the tail holds every fused frame numbered above this
  std::condition_variable refuse_changed_;  // with queue_mutex_
  bool refuse_wanted_ = false, refusing_ = false;
  std::thread refuser_;  // started by the first correction that asks for re-fusion

  std::thread worker_;
};

}  // namespace stereomap::core
