// The landing chain for one vehicle, frame by frame: the pad tracked in both images, its pose
// (default or patent mode), refused when it does not fit, taken into the map with the body's
// pose, the deck's motion filtered, and the pad's distance and bearing from the vehicle. What
// stereomap-onboard --landing runs and publishes as LandingTarget.
//
//   LandingWatch watch(camera, {.pose = {.mode = PoseMode::kDefault}});
//   const LandingReport& seen = watch.update(t_s, left, right, T_map_body, T_body_camera);
#pragma once

#include <opencv2/core.hpp>

#include "onboard/camera/stereo_camera.hpp"
#include "onboard/landing/deck_filter.hpp"
#include "onboard/landing/pad_pose.hpp"
#include "onboard/landing/pad_tracker.hpp"

namespace stereomap::landing {

struct LandingWatchOptions {
  TrackerOptions tracker;
  PadPoseOptions pose;
  DeckFilterOptions deck;
};

struct LandingReport {
  double t_s = 0;
  TrackState state = TrackState::kSearching;
  std::string reason;  // the tracker's, or why the pose was refused
  PadTrack left;       // this frame's track in the left image
  bool right_tracking = false;
  bool has_pose = false;  // a pose that fits: published
  PadPose pose;           // in the left camera
  common::Rigid3 T_map_pad;
  Mat6 map_covariance = Mat6::Zero();  // (rotation, pad centre) in the map frame
  // Valid while tracking (and for a moment after); in the world (update()'s T_world_map), where
  // the deck moves, also when the map is the deck's own frame.
  DeckEstimate deck;
  PadBearing bearing;
  double track_ms = 0, pose_ms = 0;
};

class LandingWatch {
 public:
  LandingWatch(const camera::StereoCamera& camera, LandingWatchOptions options = {});
  // T_world_map: the map frame in the world when the map moves (SourceFrame::T_world_map);
  // identity when the map is the world.
  const LandingReport& update(double t_s, const cv::Mat& left, const cv::Mat& right,
                              const common::Rigid3& T_map_body, const common::Rigid3& T_body_camera,
                              const common::Rigid3& T_world_map = {});
  const LandingReport& last() const { return report_; }

 private:
  camera::StereoCamera camera_;
  LandingWatchOptions options_;
  PadTracker left_, right_;
  DeckFilter deck_;
  LandingReport report_;
};

}  // namespace stereomap::landing
