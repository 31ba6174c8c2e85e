#include "onboard/posegraph/se3.hpp"

#include <cmath>

namespace stereomap::posegraph {

void se3Exp(const Vec6& xi, Eigen::Quaterniond& q, Eigen::Vector3d& t) {
  const Eigen::Vector3d omega = xi.head<3>();
  const Eigen::Vector3d rho = xi.tail<3>();
  const double theta = omega.norm();
  q = theta < 1e-12 ? Eigen::Quaterniond::Identity()
                    : Eigen::Quaterniond(Eigen::AngleAxisd(theta, omega / theta));
  // t = V rho, V = I + b W + a W^2 (W = [omega]x).
  double a, b;
  const double theta2 = theta * theta;
  if (theta < 0.1) {  // series: the closed form cancels digits at small angles
    b = 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0;
    a = 1.0 / 6.0 - theta2 / 120.0 + theta2 * theta2 / 5040.0;
  } else {
    b = (1.0 - std::cos(theta)) / (theta * theta);
    a = (theta - std::sin(theta)) / (theta * theta * theta);
  }
  const Eigen::Vector3d w_rho = omega.cross(rho);
  t = rho + b * w_rho + a * omega.cross(w_rho);
}

}  // namespace stereomap::posegraph
