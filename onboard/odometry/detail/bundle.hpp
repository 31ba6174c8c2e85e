// Bundle adjustment for the odometry's sliding window: stereo reprojection error in both
// cameras over a few poses and their points, Huber-robust, Levenberg-Marquardt with the points
// eliminated (Schur complement) and analytic Jacobians (a window of 5 frames: 2-3 ms).
#pragma once

#include <vector>

#include "common/geometry.hpp"
#include "onboard/camera/stereo_camera.hpp"

namespace stereomap::odometry::detail {

struct BundleObservation {
  int frame = 0, point = 0;
  double u = 0, v = 0;  // pixel; for the right camera its raw column
  bool right = false;
};

struct BundleProblem {
  std::vector<common::Rigid3> T_camera_world;  // the first is held fixed (gauge)
  std::vector<common::Vec3> points;            // world frame
  std::vector<BundleObservation> observations;
  // Horizontal offset of the right image against its calibration (raw minus calibrated
  // column, pixels); refined when right_offset_sigma > 0, with a prior of that deviation
  // around its start value (a random walk from one window to the next), and only when the
  // window determines it well enough (BundleOptions::offset_gate_px).
  double right_offset = 0;
  double right_offset_sigma = 0;
};

struct BundleOptions {
  int iterations = 5;
  double huber_px = 1.0;
  // The offset is refined only when the window alone (no prior, 1 px image noise) determines
  // it to this standard deviation or better; otherwise it is held. Moving windows determine
  // it to 0.1-2 px (the prior then averages over many windows); a vehicle standing still or
  // only turning, to hundreds: there it would only wander.
  double offset_gate_px = 5.0;
};

struct BundleSummary {
  double initial_cost = 0, final_cost = 0;  // robust, half sum of squares
  int iterations = 0;                       // accepted steps
  double offset_sigma_px = 0;               // the window's own determination of the offset
};

// Refines poses (but the first), points and the offset in place.
BundleSummary adjustBundle(const camera::StereoCamera& camera, BundleProblem& problem,
                           const BundleOptions& options);

}  // namespace stereomap::odometry::detail
