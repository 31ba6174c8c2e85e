#include "common/geometry.hpp"

#include <cmath>

namespace stereomap::common {

Quat bodyFromCameraRotation() {
  Eigen::Matrix3d R_body_camera;
  // Columns are the camera axes expressed in the body frame.
  R_body_camera.col(0) = Vec3(0, -1, 0);  // camera x (right) = body -y
  R_body_camera.col(1) = Vec3(0, 0, -1);  // camera y (down)  = body -z
  R_body_camera.col(2) = Vec3(1, 0, 0);   // camera z (ahead) = body +x
  return Quat(R_body_camera);
}

bool isUnitQuaternion(const Quat& q, double tolerance) {
  if (!q.coeffs().allFinite()) return false;
  return std::abs(q.norm() - 1.0) <= tolerance;
}

Rigid3 interpolate(const Rigid3& a, const Rigid3& b, double s) {
  return {a.rotation.slerp(s, b.rotation).normalized(),
          (1 - s) * a.translation + s * b.translation};
}

}  // namespace stereomap::common
