// Angle-axis vectors and quaternions, for the odometry's solvers.
#pragma once

#include <Eigen/Geometry>

#include "common/geometry.hpp"

namespace stereomap::odometry::detail {

inline Eigen::Vector3d angleAxisOf(const common::Quat& q) {
  const Eigen::AngleAxisd aa(q.normalized());
  return aa.axis() * aa.angle();
}

inline common::Quat quatOf(const Eigen::Vector3d& angle_axis) {
  const double angle = angle_axis.norm();
  return angle > 0 ? common::Quat(Eigen::AngleAxisd(angle, angle_axis / angle))
                   : common::Quat::Identity();
}

}  // namespace stereomap::odometry::detail
