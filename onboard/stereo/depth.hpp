// Dense depth on board: a stereo matcher over rectified grey pairs (OpenCV block matching or
// semi-global matching) and the conversion of a disparity image into a down-sampled point
// cloud in the left camera frame (z = baseline * fx / d).
//
//   StereoMatcher matcher({.kind = MatcherKind::kBlockMatching});
//   cv::Mat disparity = matcher.compute(left, right);
//   PointCloud cloud = cloudFromDisparity(disparity, left, camera, {.max_range_m = 6});
#pragma once

#include <memory>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "common/geometry.hpp"
#include "common/point_cloud.hpp"
#include "onboard/camera/stereo_camera.hpp"
#include "onboard/stereo/rig_range.hpp"

namespace stereomap::stereo {

enum class MatcherKind { kBlockMatching, kSemiGlobal };
enum class SemiGlobalMode { kFivePaths, kThreeWay, kEightPaths, kEightPathsFourLines };
// Applied to both images before matching. The matchers already use a horizontal Sobel
// internally (kNone keeps just that); kLoG is the octree-mapping paper's Laplacian of
// Gaussian.
enum class Prefilter { kNone, kLoG };

// Every knob of the matcher. Start from fast() or accurate() (documented in
// docs/BENCHMARKS.md with their measured accuracy and speed) rather than from scratch.
struct MatcherOptions {
  MatcherKind kind = MatcherKind::kSemiGlobal;
  SemiGlobalMode mode = SemiGlobalMode::kThreeWay;
  int num_disparities = 80;  // multiple of 16; the nearest depth is baseline * fx / this
  int min_disparity = 0;     // see minimumDisparity(): far points the map cannot use
  int block_size = 5;        // odd
  // SGBM smoothness penalties per pixel of the block: P1 = p1 * block², P2 = p2 * block².
  int p1 = 8;
  int p2 = 32;
  int prefilter_cap = 63;
  int uniqueness_ratio = 15;    // percent margin of the best cost over the second best
  int left_right_max_diff = 1;  // left-right consistency in pixels; < 0 disables the check
  int speckle_window = 100;     // pixels; 0 disables speckle filtering
  int speckle_range = 2;
  int texture_threshold = 10;  // BM only
  // Pad the images on the left so that the first num_disparities columns get estimates too
  // (a match whose window would reach outside the right image, d > x - block/2, is dropped).
  bool pad_left = true;
  // Match at 1/downscale resolution and scale the disparity back (speed for large images).
  int downscale = 1;
  // Match on images whose rows are averaged in groups of this many (after downscale), and
  // give each row of a group the group's disparity. Rectified epipolar lines are rows, so
  // the disparity keeps its full horizontal resolution while matching costs 1/row_groups,
  // and averaging two rows halves the noise's variance. The cloud's blocks
  // (CloudOptions::block_rows) should be a multiple of it; the block_size window then spans
  // block_size * row_groups image rows.
  int row_groups = 1;
  Prefilter prefilter = Prefilter::kNone;
  double log_sigma_px = 1.0;
  // Gaussian smoothing of both images before matching, pixels (0: off); along the rows only
  // when rows are grouped. Image noise is white and the matching cost's Sobel amplifies it;
  // most scene texture is coarser.
  double smooth_sigma_px = 0;
  // Edge-aware filling of the disparity with OpenCV contrib's WLS filter (ximgproc), using
  // a right-view matcher for confidence; 0 disables. Dense but measured less accurate on
  // Middlebury than the accurate preset (docs/BENCHMARKS.md), so off by default.
  double wls_lambda = 0;
  double wls_sigma = 1.5;
  // Nearer disparities searched on reduced images (RigRange's windows after the first), each
  // with this matcher's settings at its own scale (its block covering as much of the full
  // image as the first window's). A pixel takes the finest window's match; matches on a
  // window's inner edges (a disparity beyond the window lands there) give none, and where two
  // windows disagree the one whose window of the full images fits clearly better wins (none
  // when neither does).
  std::vector<DisparityWindow> nearer;
  // Where two windows disagree, let the images decide (above); false: neither is kept.
  bool arbitrate = true;
  // Nearer windows on reduced images (block matching only): where block matching finds
  // nothing, semi-global matching over the same window fills in, if the images confirm the
  // match (its window fits the right image's clearly better than two unrelated patches would,
  // and holds texture). Block matching leaves holes in leaves and slanted surfaces that the
  // semi-global paths bridge. It runs only where block matching found surfaces in the window
  // (a fiftieth of the image), which it completes.
  bool fill_nearer = true;
  // A second look at the ground: where the image holds a plane whose disparity rises down the
  // image (a road, terrain ahead) too steeply for the block, the rows below its horizon are
  // matched again on a right image sheared by it, and its disparities fill what the windows
  // missed (StereoMatcher keeps the plane from frame to frame).
  bool ground = true;
  // The disparity error of the points this preset's clouds keep (full-image pixels), as the
  // depth range's rule needs it (RigRangeOptions::precision_px): the median absolute error of
  // the block disparities on Middlebury's pairs with sub-pixel truth (stereomap-bench-realrigs,
  // docs/BENCHMARKS.md).
  double precision_px = 0.1;

  // Real time on board: <= 15 ms per 640x480 frame with rectification and cloud, one core.
  static MatcherOptions fast();
  // Best accuracy within 60 ms per 640x480 frame, one core.
  static MatcherOptions accurate();
};

// The matchers' disparity count for a largest expected disparity: a multiple of 16.
int disparitiesFor(int max_disparity_px);
// The octree-mapping paper's rule (eq. 5): d_min = ceil(sqrt(b * f * dd / r)). Below it one
// disparity step spans more than a voxel of resolution r, so such points are not worth
// matching. dd is the disparity uncertainty (0.5 px in the paper).
int minimumDisparity(double baseline_m, double fx_px, double resolution_m, double dd_px = 0.5);

// The matcher's search window moved to what the cloud keeps: it starts at the disparity of
// max_range_m (rounded down; farther matches would be dropped anyway) unless min_disparity
// already starts nearer, and keeps its width, so the nearest depth seen is
// baseline * fx / (min_disparity + num_disparities).
MatcherOptions fitToRange(MatcherOptions options, const camera::StereoCamera& camera,
                          double max_range_m);
// The rig's range (rig_range.hpp) as this matcher sees it: its precision, its window's width.
RigRangeOptions rigRangeOptions(const MatcherOptions& matcher, double map_resolution_m,
                                double far_m = 0);
// The matcher searching a rig's windows: the first as min_disparity / num_disparities at full
// resolution (downscale 1), the rest as `nearer`.
MatcherOptions fitToWindows(MatcherOptions options, const std::vector<DisparityWindow>& windows);

// Why a matcher cannot search images `image_width` wide (a disparity beyond the image, or
// beyond OpenCV's 16-bit fixed point: a calibration with an absurd focal length or baseline
// puts even the far limit there), or empty when it can.
std::string searchProblem(const MatcherOptions& options, int image_width);

class StereoMatcher {
 public:
  explicit StereoMatcher(const MatcherOptions& options = MatcherOptions::fast());
  const MatcherOptions& options() const;
  ~StereoMatcher();
  StereoMatcher(StereoMatcher&&) noexcept;
  StereoMatcher& operator=(StereoMatcher&&) noexcept;

  // Disparity of the left image in pixels (CV_32FC1, sub-pixel in 1/16 px steps); negative
  // values are invalid. Both images must be CV_8UC1 of the same size. Reuses internal
  // buffers: one matcher per thread.
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
  // Speckle filter on the block grid: islands of at most this many blocks whose disparity
  // differs from their surroundings by more than speckle_range_px are dropped (0: off).
  // Then keep one point per voxel of this edge (their centroid and mean intensity); 0: off.
  // Thins the many near points without touching far ones; pick the map's resolution.
  double voxel_m = 0;
  int speckle_blocks = 40;
  double speckle_range_px = 1.0;
  // A block whose valid disparities span more than this gives no point: a depth edge or a
  // mismatch, whose points would land between or behind surfaces (at 0.05 m voxels: precision
  // 0.949 without, 0.966 with 0.5, on the sim; docs/BENCHMARKS.md).
  double max_block_span_px = 0.5;
  // ... unless its depths lie within this much (metres; 0: off; the depth step sets the map's
  // voxel): a near surface slanted to the camera (a road, a floor) spans pixels of disparity in
  // a block and is still one surface within a voxel.
  double max_block_depth_span_m = 0;
  // Added to every valid disparity before anything else: the right image's offset against its
  // calibration (raw minus calibrated column), as the odometry estimates it.
  double disparity_offset_px = 0;
};

// The disparity image reduced to one value per block_cols x block_rows block: the mean valid
// disparity of the block (the median when the values span more than 1 px and
// max_block_span_px allows it), quantised to 1/16 px as the matchers' (CV_32FC1, pixels,
// <= 0: no point), with the block's mean intensity (CV_8UC1). Blocks with fewer than half of their
// pixels valid or spanning more than max_block_span_px, and speckles of blocks, give no point;
// invalid disparities never count.
struct BlockDisparity {
  cv::Mat disparity;
  cv::Mat intensity;
  int block_cols = 5, block_rows = 2;
  // The pixel at a block's centre, where its point's ray goes through.
  double uCentre(int bx) const { return bx * block_cols + (block_cols - 1) / 2.0; }
  double vCentre(int by) const { return by * block_rows + (block_rows - 1) / 2.0; }
};
BlockDisparity blockDisparity(const cv::Mat& disparity, const cv::Mat& left,
                              const camera::StereoCamera& camera, const CloudOptions& options = {});

// One point per block with a disparity, on the ray through the block's centre, then
// options.voxel_m's thinning. Points are kept by depth (z <= max_range_m), so rays to the
// image's corners are longer than max_range_m.
common::PointCloud cloudFromBlocks(const BlockDisparity& blocks, const camera::StereoCamera& camera,
                                   const CloudOptions& options = {});

// blockDisparity() then cloudFromBlocks().
common::PointCloud cloudFromDisparity(const cv::Mat& disparity, const cv::Mat& left,
                                      const camera::StereoCamera& camera,
                                      const CloudOptions& options = {});

// One point per occupied cubic voxel of edge `voxel_m` (the centroid of its points, with
// their mean intensity), in order of first appearance. voxel_m must be positive.
// The distance to the cloud's farthest point, at least `at_least`: clouds are cut by depth
// (z), so rays to the image's corners are longer than max_range_m, and an octree given the
// range limit alone would cut them.
float farthestPoint(const common::PointCloud& cloud, float at_least);

// A voxel of edge voxel_m (floor(x / voxel_m) per axis, as OctoMap keys its voxels) packed
// into 64 bits: 21 bits per axis, +-1e6 voxels around the grid's origin.
uint64_t gridKey(const common::Vec3& p, double voxel_m);

// The grid may lie in another frame: T_grid_cloud takes the cloud's points into it (the map's
// voxels, for a cloud in the camera frame); the points kept stay in the cloud's frame.
common::PointCloud voxelGridDownsample(const common::PointCloud& cloud, double voxel_m,
                                       const common::Rigid3& T_grid_cloud = {});

}  // namespace stereomap::stereo
