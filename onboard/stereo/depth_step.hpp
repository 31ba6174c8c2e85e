// The vehicle's depth step, image pair to cloud, with noise kept out of the map: the images'
// noise is estimated as they come (imageNoiseSigma), and noisy images are matched smoothed,
// with larger blocks, and their block disparities averaged over frames along the camera's
// motion (TemporalFilter) so that one frame's noise and mismatches do not reach the map.
// Clean images go the fast way unchanged (the filter would only cost them recall).
//
//   DepthStep depth(camera, {});                   // noise handling chosen by the images
//   PointCloud cloud = depth.compute(left, right, T_world_camera);
//   depth.reset();                                 // tracking lost: forget the past frames
#pragma once

#include <algorithm>
#include <array>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/geometry.hpp"
#include "common/point_cloud.hpp"
#include "onboard/camera/stereo_camera.hpp"
#include "onboard/stereo/depth.hpp"
#include "onboard/stereo/rig_range.hpp"
#include "onboard/stereo/temporal_filter.hpp"

namespace stereomap::stereo {

enum class NoiseHandling {
  kAuto,  // by the estimated image noise (noisy from noisy_from_sigma grey levels)
  kOff,   // always the clean way
  kOn,    // always the noisy way
};

// How the depth step matches images from a noise level on (measured with
// stereomap-bench-map, docs/BENCHMARKS.md: the typical camera's precision 0.67 -> 0.95 at
// recall 0.90, the poor camera's 0.54 -> 0.93). Rows are matched in pairs, which pays for
// the frame averaging: 9 ms instead of 14 per frame.
struct NoiseLevel {
  double from_sigma = 1.0;  // image noise, grey levels (imageNoiseSigma)
  // The matcher's (MatcherOptions) smoothing along rows, block (odd; above 21 OpenCV's BM
  // takes twice as long, measured), uniqueness and row grouping.
  double smooth_sigma_px = 1.75;
  int block_size = 13;
  int uniqueness_ratio = 30;
  int row_groups = 2;
  double interior_px = 0.5;  // TemporalFilterOptions::interior_px at this level
};

// The depth range from the rig (RigRange): how far depth stays within a voxel of this map,
// with the matcher's precision, and windows that search from there to the rig's nearest depth.
struct AutoRange {
  double map_resolution_m = 0.1;
  double far_m = 0;  // > 0: this far limit instead of the rule's (the windows still reach near)
};

struct DepthOptions {
  MatcherOptions matcher = MatcherOptions::fast();
  CloudOptions cloud;
  // By default the range and the disparity search come from the rig, replacing
  // cloud.max_range_m and the matcher's window; nullopt: those as set (the window moved to the
  // range by fitToRange).
  std::optional<AutoRange> range = AutoRange{};
  NoiseHandling noise = NoiseHandling::kAuto;
  // Noisy images: the levels by rising noise (kOn uses the first). Images count as noisy from
  // the first level's from_sigma, and each level holds down to 0.8 of it, so that a camera
  // near a line does not flap.
  // At the second level one frame's depth is too noisy to pass unconfirmed even inside a
  // smooth surface (poor camera: precision 0.893 with, 0.910 without).
  std::array<NoiseLevel, 2> levels = {{
      {.from_sigma = 1.0,
       .smooth_sigma_px = 1.75,
       .block_size = 13,
       .uniqueness_ratio = 30,
       .row_groups = 2,
       .interior_px = 0.5},
      {.from_sigma = 3.0,
       .smooth_sigma_px = 2.0,
       .block_size = 17,
       .uniqueness_ratio = 30,
       .row_groups = 2,
       .interior_px = 0},
  }};
  // Noisy images' block disparities averaged over frames (interior_px comes from the level);
  // nullopt: off.
  std::optional<TemporalFilterOptions> temporal = TemporalFilterOptions{};
  int noise_every = 10;  // frames between noise estimates (the first frame always)
};

// The matcher a noise level uses: `base` with the level's smoothing, block, uniqueness and
// row grouping.
MatcherOptions levelMatcher(const MatcherOptions& base, const NoiseLevel& level);

class DepthStep {
 public:
  DepthStep(const camera::StereoCamera& camera, const DepthOptions& options = {});
  ~DepthStep();

  // The cloud of one rectified pair (CV_8UC1), in the left camera's frame. T_world_camera is
  // the left camera's pose (any fixed world frame); without it nothing is carried between
  // frames. disparity_offset_px: see CloudOptions. raw_noise_sigma: the image noise measured
  // before rectification (SourceFrame::raw_noise_sigma); once a source has given one, the
  // depth step goes by those, otherwise it estimates on the rectified left image, where
  // interpolation hides most noise (sigma 2 read 0.8 after a slight remap).
  common::PointCloud compute(const cv::Mat& left, const cv::Mat& right,
                             const std::optional<common::Rigid3>& T_world_camera,
                             double disparity_offset_px = 0,
                             std::optional<double> raw_noise_sigma = std::nullopt);
  // Why this camera's images cannot be searched (searchProblem), or empty; with one, compute()
  // gives no points.
  std::string problem() const;
  // Forgets earlier frames (tracking lost, a jump in the poses).
  void reset();

  // The latest image noise estimate (grey levels), whether images count as noisy and at which
  // level (index into DepthOptions::levels; -1: clean).
  double noiseSigma() const { return noise_sigma_; }
  // The rig's range and windows (nullopt when DepthOptions::range was), and the farthest depth
  // a point may have, either way.
  const std::optional<RigRange>& range() const { return range_; }
  double maxRange() const { return std::max(options_.cloud.max_range_m, noisy_max_range_m_); }
  const CloudOptions& cloudOptions() const { return options_.cloud; }  // as in effect
  // The range in a line (RigRange::explain, and how far averaged depth reaches); empty when
  // DepthOptions::range was nullopt.
  std::string describeRange() const;
  bool noisy() const { return level_ >= 0; }
  int level() const { return level_; }

 private:
  int levelFor(double sigma) const;
  void setLevel(int level);
  StereoMatcher& matcher();  // the current level's

  camera::StereoCamera camera_;
  DepthOptions options_;
  std::optional<RigRange> range_;
  // The noise levels' matcher before their own settings (levelMatcher), and their farthest
  // depth: averaged depth may reach farther than one frame's.
  MatcherOptions noisy_matcher_;
  double noisy_max_range_m_ = 0;
  std::string problem_;  // problem(), as found at construction
  // The clean matcher, then one per level; each made when first needed.
  std::vector<std::unique_ptr<StereoMatcher>> matchers_;
  std::optional<TemporalFilter> filter_;
  double noise_sigma_ = 0;
  int level_ = -1;
  bool raw_noise_ = false;  // a source gave the noise before rectification
  uint64_t frames_ = 0;
};

}  // namespace stereomap::stereo
