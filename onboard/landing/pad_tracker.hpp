// Following the pad from frame to frame: its 8 corners tracked with pyramidal Lucas-Kanade
// (forward and back), put back on the T's edges (sub-pixel edge lines) and checked against the
// template; full detection when there is nothing to track or tracking degrades. An explicit
// state with the reason for it:
//   SEARCHING  nothing found yet (or since the pad was lost and looked for again)
//   TRACKING   the corners of this frame, found or followed
//   LOST       the pad was tracked and is no longer found (kept until it is found again)
//
//   PadTracker tracker;
//   const PadTrack& seen = tracker.update(left);   // seen.state, seen.reason, seen.corners
#pragma once

#include <array>
#include <string>

#include <opencv2/core.hpp>

#include "onboard/landing/pad_detector.hpp"

namespace stereomap::landing {

enum class TrackState { kSearching, kTracking, kLost };
const char* toString(TrackState state);

struct TrackerOptions {
  DetectorOptions detector;
  int window_px = 21;  // Lucas-Kanade window
  int pyramid_levels = 3;
  double max_forward_backward_px = 0.5;  // a corner tracked there and back must land this close
  // A tracked corner further than this from where the T's edges cross is a track gone astray.
  double max_edge_shift_px = 1.5;
  int redetect_every = 0;  // full detection every n frames even while tracking (0: never)
  // Full detection on the image reduced by 2 (DetectorOptions::reduce) while the pad was last
  // seen at least this large (the square root of its area in pixels: 60 at 20 m, 150 at 8 m,
  // 240 at 5 m with f = 492 px). Its corners are still refined on the whole image.
  double reduce_above_px = 150;
  // While the reduced search keeps failing, every this many-th full detection is on the whole
  // image (the pad may have become small again: a go-around), so it is found at any size.
  int full_search_every = 10;
};

struct PadTrack {
  TrackState state = TrackState::kSearching;
  std::string reason;                    // why this state
  std::array<cv::Point2d, 8> corners{};  // a..h, when TRACKING
  PadEdgePoints edges;                   // the sub-pixel edge points behind them
  bool detected = false;                 // by full detection in this frame (else followed)
  int frames_tracked = 0;                // since the last full detection
};

class PadTracker {
 public:
  explicit PadTracker(TrackerOptions options = {}) : options_(options) {}
  const PadTrack& update(const cv::Mat& grey);
  const PadTrack& last() const { return track_; }
  void reset();

 private:
  bool follow(const cv::Mat& grey, std::string& why_not);
  void detect(const cv::Mat& grey, const std::string& why_tracking_stopped);

  TrackerOptions options_;
  PadTrack track_;
  double last_size_px_ = 0;   // the pad's size when last tracked (reduce_above_px)
  int reduced_failures_ = 0;  // full detections on the reduced image that found nothing
  std::vector<cv::Mat> previous_pyramid_;
};

}  // namespace stereomap::landing
