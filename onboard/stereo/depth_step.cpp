#include "onboard/stereo/depth_step.hpp"

#include <cmath>
#include <cstdio>

#include "onboard/camera/image_noise.hpp"

namespace stereomap::stereo {

MatcherOptions levelMatcher(const MatcherOptions& base, const NoiseLevel& level) {
  MatcherOptions matcher = base;
  matcher.smooth_sigma_px = level.smooth_sigma_px;
  matcher.block_size = level.block_size;
  matcher.uniqueness_ratio = level.uniqueness_ratio;
  matcher.row_groups = level.row_groups;
  // Noise is in both windows' fit: a clear winner is rarer and a wrong one reached the map
  // (sim, typical camera: precision 0.9704 -> 0.9696 with it, map_accuracy_test).
  matcher.arbitrate = false;
  // Likewise the semi-global fill: on the sim's typical camera it found nothing the frames'
  // averaging did not, and cost precision (0.9704 -> 0.9702, map_accuracy_test).
  matcher.fill_nearer = false;
  return matcher;
}

DepthStep::DepthStep(const camera::StereoCamera& camera, const DepthOptions& options)
    : camera_(camera), options_(options), matchers_(options.levels.size() + 1) {
  CV_Assert(options.noise_every >= 1);
  if (options.range) {
    const RigRangeOptions rig =
        rigRangeOptions(options.matcher, options.range->map_resolution_m, options.range->far_m);
    range_ = rigRange(camera, rig);
    options_.cloud.max_range_m = range_->far_m;
    options_.cloud.max_block_depth_span_m = options.range->map_resolution_m;
    options_.cloud.min_range_m = std::min(options_.cloud.min_range_m, range_->near_m);
    options_.matcher = fitToWindows(options.matcher, range_->windows);
    noisy_matcher_ = options_.matcher;
    noisy_max_range_m_ = range_->far_m;
    if (options.temporal && rig.far_m <= 0) {
      // Noisy images' depth is averaged over up to max_frames frames along the poses: the
      // matchers of the noise levels search as far as such a mean stays within a voxel, and
      // the filter keeps each block to what its own count allows.
      RigRangeOptions averaged = rig;
      averaged.precision_px /= std::sqrt(options.temporal->max_frames);
      const RigRange noisy = rigRange(camera, averaged);
      noisy_matcher_ = fitToWindows(options.matcher, noisy.windows);
      noisy_max_range_m_ = noisy.far_m;
    }
  } else {
    options_.matcher = fitToRange(options.matcher, camera, options.cloud.max_range_m);
    noisy_matcher_ = options_.matcher;
    noisy_max_range_m_ = options_.cloud.max_range_m;
  }
  for (size_t i = 0; i < options.levels.size(); ++i) {
    CV_Assert(options.levels[i].from_sigma > 0 && options.levels[i].block_size % 2 == 1 &&
              (i == 0 || options.levels[i].from_sigma > options.levels[i - 1].from_sigma));
  }
  if (options.noise == NoiseHandling::kOn) setLevel(0);
  problem_ = problem();
}

void DepthStep::setLevel(int level) {
  if (level == level_) return;
  level_ = level;
  // Other blocks, other noise: averaging starts afresh.
  filter_.reset();
  if (level >= 0 && options_.temporal) {
    TemporalFilterOptions temporal = *options_.temporal;
    temporal.interior_px = options_.levels[static_cast<size_t>(level)].interior_px;
    if (range_) {
      temporal.gate_depth_m = range_->options.map_resolution_m;
      temporal.far_disparity_px = range_->far_disparity_px;
    }
    filter_.emplace(camera_, temporal);
  }
}

std::string DepthStep::problem() const {
  const std::string clean = searchProblem(options_.matcher, camera_.width);
  return clean.empty() ? searchProblem(noisy_matcher_, camera_.width) : clean;
}

std::string DepthStep::describeRange() const {
  if (!range_) return {};
  std::string text = range_->explain();
  if (noisy_max_range_m_ > range_->far_m) {
    char more[96];
    std::snprintf(more, sizeof(more), "; noisy images' depth averaged over frames up to %.3g m",
                  noisy_max_range_m_);
    text += more;
  }
  return text;
}

DepthStep::~DepthStep() = default;

void DepthStep::reset() {
  if (filter_) filter_->reset();
}

int DepthStep::levelFor(double sigma) const {
  int level = -1;
  for (int i = 0; i < static_cast<int>(options_.levels.size()); ++i) {
    // The current level and those below it hold down to 0.8 of their start.
    const double from = options_.levels[static_cast<size_t>(i)].from_sigma;
    if (sigma >= (i <= level_ ? 0.8 * from : from)) level = i;
  }
  return level;
}

StereoMatcher& DepthStep::matcher() {
  auto& slot = matchers_[static_cast<size_t>(level_ + 1)];
  if (!slot) {
    slot = std::make_unique<StereoMatcher>(
        level_ < 0 ? options_.matcher
                   : levelMatcher(noisy_matcher_, options_.levels[static_cast<size_t>(level_)]));
  }
  return *slot;
}

common::PointCloud DepthStep::compute(const cv::Mat& left, const cv::Mat& right,
                                      const std::optional<common::Rigid3>& T_world_camera,
                                      double disparity_offset_px,
                                      std::optional<double> raw_noise_sigma) {
  if (options_.noise == NoiseHandling::kAuto) {
    if (raw_noise_sigma) {
      raw_noise_ = true;
      noise_sigma_ = *raw_noise_sigma;
      setLevel(levelFor(noise_sigma_));
    } else if (!raw_noise_ && frames_ % options_.noise_every == 0) {
      noise_sigma_ = camera::imageNoiseSigma(left);
      setLevel(levelFor(noise_sigma_));
    }
  }
  ++frames_;
  if (!problem_.empty()) return {};
  CloudOptions cloud = options_.cloud;
  cloud.disparity_offset_px = disparity_offset_px;
  const cv::Mat disparity = matcher().compute(left, right);
  if (level_ < 0) return cloudFromDisparity(disparity, left, camera_, cloud);
  // Blocks as far as an average may reach; the filter keeps each to its own count's range,
  // and without it (no pose) the one frame's range holds.
  const bool averaged = filter_ && T_world_camera;
  if (averaged) cloud.max_range_m = noisy_max_range_m_;
  auto blocks = blockDisparity(disparity, left, camera_, cloud);
  if (averaged) {
    filter_->apply(blocks, *T_world_camera);
  } else {
    reset();
  }
  return cloudFromBlocks(blocks, camera_, cloud);
}

}  // namespace stereomap::stereo
