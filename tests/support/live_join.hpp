// A live join (issue 56, item 3), run with the real binaries: a server; vehicle sim-1 maps the
// simulated room in the session's frame; then sim-2 flies the same room in its own frame
// (started `start_s` into the sim's loop, its first pose sent as `start_pose`), and, with
// `stranger`, sim-3 flies another room (seed 11) in its own frame beside it. Used by
// align_e2e_test and stereomap-bench-align.
#pragma once

#include <cstdint>
#include <limits>
#include <nlohmann/json.hpp>
#include <string>

#include "common/geometry.hpp"

namespace stereomap::testing {

struct LiveJoinOptions {
  int domain = 0;
  std::string store;  // kept (the caller's folder)
  std::string session = "site";
  int first_frames = 300;   // sim-1, 10 Hz: 30 s of the sim's 40 s loop
  int second_frames = 150;  // sim-2 and sim-3
  double start_s = 20;
  std::string start_pose = "20,0,0,90";  // x,y,z,yaw_deg
  bool stranger = false;
  bool kill_server = false;  // kill -9 at the end instead of a clean stop
};

struct LiveJoinResult {
  static constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  bool aligned = false;
  // J: from sim-2's first held frame on the server to its join (the session's frame known).
  double aligned_s = kNaN;
  // From sim-2's start to its held frames fused in the session's frame (the re-fusion done).
  double fused_s = kNaN;
  // JT: RMS over sim-2's poses of |T_session_own p_own - p_truth| (sim-1 maps in the sim's
  // frame, so the session's frame is the truth's).
  double error_m = kNaN;
  uint64_t attempts = 0;
  nlohmann::json session;        // GET /api/sessions/ID at the end
  nlohmann::json stranger;       // sim-3's vehicle_frames entry (with `stranger`)
  size_t voxels_before = 0;      // occupied once sim-1 was done
  nlohmann::json bounds_before;  // the map's then
  std::string log;               // the server's, for failures
};

LiveJoinResult runLiveJoin(const LiveJoinOptions& options);

// RMS of |T p_own - p_truth| over the poses two TUM files both have (by stamp): where a
// vehicle's own frame was placed (T), against its ground truth. NaN when none match.
double trajectoryError(const common::Rigid3& T, const std::string& own, const std::string& truth);

// The vehicle's entry in a session's "vehicle_frames" (null when none).
nlohmann::json vehicleFrame(const nlohmann::json& session, const std::string& vehicle);

}  // namespace stereomap::testing
