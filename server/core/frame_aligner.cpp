#include "server/core/frame_aligner.hpp"

#include <sstream>

#include <spdlog/spdlog.h>

#include "common/time.hpp"
#include "common/worker_pool.hpp"
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
  // Aligning can wait; journaling and fusing the vehicles' samples cannot.
  common::runAsBackgroundWork();
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
  if (!session.noteAttempt(vehicle, found, reason, options_.agree_voxels * resolution,
                           options_.agree_deg)) {
    spdlog::debug("session '{}': vehicle '{}' not aligned yet: {}", session.id(), vehicle,
                  found ? "waiting for a second attempt that agrees" : reason);
    return false;
  }
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
