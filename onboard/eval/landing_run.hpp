// Runs the pad's detection and both pose modes over a simulated descent onto the moving deck
// and scores each frame against the truth: what stereomap-landing-eval prints and the landing
// tests assert.
#pragma once

#include <functional>
#include <vector>

#include "onboard/landing/pad_detector.hpp"
#include "onboard/landing/pad_pose.hpp"
#include "onboard/sim/deck.hpp"

namespace stereomap::eval {

struct LandingFrameScore {
  double t_s = 0, distance_m = 0;
  int corners_in_view = 0;
  bool detected = false, right_detected = false;
  std::string reason;          // why not detected, or why a pose was refused
  double corner_error_px = 0;  // RMS of the 8 corners against their true projections
  struct Mode {
    bool published = false;
    double position_pct = 0;  // of the pad centre's error, as % of the distance
    double attitude_deg = 0;
    double rms_px = 0;
  } modes[2];  // default, patent
  double detect_ms = 0, pose_ms[2] = {0, 0};
};

struct LandingRunOptions {
  landing::DetectorOptions detector;
  int every = 1;  // score every n-th frame
  // Called with each rendered frame and its score (e.g. to save images).
  std::function<void(const camera::SourceFrame&, const LandingFrameScore&)> on_frame;
};

std::vector<LandingFrameScore> runLanding(sim::DeckSource& source,
                                          const LandingRunOptions& options = {});

}  // namespace stereomap::eval
