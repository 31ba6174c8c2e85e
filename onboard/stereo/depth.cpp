#include "onboard/stereo/depth.hpp"

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/ximgproc/disparity_filter.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <unordered_map>

namespace stereomap::stereo {

MatcherOptions MatcherOptions::fast() {
  MatcherOptions options;
  options.kind = MatcherKind::kBlockMatching;
  // 13 rather than 11: at 0.05 m voxels the far points' depth noise decides the map's
  // precision (0.949 against 0.959-0.969 on three sim rooms, docs/BENCHMARKS.md).
  options.block_size = 13;
  // The window's width: with DepthStep's start at the cloud's range (fitToRange), the sim
  // camera sees from 1.04 m to 6 m; 64 cost a third more time for nothing on the sim's maps
  // (docs/BENCHMARKS.md).
  options.num_disparities = 48;
  options.prefilter_cap = 31;  // BM's SIMD path needs <= 31: 63 doubles its time
  options.uniqueness_ratio = 15;
  options.speckle_window = 0;  // OpenCV's speckle filter costs 7.5 ms at 640x480, BM 10 ms
  options.left_right_max_diff = -1;
  // The left band holds far surfaces seen nowhere else in a turning flight (recall 0.83
  // without it at 0.05 m); its matches count only with the window inside the right image.
  options.pad_left = true;
  return options;
}

MatcherOptions MatcherOptions::accurate() {
  // Chosen on Middlebury against stock SGBM, and checked for sensitivity (every neighbouring
  // block size, penalty, cap, uniqueness and speckle value still beats stock; noise up to
  // sigma 5 keeps density >= 85%): see docs/BENCHMARKS.md.
  MatcherOptions options;
  options.kind = MatcherKind::kSemiGlobal;
  options.mode = SemiGlobalMode::kThreeWay;
  options.block_size = 5;
  options.p1 = 16;
  options.p2 = 32;
  options.prefilter_cap = 31;
  options.uniqueness_ratio = 10;
  options.left_right_max_diff = 1;
  options.speckle_window = 100;
  options.speckle_range = 2;
  return options;
}

int disparitiesFor(int max_disparity_px) { return std::max(16, (max_disparity_px + 15) / 16 * 16); }

int minimumDisparity(double baseline_m, double fx_px, double resolution_m, double dd_px) {
  return static_cast<int>(std::ceil(std::sqrt(baseline_m * fx_px * dd_px / resolution_m)));
}

MatcherOptions fitToRange(MatcherOptions options, const camera::StereoCamera& camera,
                          double max_range_m) {
  CV_Assert(max_range_m > 0);
  const int farthest = static_cast<int>(std::floor(camera.disparityFromDepth(max_range_m)));
  options.min_disparity = std::max(options.min_disparity, farthest);
  return options;
}

struct StereoMatcher::Impl {
  MatcherOptions options;
  cv::Ptr<cv::StereoMatcher> matcher;
  cv::Ptr<cv::StereoMatcher> right_matcher;  // for the WLS filter
  cv::Ptr<cv::ximgproc::DisparityWLSFilter> wls;
  cv::Mat fixed_point;  // reused between frames: a fresh 0.6 MB buffer costs page faults
};

namespace {

int sgbmMode(SemiGlobalMode mode) {
  switch (mode) {
    case SemiGlobalMode::kFivePaths:
      return cv::StereoSGBM::MODE_SGBM;
    case SemiGlobalMode::kThreeWay:
      return cv::StereoSGBM::MODE_SGBM_3WAY;
    case SemiGlobalMode::kEightPaths:
      return cv::StereoSGBM::MODE_HH;
    case SemiGlobalMode::kEightPathsFourLines:
      return cv::StereoSGBM::MODE_HH4;
  }
  return cv::StereoSGBM::MODE_SGBM_3WAY;
}

}  // namespace

StereoMatcher::StereoMatcher(const MatcherOptions& options) : impl_(std::make_unique<Impl>()) {
  CV_Assert(options.num_disparities > 0 && options.num_disparities % 16 == 0);
  CV_Assert(options.block_size % 2 == 1 && options.downscale >= 1 && options.row_groups >= 1);
  impl_->options = options;
  const int levels = options.num_disparities / options.downscale;
  const int num_disparities = disparitiesFor(levels);
  const int min_disparity = options.min_disparity / options.downscale;
  if (options.kind == MatcherKind::kBlockMatching) {
    auto bm = cv::StereoBM::create(num_disparities, options.block_size);
    bm->setMinDisparity(min_disparity);
    bm->setUniquenessRatio(options.uniqueness_ratio);
    bm->setTextureThreshold(options.texture_threshold);
    bm->setPreFilterCap(std::min(options.prefilter_cap, 63));
    bm->setDisp12MaxDiff(options.left_right_max_diff);
    impl_->matcher = bm;
  } else {
    const int area = options.block_size * options.block_size;
    impl_->matcher = cv::StereoSGBM::create(min_disparity, num_disparities, options.block_size,
                                            options.p1 * area, options.p2 * area,
                                            options.left_right_max_diff, options.prefilter_cap,
                                            options.uniqueness_ratio, 0, 0, sgbmMode(options.mode));
  }
  impl_->matcher->setSpeckleWindowSize(options.speckle_window);
  impl_->matcher->setSpeckleRange(options.speckle_range);
  if (options.wls_lambda > 0) {
    impl_->wls = cv::ximgproc::createDisparityWLSFilter(impl_->matcher);
    impl_->wls->setLambda(options.wls_lambda);
    impl_->wls->setSigmaColor(options.wls_sigma);
    impl_->right_matcher = cv::ximgproc::createRightMatcher(impl_->matcher);
  }
}

namespace {
// Laplacian of Gaussian, mapped to 8 bits around 128 (the paper's prefilter).
cv::Mat laplacianOfGaussian(const cv::Mat& image, double sigma) {
  cv::Mat blurred, laplacian, out;
  cv::GaussianBlur(image, blurred, cv::Size(), sigma);
  cv::Laplacian(blurred, laplacian, CV_16S, 3);
  laplacian.convertTo(out, CV_8U, -4.0, 128.0);
  return out;
}
}  // namespace

StereoMatcher::~StereoMatcher() = default;
StereoMatcher::StereoMatcher(StereoMatcher&&) noexcept = default;
StereoMatcher& StereoMatcher::operator=(StereoMatcher&&) noexcept = default;
const MatcherOptions& StereoMatcher::options() const { return impl_->options; }

cv::Mat StereoMatcher::compute(const cv::Mat& left, const cv::Mat& right) const {
  CV_Assert(left.type() == CV_8UC1 && right.type() == CV_8UC1 && left.size() == right.size());
  const MatcherOptions& o = impl_->options;
  cv::Mat l = left, r = right;
  if (o.downscale > 1) {
    const cv::Size small((left.cols + o.downscale - 1) / o.downscale,
                         (left.rows + o.downscale - 1) / o.downscale);
    cv::resize(left, l, small, 0, 0, cv::INTER_AREA);
    cv::resize(right, r, small, 0, 0, cv::INTER_AREA);
  }
  const cv::Size matched = l.size();
  if (o.row_groups > 1) {
    const cv::Size grouped(l.cols, (l.rows + o.row_groups - 1) / o.row_groups);
    cv::resize(l, l, grouped, 0, 0, cv::INTER_AREA);
    cv::resize(r, r, grouped, 0, 0, cv::INTER_AREA);
  }
  if (o.smooth_sigma_px > 0) {
    cv::Mat smoothed_left, smoothed_right;
    // Grouped rows are smoothed along the rows only: the grouping has averaged them already,
    // and more vertical smoothing cost precision (typical camera 0.957 -> 0.943, measured).
    const cv::Size kernel =
        o.row_groups > 1 ? cv::Size(cvRound(o.smooth_sigma_px * 6 + 1) | 1, 1) : cv::Size();
    cv::GaussianBlur(l, smoothed_left, kernel, o.smooth_sigma_px);
    cv::GaussianBlur(r, smoothed_right, kernel, o.smooth_sigma_px);
    l = smoothed_left;
    r = smoothed_right;
  }
  if (o.prefilter == Prefilter::kLoG) {
    l = laplacianOfGaussian(l, o.log_sigma_px);
    r = laplacianOfGaussian(r, o.log_sigma_px);
  }
  // Without padding the matchers leave the first num_disparities columns empty; with it a
  // pixel there finds its match whenever the match is inside the right image.
  const int pad =
      o.pad_left ? impl_->matcher->getNumDisparities() + impl_->matcher->getMinDisparity() : 0;
  if (pad > 0) {
    cv::copyMakeBorder(l, l, 0, 0, pad, 0, cv::BORDER_REPLICATE);
    cv::copyMakeBorder(r, r, 0, 0, pad, 0, cv::BORDER_REPLICATE);
  }
  cv::Mat& fixed_point = impl_->fixed_point;  // CV_16S, 4 fractional bits
  impl_->matcher->compute(l, r, fixed_point);
  if (impl_->wls) {
    cv::Mat right_disparity, filtered;
    impl_->right_matcher->compute(r, l, right_disparity);
    // The filter's default region of interest leaves the left band empty: use all of it.
    impl_->wls->filter(fixed_point, l, filtered, right_disparity, cv::Rect(0, 0, l.cols, l.rows),
                       r);
    fixed_point = filtered;
  }
  const int invalid_below = impl_->matcher->getMinDisparity() * 16;
  // With padding, a match counts only when the whole matching window lies inside the right
  // image (x - d >= half the block): windows reaching into the padding give biased matches.
  const int inside = o.block_size / 2;
  const float scale = static_cast<float>(o.downscale) / 16.0f;
  cv::Mat disparity(matched, CV_32FC1);
  for (int v = 0; v < disparity.rows; ++v) {
    const int16_t* in = fixed_point.ptr<int16_t>(v / o.row_groups) + pad;
    float* out = disparity.ptr<float>(v);
    for (int u = 0; u < disparity.cols; ++u) {
      const bool valid = in[u] >= invalid_below && (pad == 0 || in[u] <= (u - inside) * 16);
      out[u] = valid ? in[u] * scale : -1.0f;
    }
  }
  if (o.downscale > 1) {
    cv::Mat full;
    cv::resize(disparity, full, left.size(), 0, 0, cv::INTER_NEAREST);  // keeps invalid apart
    disparity = full;
  }
  return disparity;
}

BlockDisparity blockDisparity(const cv::Mat& disparity, const cv::Mat& left,
                              const camera::StereoCamera& camera, const CloudOptions& options) {
  CV_Assert(disparity.type() == CV_32FC1);
  CV_Assert(!options.with_intensity || (left.type() == CV_8UC1 && left.size() == disparity.size()));
  CV_Assert(options.block_cols >= 1 && options.block_rows >= 1);
  const double min_disparity = camera.disparityFromDepth(options.max_range_m);
  const double max_disparity = camera.disparityFromDepth(options.min_range_m);
  const float offset = static_cast<float>(options.disparity_offset_px);
  const int block_pixels = options.block_cols * options.block_rows;
  const int grid_rows = disparity.rows / options.block_rows;
  const int grid_cols = disparity.cols / options.block_cols;

  // Each block's median disparity (x16, fixed point as OpenCV's speckle filter wants;
  // -16 = no point) and mean intensity.
  cv::Mat block_disparity(grid_rows, grid_cols, CV_16SC1, cv::Scalar(-16));
  BlockDisparity blocks{.disparity = cv::Mat(),
                        .intensity = cv::Mat(grid_rows, grid_cols, CV_8UC1, cv::Scalar(0)),
                        .block_cols = options.block_cols,
                        .block_rows = options.block_rows};
  cv::Mat& block_intensity = blocks.intensity;
  std::vector<float> valid(static_cast<size_t>(block_pixels));
  for (int by = 0; by < grid_rows; ++by) {
    const int v0 = by * options.block_rows;
    int16_t* out_disparity = block_disparity.ptr<int16_t>(by);
    uint8_t* out_intensity = block_intensity.ptr<uint8_t>(by);
    for (int bx = 0; bx < grid_cols; ++bx) {
      const int u0 = bx * options.block_cols;
      int count = 0, intensity_sum = 0;
      float sum = 0, lo = std::numeric_limits<float>::max(), hi = 0;
      for (int v = v0; v < v0 + options.block_rows; ++v) {
        const float* row = disparity.ptr<float>(v) + u0;
        const uint8_t* grey = options.with_intensity ? left.ptr<uint8_t>(v) + u0 : nullptr;
        for (int i = 0; i < options.block_cols; ++i) {
          const float d = row[i] + offset;
          if (row[i] > 0 && d >= min_disparity && d <= max_disparity) {
            valid[count++] = d;
            sum += d;
            lo = std::min(lo, d);
            hi = std::max(hi, d);
            if (grey != nullptr) intensity_sum += grey[i];
          }
        }
      }
      if (count == 0 || 2 * count < block_pixels) continue;
      if (hi - lo > options.max_block_span_px) continue;
      // One surface (values within 1 px): their mean; otherwise the median, so that a block
      // on a depth edge takes one side instead of a point in the air between them.
      float value = sum / static_cast<float>(count);
      if (hi - lo > 1.0f) {
        const auto middle = valid.begin() + count / 2;
        std::nth_element(valid.begin(), middle, valid.begin() + count);
        value = *middle;
      }
      out_disparity[bx] = static_cast<int16_t>(std::min(std::lround(value * 16.0f), 32767L));
      out_intensity[bx] = static_cast<uint8_t>(intensity_sum / count);
    }
  }
  // Speckles (small islands of disparity unlike their surroundings) are mostly mismatches;
  // filtering the block grid costs a tenth of filtering the full image.
  if (options.speckle_blocks > 0) {
    cv::filterSpeckles(block_disparity, -16, options.speckle_blocks,
                       static_cast<double>(options.speckle_range_px * 16));
  }
  block_disparity.convertTo(blocks.disparity, CV_32FC1, 1.0 / 16);
  return blocks;
}

common::PointCloud cloudFromBlocks(const BlockDisparity& blocks, const camera::StereoCamera& camera,
                                   const CloudOptions& options) {
  CV_Assert(blocks.disparity.type() == CV_32FC1 &&
            (!options.with_intensity || blocks.intensity.size() == blocks.disparity.size()));
  const int grid_rows = blocks.disparity.rows, grid_cols = blocks.disparity.cols;
  common::PointCloud cloud;
  cloud.points.reserve(static_cast<size_t>(grid_rows) * grid_cols);
  if (options.with_intensity) cloud.intensity.reserve(cloud.points.capacity());
  const double baseline_fx = camera.baseline * camera.fx;  // z = B f / d
  for (int by = 0; by < grid_rows; ++by) {
    const double v_centre = blocks.vCentre(by);
    const float* d = blocks.disparity.ptr<float>(by);
    const uint8_t* grey = blocks.intensity.ptr<uint8_t>(by);
    for (int bx = 0; bx < grid_cols; ++bx) {
      if (d[bx] <= 0) continue;
      const double depth = baseline_fx / d[bx];
      cloud.points.push_back(
          (camera.rayThrough(blocks.uCentre(bx), v_centre) * depth).cast<float>());
      if (options.with_intensity) cloud.intensity.push_back(grey[bx]);
    }
  }
  return options.voxel_m > 0 ? voxelGridDownsample(cloud, options.voxel_m) : cloud;
}

common::PointCloud cloudFromDisparity(const cv::Mat& disparity, const cv::Mat& left,
                                      const camera::StereoCamera& camera,
                                      const CloudOptions& options) {
  return cloudFromBlocks(blockDisparity(disparity, left, camera, options), camera, options);
}

float farthestPoint(const common::PointCloud& cloud, float at_least) {
  float longest = at_least;
  for (const auto& p : cloud.points) longest = std::max(longest, p.norm());
  return longest;
}

uint64_t gridKey(const common::Vec3& p, double voxel_m) {
  auto index = [voxel_m](double x) {
    return static_cast<uint64_t>(static_cast<int64_t>(std::floor(x / voxel_m)) + (1 << 20)) &
           0x1FFFFF;
  };
  return index(p.x()) | index(p.y()) << 21 | index(p.z()) << 42;
}

common::PointCloud voxelGridDownsample(const common::PointCloud& cloud, double voxel_m,
                                       const common::Rigid3& T_grid_cloud) {
  CV_Assert(voxel_m > 0);
  struct Cell {
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    uint32_t intensity_sum = 0;
    uint32_t count = 0;
  };
  const Eigen::Matrix3d R = T_grid_cloud.rotation.toRotationMatrix();
  const common::Vec3 t = T_grid_cloud.translation;
  auto key = [&](const common::Vec3f& p) { return gridKey(R * p.cast<double>() + t, voxel_m); };
  std::unordered_map<uint64_t, uint32_t> slot;
  std::vector<Cell> cells;
  slot.reserve(cloud.size());
  for (size_t i = 0; i < cloud.size(); ++i) {
    auto [it, inserted] =
        slot.try_emplace(key(cloud.points[i]), static_cast<uint32_t>(cells.size()));
    if (inserted) cells.emplace_back();
    Cell& cell = cells[it->second];
    cell.sum += cloud.points[i].cast<double>();
    if (cloud.hasIntensity()) cell.intensity_sum += cloud.intensity[i];
    ++cell.count;
  }
  common::PointCloud out;
  out.points.reserve(cells.size());
  for (const Cell& cell : cells) {
    out.points.push_back((cell.sum / cell.count).cast<float>());
    if (cloud.hasIntensity())
      out.intensity.push_back(static_cast<uint8_t>(cell.intensity_sum / cell.count));
  }
  return out;
}

}  // namespace stereomap::stereo
