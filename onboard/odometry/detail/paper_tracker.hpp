// The stereo-VO paper's method (VoMode::kPaper), kept faithful so that its figures can be
// reproduced: see odometry.hpp and ../shared/PAPERS.md section 1.
#pragma once

#include <opencv2/core.hpp>
#include <random>
#include <vector>

#include "onboard/odometry/odometry.hpp"

namespace stereomap::odometry::detail {

class PaperTracker {
 public:
  PaperTracker(const camera::StereoCamera& camera, const VoOptions& options);
  VoEstimate track(const cv::Mat& left, const cv::Mat& right);

 private:
  struct StereoFrame {
    cv::Mat left, right;
    std::vector<cv::Point2f> corners;  // left corners with a stereo match
    std::vector<cv::Point2f> right_corners;
  };
  StereoFrame stereoFrame(const cv::Mat& left, const cv::Mat& right) const;

  camera::StereoCamera camera_;
  VoOptions options_;
  bool initialised_ = false;
  StereoFrame previous_;
  common::Rigid3 T_world_camera_;
  std::mt19937 random_{7};
};

// Harris corners (3x3 gradient window, k) with non-maximum suppression over `nms_window`,
// the `count` strongest.
std::vector<cv::Point2f> harrisCorners(const cv::Mat& image, double k, int nms_window, int count);
// Normalised cross-correlation of the `window` squares centred on a and b (-1 when a window
// leaves an image).
double ncc(const cv::Mat& a, cv::Point2f pa, const cv::Mat& b, cv::Point2f pb, int window);

}  // namespace stereomap::odometry::detail
