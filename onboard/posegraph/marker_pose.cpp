#include "onboard/posegraph/marker_pose.hpp"

#include <Eigen/Geometry>
#include <Eigen/SVD>

namespace stereomap::posegraph {
namespace {

using common::Vec3;

// The nearest rotation to M (Frobenius), or nullopt when M is degenerate.
std::optional<Eigen::Matrix3d> nearestRotation(const Eigen::Matrix3d& M) {
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(M, Eigen::ComputeFullU | Eigen::ComputeFullV);
  if (svd.singularValues()(2) < 1e-9 * std::max(1.0, svd.singularValues()(0))) return std::nullopt;
  Eigen::Matrix3d R = svd.matrixU() * svd.matrixV().transpose();
  if (R.determinant() < 0) {
    Eigen::Matrix3d flip = Eigen::Matrix3d::Identity();
    flip(2, 2) = -1;
    R = svd.matrixU() * flip * svd.matrixV().transpose();
  }
  return R;
}

// The midpoint of the shortest segment between the lines a0 + s (a1 - a0) and
// b0 + u (b1 - b0); nullopt for parallel lines.
std::optional<Vec3> crossingPoint(const Vec3& a0, const Vec3& a1, const Vec3& b0, const Vec3& b1) {
  const Vec3 d1 = a1 - a0, d2 = b1 - b0, r = a0 - b0;
  const double a = d1.dot(d1), b = d1.dot(d2), c = d2.dot(d2), d = d1.dot(r), e = d2.dot(r);
  const double denominator = a * c - b * b;
  if (denominator < 1e-12 * a * c) return std::nullopt;
  const double s = (b * e - c * d) / denominator;
  const double u = (a * e - b * d) / denominator;
  return 0.5 * ((a0 + s * d1) + (b0 + u * d2));
}

// D = (A_1, A_2, B) of eqs. 10-12, or nullopt when A_1 and A_2 are parallel.
std::optional<Eigen::Matrix3d> vectorCrossBasis(const Markers& p) {
  const Vec3 a1 = (p[2] - p[0]).normalized();
  const Vec3 a2 = (p[3] - p[1]).normalized();
  const Vec3 b = a1.cross(a2);
  if (!a1.allFinite() || !a2.allFinite() || b.norm() < 1e-6) return std::nullopt;
  Eigen::Matrix3d D;
  D << a1, a2, b.normalized();
  return D;
}

}  // namespace

std::optional<common::Rigid3> leastSquaresPose(const std::vector<Vec3>& model,
                                               const std::vector<Vec3>& world) {
  if (model.size() != world.size() || model.size() < 3) return std::nullopt;
  Eigen::Matrix3Xd src(3, model.size()), dst(3, world.size());
  for (size_t i = 0; i < model.size(); ++i) {
    if (!model[i].allFinite() || !world[i].allFinite()) return std::nullopt;
    src.col(static_cast<Eigen::Index>(i)) = model[i];
    dst.col(static_cast<Eigen::Index>(i)) = world[i];
  }
  // Points on one line leave the rotation about it undetermined.
  const Eigen::Matrix3Xd centred = src.colwise() - src.rowwise().mean();
  const Eigen::JacobiSVD<Eigen::Matrix3Xd> spread(centred);
  if (spread.singularValues()(1) < 1e-9 * std::max(1.0, spread.singularValues()(0))) {
    return std::nullopt;
  }
  const Eigen::Matrix4d T = Eigen::umeyama(src, dst, /*with_scaling=*/false);
  common::Rigid3 pose;
  pose.rotation = common::Quat(Eigen::Matrix3d(T.topLeftCorner<3, 3>())).normalized();
  pose.translation = T.topRightCorner<3, 1>();
  return pose;
}

std::optional<common::Rigid3> vectorCrossPose(const Markers& model, const Markers& world) {
  const auto D_m = vectorCrossBasis(model);
  const auto D_w = vectorCrossBasis(world);
  if (!D_m || !D_w) return std::nullopt;
  const auto R = nearestRotation(*D_w * D_m->inverse());
  const auto X_m = crossingPoint(model[0], model[2], model[1], model[3]);
  const auto X_w = crossingPoint(world[0], world[2], world[1], world[3]);
  if (!R || !X_m || !X_w) return std::nullopt;
  common::Rigid3 pose;
  pose.rotation = common::Quat(*R).normalized();
  pose.translation = *X_w - *R * *X_m;
  return pose;
}

std::optional<common::Rigid3> bodyFrameFromMarkers(const Markers& world) {
  const Vec3 centroid = (world[0] + world[1] + world[2] + world[3]) / 4.0;
  const Vec3 x = (world[2] - world[0]).normalized();
  const Vec3 normal = (world[1] - world[0]).cross(world[2] - world[0]);
  if (!x.allFinite() || normal.norm() < 1e-9 * (world[2] - world[0]).squaredNorm()) {
    return std::nullopt;
  }
  const Vec3 z = (normal - normal.dot(x) * x).normalized();
  const Vec3 y = z.cross(x);
  Eigen::Matrix3d R;
  R << x, y, z;
  return common::Rigid3{common::Quat(R).normalized(), centroid};
}

}  // namespace stereomap::posegraph
