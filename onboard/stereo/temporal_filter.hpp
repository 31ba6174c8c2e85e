// Depth averaged over frames on the block grid: a static surface is seen in many frames in a
// row, and one frame's disparity noise (a fifth of a pixel with a typical camera's image
// noise) spreads its points over several voxels in depth at 4-6 m, which the map keeps as a
// surface two voxels thick. Each block's disparity is carried to the next frame with the
// camera's motion (each new block's point is moved into the previous camera, the previous
// disparity read there, moved along its surface's slope, and that point brought back) and averaged
// with the new measurement when the two agree; a block that has not been seen consistently in
// min_frames frames gives no point (one-frame mismatches never reach the map).
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
  // ... unless their depths lie within this much (metres; 0: off; the depth step sets the map's
  // voxel): near points move by pixels of disparity with a pose's small error and still agree
  // within a voxel.
  double gate_depth_m = 0;
  // The depth range's rule (rig_range.hpp) for one frame's disparity, > 0: a block averaged
  // over n frames gives its point only from far_disparity_px / n^(1/4) on (its mean is sqrt(n)
  // times as precise, so it may lie farther); 0: no limit here.
  double far_disparity_px = 0;
  // Unconfirmed blocks inside a smooth surface (all 8 neighbours within this many pixels)
  // give their point at once; 0: off.
  double interior_px = 0;
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
  struct Frame {
    cv::Mat disparity;  // CV_32FC1, averaged, every measured block (confirmed or not)
    cv::Mat count;      // CV_32SC1, frames averaged
    common::Rigid3 T_world_camera;
    int block_cols = 0, block_rows = 0;
  };
  // The pose change between the frames as the per-block arithmetic uses it (float; translations
  // divided by baseline * fx, so that a block's point needs no depth).
  struct Transforms {
    Eigen::Matrix3f R_previous_current;
    Eigen::Vector3f t_previous_current_fb;
    Eigen::Vector3f current_previous_z_row;  // the third row of R_current_previous
    float current_previous_z_fb = 0;
  };
  // The previous frame's view of a block's point (on `ray`, z = 1, at the measured disparity):
  // its disparity there, brought into this camera, when within the gate of the measured one,
  // with that frame's count.
  bool carry(const Frame& frame, const Transforms& transforms, const Eigen::Vector3f& ray,
             float measured, const BlockDisparity& blocks, float& carried, int& count) const;
  // Two disparities of one surface: within gate_px, or within gate_depth_m in depth.
  bool agree(float a, float b) const;
  // The smallest disparity a block averaged over `count` frames may have (far_disparity_px).
  float nearestFar(int count) const;
  // Block (x, y)'s disparity moved to grid position (gx, gy) along its surface; 0: none.
  float disparityAt(const Frame& frame, int x, int y, double gx, double gy) const;

  camera::StereoCamera camera_;
  TemporalFilterOptions options_;
  bool has_previous_ = false;
  Frame previous_;
  Frame spare_;  // the one before, its buffers reused for the next frame
};

}  // namespace stereomap::stereo
