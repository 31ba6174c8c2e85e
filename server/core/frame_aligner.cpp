#include "server/core/frame_aligner.hpp"

#include <sstream>

#include <spdlog/spdlog.h>

#include "common/time.hpp"
#include "proto/pose_fields.hpp"

namespace stereomap::core {

FrameAligner::FrameAligner(MapServer& server, Options options)
    : server_(server), options_(std::move(options)) {
  thread_ = std::thread([this] { run(); });
}

FrameAligner::~FrameAligner() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  stop_changed_.notify_all();
  thread_.join();
}

void FrameAligner::run() {
  // At the ingest threads' priority, above fusion's: on a busy server (two cores, vehicles
  // simulated beside it) an attempt at fusion's took 5 s instead of 1-2, and a vehicle waits
  // held apart for every attempt. Journaling is not slowed: it waits on the disk, and the
  // aligner is one thread.
  for (;;) {
    {
      std::unique_lock lock(mutex_);
      if (stop_changed_.wait_for(lock, options_.every, [this] { return stopping_; })) return;
    }
    for (const auto& session : server_.sessions()) {
      for (const auto& vehicle : session->alignmentsDue()) {
        attempt(*session, vehicle);
        std::lock_guard lock(mutex_);
        if (stopping_) return;
      }
    }
  }
}

bool FrameAligner::attempt(Session& session, const std::string& vehicle) {
  const auto start = std::chrono::steady_clock::now();
  auto held = session.heldMap(vehicle);
  if (!held) return false;
  std::optional<common::Rigid3> found;
  std::string reason;
  double overlap = 0, rmse_m = 0;
  // The session's map as it is now: a forked child writes it, fusion goes on.
  auto bytes = session.mapFull();
  std::unique_ptr<fusion::OccupancyMap> map;
  if (bytes) {
    std::istringstream in(*bytes);
    if (auto loaded = fusion::OccupancyMap::load(in); loaded) map = std::move(*loaded);
  }
  if (!map) {
    reason = "the session's map could not be read";
  } else if (map->occupiedCount() < align::kMinVoxels) {
    reason = "the session's map is still empty";
  } else if (auto aligned = align::alignMaps(*map, *held, options_.align); !aligned) {
    reason = aligned.error().message;
  } else if (!aligned->found) {
    reason = aligned->reason;
  } else {
    found = aligned->T_a_b;
    overlap = aligned->overlap;
    rmse_m = aligned->rmse_m;
  }
  const double resolution = held->resolution();
  const auto [agreed, attempts] = session.noteAttempt(
      vehicle, found, reason, options_.agree_voxels * resolution, options_.agree_deg);
  // The first few attempts and then one in ten: a vehicle that never overlaps is tried for
  // as long as it flies.
  if (!agreed && (attempts <= 5 || attempts % 10 == 0)) {
    spdlog::info(
        "session '{}': vehicle '{}' not aligned yet (attempt {}, {} voxels held, {:.1f} "
        "s): {}",
        session.id(), vehicle, attempts, held->occupiedCount(),
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(),
        found ? "a pose found; the next attempt must agree" : reason);
  }
  if (!agreed) return false;
  proto::FrameAlignmentMsg alignment;
  alignment.vehicle_id = vehicle;
  alignment.session_id = session.id();
  alignment.stamp_ns = common::nowNs();
  proto::fieldsFromRigid(*found, alignment.position, alignment.orientation);
  alignment.overlap = overlap;
  alignment.rmse_m = rmse_m;
  return server_.ingest(alignment, Origin::kLive);
}

}  // namespace stereomap::core
