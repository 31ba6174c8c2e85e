// How far and how near a stereo rig can map at a map resolution, and the disparity search that
// covers it: the defaults of the depth step come from the camera it is given, not from one
// camera's numbers.
//
// Far: the octree-mapping paper's rule (eq. 5: d_min = sqrt(b f dd / r)) with the matcher's
// measured disparity precision as dd: beyond z = sqrt(r b f / dd) one disparity error moves a
// point by more than a voxel (dz = z^2 dd / (b f)), so the map would smear it. Near: where the
// two views still share most of the image (a disparity of a quarter of the image's width).
// Between them the search is a pyramid of windows: the far end at full resolution, where depth
// needs every sub-pixel; nearer ones on images halved again and again, where a coarser
// disparity still puts a point within its voxel (dz falls as z^2) and costs a quarter as much.
//
//   RigRange range = rigRange(camera, {.map_resolution_m = 0.1, .precision_px = 0.15});
//   range.far_m, range.near_m, range.windows, range.explain()
#pragma once

#include <string>
#include <vector>

#include "onboard/camera/stereo_camera.hpp"

namespace stereomap::stereo {

struct RigRangeOptions {
  double map_resolution_m = 0.1;
  // The matcher's disparity error (pixels of the full image) on the points it keeps
  // (MatcherOptions::precision_px).
  double precision_px = 0.15;
  // The nearest depth searched: its disparity is this share of the image's width.
  double nearest_share_of_width = 0.25;
  // Each window's width in disparities of its own level (a multiple of 16); the window at full
  // resolution may be wider, to reach where the next level's precision suffices.
  int window_disparities = 64;
  int max_levels = 4;  // full resolution, then halved up to max_levels - 1 times
  // An explicit far limit (metres, > 0) instead of the rule's; the near one stays the rig's.
  double far_m = 0;
  // The rule's limit at most this (a long baseline and coarse voxels reach hundreds of metres):
  // the server takes rays up to 100 m (server/core/validate.hpp), and rays to an image's
  // corners are longer than their depth.
  double max_far_m = 70;
};

// One matcher's search: disparities [min_px, min_px + num_px) of the full image, matched on
// images reduced by `downscale` (num_px is a multiple of 16 * downscale).
struct DisparityWindow {
  int downscale = 1;
  int min_px = 0;
  int num_px = 64;
  int maxPx() const { return min_px + num_px; }
};

struct RigRange {
  double far_m = 0, near_m = 0;
  double far_disparity_px = 0, near_disparity_px = 0;
  bool far_from_rule = true;  // false: RigRangeOptions::far_m was given
  bool far_capped = false;    // the rule's limit was beyond RigRangeOptions::max_far_m
  RigRangeOptions options;
  std::vector<DisparityWindow> windows;  // far (full resolution) to near
  // One line for logs and summaries: the limits, why, and the windows.
  std::string explain() const;
};

// The rule's far limit: sqrt(r b f / precision), metres.
double farthestMappable(const camera::StereoCamera& camera, double map_resolution_m,
                        double precision_px);

// The range and windows for this camera. map_resolution_m and precision_px must be positive.
RigRange rigRange(const camera::StereoCamera& camera, const RigRangeOptions& options);

}  // namespace stereomap::stereo
