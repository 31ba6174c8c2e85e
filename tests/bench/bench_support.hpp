// What the server benchmarks share: timing, the process's resident memory, the sim vehicle's
// frames as it would send them, and the Freiburg campus map as a session.
#pragma once

#include <chrono>
#include <cstddef>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

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
// A 0.2 m session of `server` restored from `ot`.
std::shared_ptr<core::Session> campusSession(core::MapServer& server, const std::string& id,
                                             const std::string& ot);

}  // namespace stereomap::bench
