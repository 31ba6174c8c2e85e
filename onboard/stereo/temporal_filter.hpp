// Depth averaged over frames on the block grid: a static surface is seen in many frames in a
// row, and one frame's disparity noise (a fifth of a pixel with a typical camera's image
// noise) spreads its points over several voxels in depth at 4-6 m, which the map keeps as a
// surface two voxels thick. Each block's disparity is carried to the next frame with the
// camera's motion (its 3D point moved into the new camera, projected, corrected to the new
// block's centre by the local disparity gradient) and averaged with the new measurement when
// the two agree; a block that has not been seen consistently in min_frames frames gives no
// point (one-frame mismatches never reach the map).
//
//   TemporalFilter filter(camera, {});
//   BlockDisparity blocks = blockDisparity(disparity, left, camera, cloud_options);
//   filter.apply(blocks, T_world_camera);  // blocks now averaged; unconfirmed ones cleared
//   PointCloud cloud = cloudFromBlocks(blocks, camera, cloud_options);
#pragma once

#include "common/geometry.hpp"
#include "onboard/camera/stereo_camera.hpp"
#include "onboard/stereo/depth.hpp"

namespace stereomap::stereo {

struct TemporalFilterOptions {
  int min_frames = 2;    // a block gives a point once seen consistently this many times
  int max_frames = 8;    // the running mean's memory (then exponential, weight 1 / max)
  double gate_px = 1.0;  // a measurement this far from the carried disparity starts afresh
};

class TemporalFilter {
 public:
  TemporalFilter(const camera::StereoCamera& camera, const TemporalFilterOptions& options = {});

  // Averages `blocks` in place with what earlier frames saw, given the left camera's pose.
  // Blocks that are not yet confirmed are cleared (no point).
  void apply(BlockDisparity& blocks, const common::Rigid3& T_world_camera);
  // Forget the past (tracking lost, a jump in the poses).
  void reset();

 private:
  camera::StereoCamera camera_;
  TemporalFilterOptions options_;
  bool has_previous_ = false;
  common::Rigid3 T_world_previous_;
  cv::Mat previous_disparity_;  // CV_32FC1, averaged, every measured block (confirmed or not)
  cv::Mat previous_count_;      // CV_32SC1, frames averaged
  int block_cols_ = 0, block_rows_ = 0;
};

}  // namespace stereomap::stereo
