// The SE(3) logarithm the pose graph's error uses (the pose-graph paper, eq. 17:
// e = log(T_ij^-1 T_i^-1 T_j)), templated so that Ceres can differentiate it. Tangent vectors
// are ordered (rotation, translation), as the odometry's covariance is.
#pragma once

#include <ceres/rotation.h>

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace stereomap::posegraph {

using Vec6 = Eigen::Matrix<double, 6, 1>;
using Mat6 = Eigen::Matrix<double, 6, 6>;

// log of the transform (q, t): omega = the rotation's angle-axis, rho = V(omega)^-1 t, where V
// is SO(3)'s left Jacobian, so that exp(log(T)) = T. Near the identity the series of V^-1 is
// used (below 0.1 rad): theta^2 appears there without a square root, whose derivative at 0
// is undefined, and without the cancellation of 1 - cos(theta).
template <typename T>
Eigen::Matrix<T, 6, 1> se3Log(const Eigen::Quaternion<T>& q, const Eigen::Matrix<T, 3, 1>& t) {
  // The shorter way round: q and -q are the same rotation.
  const T sign = q.w() < T(0) ? T(-1) : T(1);
  const T wxyz[4] = {sign * q.w(), sign * q.x(), sign * q.y(), sign * q.z()};
  Eigen::Matrix<T, 3, 1> omega;
  ceres::QuaternionToAngleAxis(wxyz, omega.data());

  const T theta2 = omega.squaredNorm();
  T c;  // V^-1 = I - W/2 + c W^2, W = [omega]x
  if (theta2 < T(1e-2)) {
    // The closed form below loses digits to cancellation at small angles (1 - cos).
    c = T(1.0 / 12.0) + theta2 / T(720.0) + theta2 * theta2 / T(30240.0);
  } else {
    using std::cos;
    using std::sin;
    using std::sqrt;
    const T theta = sqrt(theta2);
    c = (T(1) - theta * sin(theta) / (T(2) * (T(1) - cos(theta)))) / theta2;
  }
  const Eigen::Matrix<T, 3, 1> wt = omega.cross(t);
  const Eigen::Matrix<T, 3, 1> rho = t - T(0.5) * wt + c * omega.cross(wt);

  Eigen::Matrix<T, 6, 1> out;
  out << omega, rho;
  return out;
}

// exp of a tangent vector (rotation, translation): the inverse of se3Log.
void se3Exp(const Vec6& xi, Eigen::Quaterniond& q, Eigen::Vector3d& t);

}  // namespace stereomap::posegraph
