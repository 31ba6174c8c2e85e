// Geometry types shared by every stereomap module: rigid transforms named by their frames
// (`T_a_b` maps a point from frame b into frame a), points and axis-aligned boxes.
// Units are metres and radians; quaternions are Hamilton, stored x y z w (Eigen coeffs()).
// Camera frame is OpenCV's (x right, y down, z forward); the map frame is z-up.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace stereomap::common {

using Vec3 = Eigen::Vector3d;
using Vec3f = Eigen::Vector3f;
using Quat = Eigen::Quaterniond;

// A rigid transform T_a_b: p_a = rotation * p_b + translation.
struct Rigid3 {
  Quat rotation = Quat::Identity();
  Vec3 translation = Vec3::Zero();

  static Rigid3 identity() { return {}; }
  Vec3 operator*(const Vec3& p_b) const { return rotation * p_b + translation; }
  // Composition: (T_a_b * T_b_c) = T_a_c.
  Rigid3 operator*(const Rigid3& T_b_c) const {
    return {rotation * T_b_c.rotation, rotation * T_b_c.translation + translation};
  }
  Rigid3 inverse() const {
    const Quat r_inv = rotation.conjugate();
    return {r_inv, -(r_inv * translation)};
  }
};

// The pose a fraction s (0..1) of the way from a to b: position linearly, attitude by slerp.
Rigid3 interpolate(const Rigid3& a, const Rigid3& b, double s);

// Axis-aligned box; empty when min > max on any axis.
struct Box3 {
  Vec3 min = Vec3::Constant(std::numeric_limits<double>::infinity());
  Vec3 max = Vec3::Constant(-std::numeric_limits<double>::infinity());

  bool empty() const { return (min.array() > max.array()).any(); }
  void extend(const Vec3& p) {
    min = min.cwiseMin(p);
    max = max.cwiseMax(p);
  }
  bool contains(const Vec3& p) const {
    return (p.array() >= min.array()).all() && (p.array() <= max.array()).all();
  }
};

// Rotation that takes OpenCV camera axes (x right, y down, z forward) to a FLU body frame
// (x forward, y left, z up) whose camera looks along body +x: R_body_camera.
Quat bodyFromCameraRotation();

// True when q has finite coefficients and unit norm within `tolerance`.
bool isUnitQuaternion(const Quat& q, double tolerance = 1e-3);

}  // namespace stereomap::common
