// Runs the landing chain (LandingWatch, default mode) over a simulated descent onto the moving
// deck and scores each frame against the truth, with the patent mode's pose from the same
// corners beside it. What stereomap-landing-eval prints.
#pragma once

#include <functional>
#include <vector>

#include "onboard/landing/landing_watch.hpp"
#include "onboard/sim/deck.hpp"

namespace stereomap::eval {

struct LandingFrameScore {
  double t_s = 0, distance_m = 0;
  int corners_in_view = 0;
  landing::TrackState state = landing::TrackState::kSearching;
  bool detected = false;  // this frame's corners came from full detection (not tracking)
  bool right_found = false;
  std::string reason;          // the tracker's, or why the default pose was refused
  double corner_error_px = 0;  // RMS of the 8 corners against their true projections
  struct Mode {
    bool published = false;
    double position_pct = 0;  // the pad centre's error, as % of the distance
    double attitude_deg = 0;
    double rms_px = 0;
  } modes[2];            // default, patent
  double track_ms = 0;   // the left tracker's update (detection or following)
  double detect_ms = 0;  // full detection on the left image, for its speed alone
  double pose_ms[2] = {0, 0};
  bool deck_valid = false;
  double heave_rate_error = 0;  // m/s, the filter's deck velocity z against the truth
  double deck_attitude_error_deg = 0;
};

struct LandingRunOptions {
  landing::TrackerOptions tracker;
  int every = 1;  // score every n-th frame (every frame is tracked)
  // Called with each scored frame (e.g. to save images).
  std::function<void(const camera::SourceFrame&, const LandingFrameScore&,
                     const landing::PadTrack&)>
      on_frame;
};

std::vector<LandingFrameScore> runLanding(sim::DeckSource& source,
                                          const LandingRunOptions& options = {});

}  // namespace stereomap::eval
