// Stereo visual odometry: the pose of the left camera from rectified stereo pairs alone.
//
//   StereoOdometry vo(camera, {.mode = VoMode::kFast});
//   for (each rectified pair) {
//     const VoEstimate e = vo.track(left, right);
//     if (e.state != TrackingState::kLost) use(e.T_world_camera, e.covariance);
//   }
//
// kFast (default): FAST corners bucketed over the image, pyramidal KLT between frames with a
// forward-backward check and between left and right, 3D-2D RANSAC (P3P, adaptive iterations)
// against the current keyframe's stereo points, then Ceres refinement of the reprojection
// error in both cameras (Huber loss, constant-velocity prior), bundle adjustment over a
// sliding window of frames (which also estimates the right image's offset against its
// calibration), a 6x6 covariance, and an explicit state: ok / degraded / lost (lost
// re-initialises at the next frame).
// kPaper: the stereo-VO paper (docs/BENCHMARKS.md): Harris corners with 13x13 non-maximum
// suppression, NCC 25x25 matching (left-right along rows, and circular between frames),
// triangulation, RANSAC on 3 points (2 px, 20 iterations) and Levenberg-Marquardt on Euler
// angles minimising the 3D-3D error.
// The world frame is the first frame's left camera (OpenCV axes); callers re-anchor it.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <opencv2/core.hpp>

#include "common/geometry.hpp"
#include "onboard/camera/stereo_camera.hpp"

namespace stereomap::odometry {

enum class VoMode { kFast, kPaper };
enum class TrackingState { kInit, kOk, kDegraded, kLost };
const char* stateName(TrackingState state);

struct VoOptions {
  VoMode mode = VoMode::kFast;
  // kFast
  int grid_cols = 10, grid_rows = 4;  // buckets for an even spread of features
  int features_per_bucket = 10;
  int fast_threshold = 8;  // low: the bucket keeps its strongest corners anyway
  int klt_window = 15;
  int klt_levels = 3;
  double forward_backward_px = 0.8;  // circular consistency of the temporal tracks
  double ransac_px = 1.0;
  int ok_inliers = 60;        // at least this many inliers: ok
  int degraded_inliers = 15;  // fewer: lost
  // A new keyframe when fewer than this share of the keyframe's points are still inliers.
  double keyframe_inlier_share = 0.6;
  int window_frames = 5;  // bundle adjustment over the last frames (below 2: off)
  int window_iterations = 5;
  // Online estimate of the right image's horizontal offset against its calibration (a
  // disparity bias; real rigs drift by a pixel or so): the deviation of its prior around the
  // last estimate at each window adjustment (0: not estimated), and a hard bound. A window
  // that cannot tell it (standing still, only turning) leaves it as it is.
  double right_offset_step_px = 0.1;
  double right_offset_max_px = 3.0;
  // kPaper (the paper's values)
  double harris_k = 0.04;
  int paper_corners = 430;
  int nms_window = 13;
  int ncc_window = 25;
  double ncc_min = 0.8;
  int paper_ransac_iterations = 20;
  double paper_ransac_px = 2.0;
};

struct VoEstimate {
  TrackingState state = TrackingState::kInit;
  common::Rigid3 T_world_camera;  // left camera, OpenCV axes
  Eigen::Matrix<double, 6, 6> covariance = Eigen::Matrix<double, 6, 6>::Zero();  // rot, trans
  int features = 0;  // tracked or matched this frame
  int inliers = 0;
  bool keyframe = false;
  double milliseconds = 0;
  // Estimated horizontal offset of the right image against its calibration, pixels (fast
  // mode). Disparities are corrected by it; far from 0 means the rig needs recalibrating.
  double right_offset_px = 0;
  // Estimated gain of the right camera against the left (fast mode; the right image is
  // levelled by it before stereo matching).
  double right_gain = 1.0;
};

class StereoOdometry {
 public:
  StereoOdometry(const camera::StereoCamera& camera, const VoOptions& options = {});
  ~StereoOdometry();
  StereoOdometry(StereoOdometry&&) noexcept;
  StereoOdometry& operator=(StereoOdometry&&) noexcept;

  // One rectified CV_8UC1 pair; never throws for bad tracking (the state says so). The
  // velocity (the paper's eq. 10, a finite difference of positions) is the pipeline's, for
  // every pose source alike: onboard/pipeline.
  VoEstimate track(const cv::Mat& left, const cv::Mat& right);
  const VoOptions& options() const;

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

// The stereo-VO paper's attitude (eq. 12) from a rotation: pitch = asin(-r32),
// yaw = atan(r31 / r33), roll = atan(r12 / r22), radians.
struct EulerAngles {
  double yaw = 0, pitch = 0, roll = 0;
};
EulerAngles paperAttitude(const Eigen::Matrix3d& R);

}  // namespace stereomap::odometry
