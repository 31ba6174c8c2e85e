#include "onboard/stereo/depth.hpp"

#include <opencv2/calib3d.hpp>

#include <algorithm>
#include <array>

namespace stereomap::stereo {

struct StereoMatcher::Impl {
  cv::Ptr<cv::StereoMatcher> matcher;
};

StereoMatcher::StereoMatcher(const MatcherOptions& options) : impl_(std::make_unique<Impl>()) {
  if (options.kind == MatcherKind::kBlockMatching) {
    auto bm = cv::StereoBM::create(options.num_disparities, options.block_size);
    bm->setUniquenessRatio(options.uniqueness_ratio);
    bm->setTextureThreshold(10);
    bm->setPreFilterCap(31);
    impl_->matcher = bm;
  } else {
    constexpr int kBlock = 5;
    auto sgbm = cv::StereoSGBM::create(0, options.num_disparities, kBlock, 8 * kBlock * kBlock,
                                       32 * kBlock * kBlock, 1, 63, options.uniqueness_ratio, 0, 0,
                                       cv::StereoSGBM::MODE_SGBM_3WAY);
    impl_->matcher = sgbm;
  }
  impl_->matcher->setSpeckleWindowSize(options.speckle_window);
  impl_->matcher->setSpeckleRange(options.speckle_range);
}

StereoMatcher::~StereoMatcher() = default;
StereoMatcher::StereoMatcher(StereoMatcher&&) noexcept = default;
StereoMatcher& StereoMatcher::operator=(StereoMatcher&&) noexcept = default;

cv::Mat StereoMatcher::compute(const cv::Mat& left, const cv::Mat& right) const {
  CV_Assert(left.type() == CV_8UC1 && right.type() == CV_8UC1 && left.size() == right.size());
  cv::Mat fixed_point;  // CV_16S, 4 fractional bits
  impl_->matcher->compute(left, right, fixed_point);
  cv::Mat disparity;
  fixed_point.convertTo(disparity, CV_32F, 1.0 / 16.0);
  return disparity;
}

common::PointCloud cloudFromDisparity(const cv::Mat& disparity, const cv::Mat& left,
                                      const camera::StereoCamera& camera,
                                      const CloudOptions& options) {
  CV_Assert(disparity.type() == CV_32FC1);
  CV_Assert(!options.with_intensity || (left.type() == CV_8UC1 && left.size() == disparity.size()));
  CV_Assert(options.block_cols >= 1 && options.block_rows >= 1);
  const double min_disparity = camera.disparityFromDepth(options.max_range_m);
  const double max_disparity = camera.disparityFromDepth(options.min_range_m);
  const int block_pixels = options.block_cols * options.block_rows;

  common::PointCloud cloud;
  std::vector<float> valid;
  valid.reserve(block_pixels);
  for (int v0 = 0; v0 + options.block_rows <= disparity.rows; v0 += options.block_rows) {
    for (int u0 = 0; u0 + options.block_cols <= disparity.cols; u0 += options.block_cols) {
      valid.clear();
      int intensity_sum = 0;
      for (int v = v0; v < v0 + options.block_rows; ++v) {
        const float* row = disparity.ptr<float>(v);
        for (int u = u0; u < u0 + options.block_cols; ++u) {
          if (row[u] > 0 && row[u] >= min_disparity && row[u] <= max_disparity) {
            valid.push_back(row[u]);
            if (options.with_intensity) intensity_sum += left.at<uint8_t>(v, u);
          }
        }
      }
      if (2 * static_cast<int>(valid.size()) < block_pixels || valid.empty()) continue;
      auto middle = valid.begin() + valid.size() / 2;
      std::nth_element(valid.begin(), middle, valid.end());
      const double depth = camera.depthFromDisparity(*middle);
      const double u_centre = u0 + (options.block_cols - 1) / 2.0;
      const double v_centre = v0 + (options.block_rows - 1) / 2.0;
      cloud.points.push_back((camera.rayThrough(u_centre, v_centre) * depth).cast<float>());
      if (options.with_intensity) {
        cloud.intensity.push_back(static_cast<uint8_t>(intensity_sum / valid.size()));
      }
    }
  }
  return cloud;
}

}  // namespace stereomap::stereo
