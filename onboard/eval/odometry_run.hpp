// Runs the visual odometry over a frame source that has ground truth and keeps both
// trajectories (left camera poses, the estimate anchored at the first true pose), for tests
// and benchmarks.
#pragma once

#include <vector>

#include "common/trajectory.hpp"
#include "onboard/camera/frame_source.hpp"
#include "onboard/odometry/odometry.hpp"
#include "onboard/posegraph/graph_follower.hpp"

namespace stereomap::eval {

struct OdometryRun {
  common::Trajectory truth, estimate;
  // With a pose graph (runOdometryWithGraph): every frame through its keyframe's pose after
  // the last solve, and what the graph found.
  common::Trajectory optimised;
  int loops = 0;
  int tracks = 0, joined_tracks = 0;  // the odometry's tracks; later ones joined by a place
  double solve_ms_max = 0;
  std::vector<double> milliseconds;  // per frame
  int lost = 0, degraded = 0, keyframes = 0;
  double right_offset_px = 0;  // the odometry's estimate after the last frame
  double right_gain = 1.0;     // likewise
  double medianMilliseconds() const;
};

// Frames without ground truth get the identity as truth.
OdometryRun runOdometry(camera::FrameSource& source, const odometry::VoOptions& options);
OdometryRun runOdometryWithGraph(camera::FrameSource& source, const odometry::VoOptions& options,
                                 const posegraph::KeyframeGraphOptions& graph_options = {});

}  // namespace stereomap::eval
