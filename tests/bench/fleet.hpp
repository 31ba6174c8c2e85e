// A fleet for stereomap-bench-scale --sessions: vehicles' streams as vehicles send them, fed
// into one in-process MapServer at their real pace through the path DdsIngest takes.
//
// The streams are recorded once from real flights: a stereomap-server process and, for each
// distinct stream, a stereomap-onboard --source sim with the vehicle's default link (thinned
// to the map's voxels, clouds with nothing new skipped, the 1 Mbit/s budget), the typical
// camera and its own room (--seed); what the server journaled is each vehicle's stream, sample
// for sample as sent. Each flight is one lap of the sim's 40 s loop, so a stream can be
// replayed from any point of it, wrapping round: vehicle v plays stream v % K from its own
// phase, with its own session, vehicle id, stream id and seqs.
#pragma once

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <variant>
#include <vector>

#include "proto/dds.hpp"
#include "proto/messages.hpp"

namespace stereomap::bench {

// One recorded sample and its time from the flight's start.
struct FleetSample {
  double t_s = 0;
  std::variant<proto::CloudFrameMsg, proto::PoseMsg, proto::SessionEventMsg> message;
};
struct FleetStream {
  std::vector<FleetSample> samples;  // by time
  double lap_s = 0;                  // the flight's length: replays wrap round after it
  size_t clouds = 0, poses = 0;
  uint64_t cloud_bytes = 0;  // Draco payloads
};

// Records `count` streams of `frames` frames at 10 Hz (seeds 1..count) into `dir`, or reads
// them from there when a previous run left them. Progress on stdout.
std::vector<FleetStream> fleetStreams(const std::filesystem::path& dir, int count, int frames,
                                      int domain);

struct FleetRun {
  int vehicles = 0;
  double seconds = 0;                  // measured (after the warm-up)
  uint64_t clouds = 0, poses = 0;      // fed in the measured window
  uint64_t received = 0, dropped = 0;  // clouds the sessions took; dropped or deferred
  double lag_p50_ms = 0, lag_p95_ms = 0, lag_max_ms = 0;  // arrival to tiles published
  double late_p95_ms = 0;  // how late the feeders handed samples to the server
  double cpu_percent = 0;  // the process's CPU over the window (100 %: one core)
  double rss_mb = 0;       // the process's peak RSS during the run, less `rss_before` (runFleet)
  bool ok(double max_lag_ms) const { return dropped == 0 && lag_p95_ms <= max_lag_ms; }
};

// `vehicles` vehicles for `seconds`: every sample handed to the server when due, one thread for
// clouds and one for poses and events (as DdsIngest's readers), acks taken every 200 ms; a
// store in `store_dir` (journals with fdatasync, snapshots, deferral, as stereomap-server's).
// Lag is counted from when a cloud was due, so a feeder running late counts against it.
// `rss_before`: the process's RSS before the first fleet ran (MB); memory the allocator kept
// from earlier runs counts too, so a run's figure is an upper bound.
FleetRun runFleet(const std::vector<FleetStream>& streams, int vehicles, double seconds,
                  const std::filesystem::path& store_dir, double rss_before);

// The same streams over DDS into a stereomap-server process (issue 55): a participant per
// vehicle, as `identities[v]` when given (DDS Security: the certificate's name is
// `vehicle_ids[v]`), writing in its own partition; every writer matched before the clock
// starts. `only` >= 0: vehicle `only` of the fleet alone (one process per vehicle: Cyclone
// 0.10.2 refuses a second identity's endpoints in one process), its clock starting at
// `start_at` when given. The server's lag and CPU are read from it by the caller.
struct DdsFleetRun {
  double seconds = 0;
  uint64_t clouds = 0, poses = 0;  // written
  double late_p95_ms = 0;          // how late the feeders wrote samples
  double join_s = 0;               // participants made and matched (handshakes included)
  std::string error;               // empty when it ran
};
DdsFleetRun replayOverDds(const std::vector<FleetStream>& streams, int vehicles, double seconds,
                          const proto::DdsOptions& dds, const std::vector<std::string>& vehicle_ids,
                          const std::vector<std::string>& identities, int only = -1,
                          std::optional<std::chrono::system_clock::time_point> start_at = {});

}  // namespace stereomap::bench
