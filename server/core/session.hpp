// One mapping session on the server: its occupancy map, fed by a fusion worker thread
// through a bounded queue (so DDS reading never blocks), its vehicles' trajectory, and
// snapshots of the occupied voxels for viewers (the network never reads the live map).
//
// Threads: enqueue()/addPose() from ingest threads; status()/voxels()/trajectory()/
// mapBinary() from any thread; the fusion worker is owned by the session.
#pragma once

#include <condition_variable>
#include <deque>
#include <functional>
#include <istream>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "common/geometry.hpp"
#include "common/point_cloud.hpp"
#include "common/result.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace stereomap::core {

struct PoseRecord {
  std::string vehicle_id;
  int64_t stamp_ns = 0;
  common::Rigid3 T_map_body;
};

struct FusionJob {
  std::string vehicle_id;
  uint64_t seq = 0;
  common::PointCloud cloud_camera;
  common::Rigid3 T_map_camera;
  double max_range_m = 0;
  // The frame's journal record number; 0: none (no journal), enqueue() numbers it by arrival.
  uint64_t journal_number = 0;
};

struct VoxelSnapshot {
  uint64_t version = 0;  // bumps whenever the occupied set may have changed
  double resolution = 0;
  std::vector<fusion::VoxelIndex> voxels;  // sorted
};

struct SessionStatus {
  std::string id;
  std::vector<std::string> vehicles;  // in order of first appearance
  double resolution = 0;
  uint64_t frames_received = 0;
  uint64_t frames_fused = 0;
  uint64_t frames_dropped = 0;  // queue full: fusion fell behind
  size_t backlog = 0;
  size_t occupied_voxels = 0;
  common::Box3 bounds;
  size_t poses = 0;
  bool ended = false;
  // Who ended it: "vehicle" (its end event) or "silence" (no samples for the server's
  // --vehicle-timeout: the vehicle stopped unseen, e.g. while the server was down).
  std::string ended_by;
  bool read_only = false;     // opened from the store: takes no new samples
  bool closed = false;        // kept in the store only (not loaded)
  double fusion_seconds = 0;  // total time spent inserting clouds
  // Why the last sample could not be journaled ("" once one could again): it was refused.
  std::string store_error;
  uint64_t samples_refused = 0;  // samples the journal could not keep
};

// "live", "ended" (its vehicle said so), "opened" (read-only from the store) or "closed".
const char* stateName(const SessionStatus& status);

class Session {
 public:
  struct Options {
    double resolution = 0.1;
    size_t queue_capacity = 200;  // frames waiting for fusion before new ones are dropped
    bool read_only = false;       // opened from the store (the MapServer refuses live samples)
    // Every this many fused frames the worker hands a .ot of the map to on_snapshot, with
    // the journal record number of the last frame in it. 0: off.
    size_t snapshot_every = 0;
    std::function<common::Status(uint64_t journal_number, const std::string& ot)> on_snapshot;
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
  // Hands a frame to fusion; false (and counted) when the queue is full, unless
  // `wait_for_room`, which blocks until the worker makes room (replay at start-up).
  bool enqueue(FusionJob job, bool wait_for_room = false);
  // True the first time a (topic, vehicle) sample with this seq and stamp is seen: false
  // when neither is newer than the last claimed one (a redelivered sample).
  bool claim(const std::string& topic, const std::string& vehicle, uint64_t seq, int64_t stamp_ns);
  // Whether claim() would call this sample a duplicate (it claims nothing).
  bool seen(const std::string& topic, const std::string& vehicle, uint64_t seq,
            int64_t stamp_ns) const;
  // Why a sample could not be journaled; "" when one was journaled again.
  void noteStoreError(const std::string& error);
  void addPose(PoseRecord pose);
  void markEnded();  // by its vehicle's end event
  // A live sample arrived (a new one or DDS history): the vehicle is there. Revives a
  // session that silence had ended.
  void noteLive(int64_t now_ns);
  // Ends a live session whose vehicles sent nothing for `timeout_ns`; true when it did now.
  bool endIfSilent(int64_t now_ns, int64_t timeout_ns);

  SessionStatus status() const;
  std::shared_ptr<const VoxelSnapshot> voxels() const;
  // Poses [from, end) in arrival order.
  std::vector<PoseRecord> trajectory(size_t from = 0) const;
  // TUM lines "t tx ty tz qx qy qz qw" for one vehicle (all vehicles when empty).
  std::string trajectoryTum(const std::string& vehicle_id = "") const;
  // OctoMap binary of the map as it is now (waits for the frame being fused, if any).
  std::string mapBinary() const;
  // OctoMap full format (.ot, log-odds kept).
  std::string mapFull() const;
  // Binary PLY of the occupied voxels' centres (map frame, metres).
  std::string occupiedPly() const;
  // A top-down PNG of the occupied voxels with centres in [z_min, z_max] (one pixel per
  // voxel, or a square of pixels_per_voxel; white occupied, black not); pixel (0, 0) is the
  // voxel with the smallest x and largest y. Empty when nothing is occupied in the band.
  std::string occupancyPng(double z_min, double z_max, int pixels_per_voxel = 1) const;
  // Blocks until every queued frame is fused (for tests and shutdown).
  void waitUntilIdle() const;
  // A .ot of the map and the journal record number it covers up to, once idle (close()).
  std::pair<uint64_t, std::string> snapshotNow() const;

 private:
  void run();
  void publishSnapshot();

  const std::string id_;
  const Options options_;

  mutable std::mutex queue_mutex_;
  mutable std::condition_variable queue_changed_;
  std::deque<FusionJob> queue_;
  bool busy_ = false;
  bool stopping_ = false;

  mutable std::mutex map_mutex_;  // the worker holds it while inserting
  fusion::OccupancyMap map_;
  uint64_t last_fused_number_ = 0;  // journal record number of the last frame in map_

  mutable std::mutex state_mutex_;
  std::vector<std::string> vehicles_;
  std::map<std::pair<std::string, std::string>, std::pair<uint64_t, int64_t>> last_claimed_;
  std::vector<PoseRecord> trajectory_;
  std::shared_ptr<const VoxelSnapshot> snapshot_;
  common::Box3 bounds_;
  uint64_t frames_received_ = 0, frames_fused_ = 0, frames_dropped_ = 0;
  double fusion_seconds_ = 0;
  bool ended_ = false;
  std::string ended_by_;
  int64_t last_live_ns_ = 0;  // the last live sample (or the session's creation)
  std::string store_error_;
  uint64_t samples_refused_ = 0;

  std::thread worker_;
};

}  // namespace stereomap::core
