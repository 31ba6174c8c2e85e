// The rectified stereo camera model used on board: a pinhole camera (fx, fy, cx, cy) with a
// second camera `baseline` metres along +x. Depth from disparity is z = baseline * fx / d.
// The default is the camera of the stereo-VO paper (Bumblebee2, 640x480).
#pragma once

#include <optional>

#include "common/geometry.hpp"

namespace stereomap::camera {

struct StereoCamera {
  int width = 640;
  int height = 480;
  double fx = 492.45;
  double fy = 492.45;
  double cx = 321.16;
  double cy = 250.95;
  double baseline = 0.120081;  // metres

  // Ray through pixel (u, v) in the camera frame, scaled so that its z is 1.
  common::Vec3 rayThrough(double u, double v) const { return {(u - cx) / fx, (v - cy) / fy, 1.0}; }
  // Depth (z, metres) of a disparity in pixels; disparity must be > 0.
  double depthFromDisparity(double disparity_px) const { return baseline * fx / disparity_px; }
  double disparityFromDepth(double depth_m) const { return baseline * fx / depth_m; }
  // Projects a camera-frame point; nullopt when it is behind the camera.
  std::optional<Eigen::Vector2d> project(const common::Vec3& p_camera) const {
    if (p_camera.z() <= 0) return std::nullopt;
    return Eigen::Vector2d(fx * p_camera.x() / p_camera.z() + cx,
                           fy * p_camera.y() / p_camera.z() + cy);
  }
};

}  // namespace stereomap::camera
