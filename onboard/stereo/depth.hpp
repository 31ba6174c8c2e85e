// Dense depth on board: a stereo matcher over rectified grey pairs (OpenCV block matching or
// semi-global matching) and the conversion of a disparity image into a down-sampled point
// cloud in the left camera frame (z = baseline * fx / d).
//
//   StereoMatcher matcher({.kind = MatcherKind::kBlockMatching});
//   cv::Mat disparity = matcher.compute(left, right);
//   PointCloud cloud = cloudFromDisparity(disparity, left, camera, {.max_range_m = 6});
#pragma once

#include <memory>

#include <opencv2/core.hpp>

#include "common/point_cloud.hpp"
#include "onboard/camera/stereo_camera.hpp"

namespace stereomap::stereo {

enum class MatcherKind { kBlockMatching, kSemiGlobal };

struct MatcherOptions {
  MatcherKind kind = MatcherKind::kBlockMatching;
  int num_disparities = 80;  // multiple of 16; the nearest depth is baseline * fx / this
  int block_size = 11;       // odd; BM window (SGBM uses 5)
  int uniqueness_ratio = 15;
  int speckle_window = 100;  // pixels; 0 disables speckle filtering
  int speckle_range = 2;
};

class StereoMatcher {
 public:
  explicit StereoMatcher(const MatcherOptions& options = {});
  ~StereoMatcher();
  StereoMatcher(StereoMatcher&&) noexcept;
  StereoMatcher& operator=(StereoMatcher&&) noexcept;

  // Disparity of the left image in pixels (CV_32FC1, sub-pixel in 1/16 px steps); values
  // <= 0 are invalid. Both images must be CV_8UC1 of the same size.
  cv::Mat compute(const cv::Mat& left, const cv::Mat& right) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

struct CloudOptions {
  double min_range_m = 0.3;
  double max_range_m = 6.0;  // points beyond are dropped (stereo depth error grows as z²)
  int block_cols = 5;        // down-sampling block (the octree-mapping paper's 5x2)
  int block_rows = 2;
  bool with_intensity = true;
};

// One point per block_cols x block_rows block: the median valid disparity of the block,
// placed on the ray through the block's centre. Blocks with fewer than half of their pixels
// valid give no point; invalid disparities never become points.
common::PointCloud cloudFromDisparity(const cv::Mat& disparity, const cv::Mat& left,
                                      const camera::StereoCamera& camera,
                                      const CloudOptions& options = {});

}  // namespace stereomap::stereo
