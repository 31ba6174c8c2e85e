// What the server benchmarks share: timing, the process's resident memory, the sim vehicle's
// frames as it would send them, and the Freiburg campus map as a session.
#pragma once

#include <chrono>
#include <cstddef>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "common/geometry.hpp"
#include "common/point_cloud.hpp"
#include "common/time.hpp"
#include "proto/messages.hpp"
#include "server/core/map_server.hpp"

namespace stereomap::bench {

using Clock = std::chrono::steady_clock;

using common::msSince;
// VmRSS of this process, MB.
double residentMegabytes();
// The sim vehicle's first `count` frames (ground-truth poses, fast matcher), Draco-encoded.
std::vector<proto::CloudFrameMsg> simFrames(size_t count);
// An OctoMap .bt as a .ot snapshot (what a session restores); `octomap_bytes` gets OctoMap's
// own memoryUsage() of it.
std::string campusSnapshot(const std::filesystem::path& path, size_t& octomap_bytes);
// A cloud in the sensor's frame and the sensor's pose.
struct Frame {
  common::PointCloud cloud;
  common::Rigid3 pose;
};
// The fusion benchmark's headline cloud: 50k rays (250 x 200) over 65 x 50 degrees along +x,
// ending 2-10 m away on a rough surface.
Frame frustumFrame();
// Our insertion and OctoMap's insertPointCloud side by side: median ms of inserting `frames`
// into an empty map (its destruction included), `runs` and `stock_runs` times, and how the
// final maps' classifications agree.
struct InsertionComparison {
  double stock_ms = 0, fast_ms = 0;
  double agreement = 0;
};
InsertionComparison compareInsertion(const std::vector<Frame>& frames, double resolution,
                                     double max_range, int runs, int stock_runs, unsigned threads);

// A 0.2 m session of `server` restored from `ot`.
std::shared_ptr<core::Session> campusSession(core::MapServer& server, const std::string& id,
                                             const std::string& ot);

}  // namespace stereomap::bench
