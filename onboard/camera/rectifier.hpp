// Rectification of raw stereo pairs: maps computed once from a StereoCalibration (OpenCV's
// stereoRectify, zero disparity at infinity, no black border), then applied per frame with
// a fixed-point remap. An already rectified calibration passes images through untouched.
#pragma once

#include <opencv2/core.hpp>

#include "common/result.hpp"
#include "onboard/camera/calibration.hpp"
#include "onboard/camera/stereo_camera.hpp"

namespace stereomap::camera {

class Rectifier {
 public:
  // `image_size` overrides the calibration's (which may be unknown, 0x0).
  static common::Result<Rectifier> create(const StereoCalibration& calibration,
                                          cv::Size image_size = {});

  // The rectified pinhole pair (fx, fy, cx, cy, baseline in the calibration's T units).
  const StereoCamera& camera() const { return camera_; }
  // Rotation from the raw left camera frame to the rectified left camera frame.
  const cv::Matx33d& leftRotation() const { return R_left_; }
  bool passThrough() const { return pass_through_; }

  // Rectifies a pair (grey or colour; the output is 8-bit grey). Fails with a message when
  // an image is empty or not of the calibrated size.
  common::Status rectify(const cv::Mat& left, const cv::Mat& right, cv::Mat& left_out,
                         cv::Mat& right_out) const;
  // Raw left/right pixel coordinates to rectified ones (for checks and tests).
  std::vector<cv::Point2f> rectifyLeftPoints(const std::vector<cv::Point2f>& raw) const;
  std::vector<cv::Point2f> rectifyRightPoints(const std::vector<cv::Point2f>& raw) const;

 private:
  std::vector<cv::Point2f> rectifyPoints(const std::vector<cv::Point2f>& raw,
                                         const CameraIntrinsics& camera, const cv::Matx33d& R,
                                         const cv::Matx34d& P) const;

  StereoCalibration calibration_;
  StereoCamera camera_;
  cv::Matx33d R_left_ = cv::Matx33d::eye(), R_right_ = cv::Matx33d::eye();
  cv::Matx34d P_left_, P_right_;
  cv::Mat left_map1_, left_map2_, right_map1_, right_map2_;
  bool pass_through_ = false;
};

}  // namespace stereomap::camera
