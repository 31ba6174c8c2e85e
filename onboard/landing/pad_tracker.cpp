#include "onboard/landing/pad_tracker.hpp"

#include <cmath>
#include <opencv2/video/tracking.hpp>

namespace stereomap::landing {

const char* toString(TrackState state) {
  switch (state) {
    case TrackState::kSearching:
      return "SEARCHING";
    case TrackState::kTracking:
      return "TRACKING";
    case TrackState::kLost:
      return "LOST";
  }
  return "?";
}

namespace {

// The square root of the area the corners enclose, in pixels.
double sizeOf(const std::array<cv::Point2d, 8>& corners) {
  double twice_area = 0;
  for (int k = 0; k < 8; ++k) {
    const cv::Point2d& a = corners[k];
    const cv::Point2d& b = corners[(k + 1) % 8];
    twice_area += a.x * b.y - a.y * b.x;
  }
  return std::sqrt(std::abs(twice_area) / 2);
}

}  // namespace

void PadTracker::reset() {
  track_ = {};
  previous_pyramid_.clear();
  last_size_px_ = 0;
  reduced_failures_ = 0;
}

bool PadTracker::follow(const cv::Mat& grey, std::string& why_not) {
  std::vector<cv::Mat> pyramid;
  const cv::Size window(options_.window_px, options_.window_px);
  cv::buildOpticalFlowPyramid(grey, pyramid, window, options_.pyramid_levels);
  std::vector<cv::Point2f> before, after, back;
  for (const auto& c : track_.corners) before.emplace_back(c);
  std::vector<uint8_t> status, status_back;
  std::vector<float> error;
  cv::calcOpticalFlowPyrLK(previous_pyramid_, pyramid, before, after, status, error, window,
                           options_.pyramid_levels);
  cv::calcOpticalFlowPyrLK(pyramid, previous_pyramid_, after, back, status_back, error, window,
                           options_.pyramid_levels);
  previous_pyramid_ = std::move(pyramid);
  std::array<cv::Point2d, 8> moved;
  for (int k = 0; k < 8; ++k) {
    if (!status[k] || !status_back[k]) {
      why_not = "corner " + std::string(1, static_cast<char>('a' + k)) + " not followed";
      return false;
    }
    if (cv::norm(back[k] - before[k]) > options_.max_forward_backward_px) {
      why_not = "corner " + std::string(1, static_cast<char>('a' + k)) +
                " does not track back to where it was";
      return false;
    }
    moved[k] = after[k];
    if (moved[k].x < 0 || moved[k].y < 0 || moved[k].x > grey.cols - 1 ||
        moved[k].y > grey.rows - 1) {
      why_not = "the pad is leaving the image";
      return false;
    }
  }
  // Back onto the T's edges; a corner the edges put elsewhere followed something else.
  PadEdgePoints edges;
  const auto refined = refineCorners(grey, moved, &edges);
  for (int k = 0; k < 8; ++k) {
    if (cv::norm(refined[k] - moved[k]) > options_.max_edge_shift_px) {
      why_not = "corner " + std::string(1, static_cast<char>('a' + k)) + " is off the T's edges";
      return false;
    }
  }
  if (padShapeError(refined) > options_.detector.max_shape_error) {
    why_not = "the tracked corners no longer make the pad's T";
    return false;
  }
  track_.corners = refined;
  track_.edges = std::move(edges);
  return true;
}

void PadTracker::detect(const cv::Mat& grey, const std::string& why_tracking_stopped) {
  const TrackState before = track_.state;
  DetectorOptions detector = options_.detector;
  const bool whole_due =
      options_.full_search_every > 0 &&
      reduced_failures_ % options_.full_search_every == options_.full_search_every - 1;
  if (last_size_px_ >= options_.reduce_above_px && !whole_due) detector.reduce = 2;
  const PadDetection found = detectPad(grey, detector);
  track_.detected = true;
  reduced_failures_ = found ? 0 : reduced_failures_ + (last_size_px_ >= options_.reduce_above_px);
  if (found) {
    last_size_px_ = sizeOf(found.corners);
    track_.state = TrackState::kTracking;
    track_.reason =
        why_tracking_stopped.empty() ? "found" : "found again (" + why_tracking_stopped + ")";
    track_.corners = found.corners;
    track_.edges = found.edges;
    track_.frames_tracked = 0;
    previous_pyramid_.clear();
    cv::buildOpticalFlowPyramid(grey, previous_pyramid_,
                                cv::Size(options_.window_px, options_.window_px),
                                options_.pyramid_levels);
    return;
  }
  previous_pyramid_.clear();
  track_.state = before == TrackState::kSearching ? TrackState::kSearching : TrackState::kLost;
  track_.reason =
      why_tracking_stopped.empty() ? found.reason : why_tracking_stopped + "; " + found.reason;
}

const PadTrack& PadTracker::update(const cv::Mat& grey) {
  track_.detected = false;
  if (track_.state == TrackState::kTracking && !previous_pyramid_.empty()) {
    const bool due =
        options_.redetect_every > 0 && track_.frames_tracked + 1 >= options_.redetect_every;
    std::string why_not;
    if (!due && follow(grey, why_not)) {
      last_size_px_ = sizeOf(track_.corners);
      ++track_.frames_tracked;
      track_.reason = "followed";
      return track_;
    }
    detect(grey, due ? std::string() : why_not);
    return track_;
  }
  detect(grey, "");
  return track_;
}

}  // namespace stereomap::landing
