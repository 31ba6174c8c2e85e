// What a cluster did with a flight, checked against what its vehicle says it sent: for the
// cluster's tests and its benchmarks (stereomap-bench-cluster, stereomap-bench-chaos). Every
// sample counted once in the journal, every pose of the vehicle's --trajectory-out journaled,
// and the owner's live map the journal's, fused again offline (voxel for voxel).
#pragma once

#include <chrono>
#include <cstddef>
#include <string>
#include <vector>

#include "proto/journal/journal.hpp"

#include "tests/support/cluster_harness.hpp"

namespace stereomap::testing {

struct FlightCheck {
  std::string session;
  size_t sent_poses = 0, sent_clouds = 0;  // the vehicle's closing lines
  size_t journaled_poses = 0, journaled_clouds = 0;
  size_t repeated = 0;            // samples journaled more than once
  size_t trajectory_poses = 0;    // lines of its --trajectory-out
  size_t trajectory_missing = 0;  // of those, not journaled (stamp to the microsecond)
  size_t live_leaves = 0;         // the live map's leaves (when the map was checked)
  bool map_is_journals = false;   // the live map equals the journal fused offline
  std::string problem;            // what could not be read or compared ("" when none)

  // Samples the vehicle sent that are not journaled (negative: journaled more than sent).
  long lost() const {
    return static_cast<long>(sent_poses + sent_clouds) -
           static_cast<long>(journaled_poses + journaled_clouds);
  }
  // True when nothing was lost, repeated or left out, and (when checked) the map matched.
  bool whole(bool with_map) const;
  std::string summary() const;
};

// Vehicle `i` of `cluster` (session flight<i>), ended. `with_map`: also the live map of the
// session's owner (waiting up to `fuse_timeout` for it to have fused everything; once the
// session has left memory, the snapshot it left with) against the journal fused offline.
FlightCheck checkFlight(ClusterHarness& cluster, int i, bool with_map,
                        std::chrono::seconds fuse_timeout = std::chrono::seconds(60));

// A flight as its vehicle sent it (poses and the thinned clouds, whole, in journal order), read
// back from the cluster's journal: what the benchmarks replay as virtual vehicles or history.
std::vector<proto::journal::JournalRecord> recordedFlight(ClusterHarness& cluster,
                                                          const std::string& session);

}  // namespace stereomap::testing
