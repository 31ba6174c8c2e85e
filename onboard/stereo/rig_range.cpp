#include "onboard/stereo/rig_range.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>

#include <opencv2/core.hpp>

namespace stereomap::stereo {

namespace {

int roundUp(double value, int step) {
  return static_cast<int>(std::ceil(value / step - 1e-9)) * step;
}

}  // namespace

double farthestMappable(const camera::StereoCamera& camera, double map_resolution_m,
                        double precision_px) {
  CV_Assert(map_resolution_m > 0 && precision_px > 0);
  return std::sqrt(map_resolution_m * camera.baseline * camera.fx / precision_px);
}

RigRange rigRange(const camera::StereoCamera& camera, const RigRangeOptions& options) {
  CV_Assert(options.window_disparities >= 16 && options.window_disparities % 16 == 0);
  CV_Assert(options.max_levels >= 1 && options.nearest_share_of_width > 0);
  RigRange range;
  range.options = options;
  range.far_from_rule = !(options.far_m > 0);
  range.far_m = options.far_m;
  if (range.far_from_rule) {
    const double rule = farthestMappable(camera, options.map_resolution_m, options.precision_px);
    range.far_capped = rule > options.max_far_m;
    range.far_m = std::min(rule, options.max_far_m);
  }
  range.far_disparity_px = camera.disparityFromDepth(range.far_m);
  // The window's far end below the far limit's disparity (rounded down, as fitToRange): what
  // lies farther is matched at the window's edge and dropped by the cloud's range.
  const int far_px = static_cast<int>(std::floor(range.far_disparity_px));
  range.near_disparity_px = std::max(options.nearest_share_of_width * camera.width,
                                     range.far_disparity_px + options.window_disparities);
  range.near_m = camera.depthFromDisparity(range.near_disparity_px);

  int low = far_px;
  for (int level = 0; level < options.max_levels; ++level) {
    const int scale = 1 << level;
    const int step = 16 * scale;
    // Where the next level's coarser disparity is precise enough: its error is 2^(level+1)
    // times this one's, and the rule's range shrinks with the square root of the error.
    const double next_precise = range.far_disparity_px * std::sqrt(2.0 * scale);
    int width = std::max(options.window_disparities * scale, roundUp(next_precise - low, step));
    const bool last = level + 1 == options.max_levels || low + width >= range.near_disparity_px;
    if (last) width = std::max(step, roundUp(range.near_disparity_px - low, step));
    range.windows.push_back({.downscale = scale, .min_px = low, .num_px = width});
    if (last) break;
    // The next window overlaps this one by a few of its pixels: each window's edge values are
    // dropped (a match beyond a window lands on its edge), and no disparity may fall between.
    const int next_scale = 2 * scale;
    low = (low + width - 2 * next_scale) / next_scale * next_scale;
  }
  return range;
}

std::string RigRange::explain() const {
  std::ostringstream out;
  out.precision(3);
  if (far_capped) {
    out << "depth " << near_m << "-" << far_m << " m (the rule's far limit capped: the server "
        << "takes rays up to 100 m)";
  } else if (far_from_rule) {
    out << "depth " << near_m << "-" << far_m << " m: beyond " << far_m << " m a "
        << options.precision_px << " px disparity error moves a point by more than a "
        << options.map_resolution_m << " m voxel";
  } else {
    out << "depth " << near_m << "-" << far_m << " m (far limit as given)";
  }
  out << "; disparities";
  for (const auto& w : windows) {
    out << " " << w.min_px << "-" << w.maxPx();
    if (w.downscale > 1) out << " at 1/" << w.downscale;
  }
  return out.str();
}

}  // namespace stereomap::stereo
