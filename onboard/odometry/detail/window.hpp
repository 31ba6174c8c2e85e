// A sliding window of the last frames and the landmarks they observed, refined together by
// bundle adjustment (poses, points) with the oldest pose held fixed. Frame-to-keyframe
// tracking alone lets each frame's error through unchecked; the window makes a landmark seen
// over several frames agree with all of them, which removes most of the rotation drift.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <cstdint>
#include <deque>
#include <optional>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "common/geometry.hpp"
#include "onboard/camera/stereo_camera.hpp"

namespace stereomap::odometry::detail {

struct WindowObservation {
  int64_t landmark = 0;
  Eigen::Vector2d left;
  std::optional<Eigen::Vector2d> right;  // in the right image: raw column, row
};

class SlidingWindow {
 public:
  SlidingWindow(const camera::StereoCamera& camera, int frames)
      : camera_(camera), size_(static_cast<size_t>(std::max(frames, 1))) {}

  void clear();
  // Starts the newest frame (dropping the oldest beyond the window's size).
  void addFrame(int64_t frame, const common::Rigid3& T_world_camera);
  // An observation in the newest frame (addFrame first); `world` starts the landmark when the
  // window does not hold it yet.
  void observe(const WindowObservation& observation, const common::Vec3& world);
  // Bundle adjustment over the window; false when there is nothing to adjust. Right columns
  // are raw; `right_offset` (raw minus calibrated, pixels) is refined too when
  // `right_offset_sigma` > 0: see BundleProblem.
  bool adjust(int iterations, double huber_px, double& right_offset, double right_offset_sigma);

  std::optional<common::Rigid3> pose(int64_t frame) const;
  // A landmark's position from the last adjustment; nullopt when it was not in it (seen by
  // one frame only, or gone).
  std::optional<common::Vec3> adjustedLandmark(int64_t id) const;

 private:
  struct Frame {
    int64_t frame;
    common::Rigid3 T_world_camera;
    std::vector<WindowObservation> observations;
  };
  camera::StereoCamera camera_;
  size_t size_;
  std::deque<Frame> frames_;
  std::unordered_map<int64_t, common::Vec3> landmarks_;  // world frame
  std::unordered_set<int64_t> adjusted_;
};

}  // namespace stereomap::odometry::detail
