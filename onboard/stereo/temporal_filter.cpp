#include "onboard/stereo/temporal_filter.hpp"

#include <algorithm>
#include <cmath>

namespace stereomap::stereo {

TemporalFilter::TemporalFilter(const camera::StereoCamera& camera,
                               const TemporalFilterOptions& options)
    : camera_(camera), options_(options) {
  CV_Assert(options.min_frames >= 1 && options.max_frames >= options.min_frames &&
            options.gate_px > 0);
}

void TemporalFilter::reset() { has_previous_ = false; }

void TemporalFilter::apply(BlockDisparity& blocks, const common::Rigid3& T_world_camera) {
  cv::Mat& measured = blocks.disparity;
  CV_Assert(measured.type() == CV_32FC1);
  const int rows = measured.rows, cols = measured.cols;
  const double fb = camera_.baseline * camera_.fx;

  // What earlier frames saw, carried into this camera: per block the nearest carried point's
  // disparity, its count and where in the block it landed.
  cv::Mat carried(rows, cols, CV_32FC1, cv::Scalar(0));
  cv::Mat carried_count(rows, cols, CV_32SC1, cv::Scalar(0));
  cv::Mat offset(rows, cols, CV_32FC2, cv::Scalar(0, 0));
  if (has_previous_ && previous_disparity_.size() == measured.size() &&
      block_cols_ == blocks.block_cols && block_rows_ == blocks.block_rows) {
    const common::Rigid3 T_current_previous = T_world_camera.inverse() * T_world_previous_;
    for (int by = 0; by < rows; ++by) {
      const float* d = previous_disparity_.ptr<float>(by);
      const int* n = previous_count_.ptr<int>(by);
      for (int bx = 0; bx < cols; ++bx) {
        if (d[bx] <= 0) continue;
        const common::Vec3 p =
            T_current_previous *
            (camera_.rayThrough(blocks.uCentre(bx), blocks.vCentre(by)) * (fb / d[bx]));
        const auto pixel = camera_.project(p);
        if (!pixel) continue;
        const int nbx = static_cast<int>(std::floor((pixel->x() + 0.5) / blocks.block_cols));
        const int nby = static_cast<int>(std::floor((pixel->y() + 0.5) / blocks.block_rows));
        if (nbx < 0 || nby < 0 || nbx >= cols || nby >= rows) continue;
        const auto disparity = static_cast<float>(fb / p.z());
        float& slot = carried.at<float>(nby, nbx);
        if (disparity <= slot) continue;  // the nearer surface hides the farther one
        slot = disparity;
        carried_count.at<int>(nby, nbx) = n[bx];
        offset.at<cv::Vec2f>(nby, nbx) =
            cv::Vec2f(static_cast<float>(pixel->x() - blocks.uCentre(nbx)),
                      static_cast<float>(pixel->y() - blocks.vCentre(nby)));
      }
    }
  }

  // The measured disparity's slope across the blocks (pixels of disparity per pixel), from
  // both neighbours when both were measured, to move a carried value to the block's centre.
  auto slope = [&](int by, int bx, int dy, int dx, int pixels) {
    const int y0 = by - dy, x0 = bx - dx, y1 = by + dy, x1 = bx + dx;
    if (y0 < 0 || x0 < 0 || y1 >= rows || x1 >= cols) return 0.0f;
    const float a = measured.at<float>(y0, x0), b = measured.at<float>(y1, x1);
    return a > 0 && b > 0 ? (b - a) / static_cast<float>(2 * pixels) : 0.0f;
  };
  cv::Mat next_disparity(rows, cols, CV_32FC1, cv::Scalar(0));
  cv::Mat next_count(rows, cols, CV_32SC1, cv::Scalar(0));
  cv::Mat output = measured.clone();
  for (int by = 0; by < rows; ++by) {
    for (int bx = 0; bx < cols; ++bx) {
      const float m = measured.at<float>(by, bx);
      if (m <= 0) continue;
      float value = m;
      int count = 1;
      const float c = carried.at<float>(by, bx);
      if (c > 0) {
        const cv::Vec2f o = offset.at<cv::Vec2f>(by, bx);
        const float centred = c - slope(by, bx, 0, 1, blocks.block_cols) * o[0] -
                              slope(by, bx, 1, 0, blocks.block_rows) * o[1];
        if (std::abs(m - centred) <= options_.gate_px) {
          count = std::min(carried_count.at<int>(by, bx) + 1, options_.max_frames);
          value = centred + (m - centred) / static_cast<float>(count);
        }
      }
      next_disparity.at<float>(by, bx) = value;
      next_count.at<int>(by, bx) = count;
      output.at<float>(by, bx) = count >= options_.min_frames ? value : 0.0f;
    }
  }
  measured = output;
  previous_disparity_ = next_disparity;
  previous_count_ = next_count;
  T_world_previous_ = T_world_camera;
  block_cols_ = blocks.block_cols;
  block_rows_ = blocks.block_rows;
  has_previous_ = true;
}

}  // namespace stereomap::stereo
