// The stereo reprojection residual of the pose refinement, in Ceres' automatic-derivative
// form (also the reference the window's own solver is tested against): a point seen through a
// pose (angle-axis + translation, to camera) by the left camera (bx = 0) or the right one
// (bx = baseline), in pixels.
#pragma once

#include <ceres/rotation.h>

#include "onboard/camera/stereo_camera.hpp"
#include "onboard/odometry/detail/rotation.hpp"

namespace stereomap::odometry::detail {

struct PinholeResidual {
  PinholeResidual(const camera::StereoCamera& c, double u, double v, double bx)
      : fx(c.fx), fy(c.fy), cx(c.cx), cy(c.cy), bx(bx), u(u), v(v) {}
  template <typename T>
  void operator()(const T* angle_axis, const T* t, const T* point, T* residual) const {
    T q[3];
    ceres::AngleAxisRotatePoint(angle_axis, point, q);
    q[0] += t[0] - T(bx);
    q[1] += t[1];
    q[2] += t[2];
    if (q[2] < T(1e-6)) q[2] = T(1e-6);
    residual[0] = T(fx) * q[0] / q[2] + T(cx) - T(u);
    residual[1] = T(fy) * q[1] / q[2] + T(cy) - T(v);
  }
  double fx, fy, cx, cy, bx, u, v;
};

}  // namespace stereomap::odometry::detail
