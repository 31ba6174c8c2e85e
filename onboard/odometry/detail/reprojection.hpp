// The stereo reprojection residual shared by the pose refinement and the window adjustment:
// a world point seen through a pose (angle-axis + translation, world to camera) by the left
// camera (bx = 0) or the right one (bx = baseline), in pixels.
#pragma once

#include <ceres/rotation.h>

#include "common/geometry.hpp"
#include "onboard/camera/stereo_camera.hpp"

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

inline Eigen::Vector3d angleAxisOf(const common::Quat& q) {
  const Eigen::AngleAxisd aa(q.normalized());
  return aa.axis() * aa.angle();
}

inline common::Quat quatOf(const Eigen::Vector3d& angle_axis) {
  const double angle = angle_axis.norm();
  return angle > 0 ? common::Quat(Eigen::AngleAxisd(angle, angle_axis / angle)) : common::Quat::Identity();
}

}  // namespace stereomap::odometry::detail
