#include "server/align/icp.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
#include <Eigen/LU>

#include <cmath>

namespace stereomap::align {

namespace {

using Vector6d = Eigen::Matrix<double, 6, 1>;
using Matrix6d = Eigen::Matrix<double, 6, 6>;

// Each moved source point's nearest target point within reach; the share and RMSE.
struct Correspondences {
  std::vector<std::pair<size_t, int>> pairs;
  double fitness = 0, rmse = 0;
};

Correspondences correspond(const std::vector<Eigen::Vector3d>& moved,
                           const open3d::geometry::KDTreeFlann& tree, double reach) {
  // Searched in parallel, gathered in order: the same sums with any number of threads.
  const auto n = static_cast<ptrdiff_t>(moved.size());
  std::vector<int> nearest(moved.size(), -1);
  std::vector<double> nearest2(moved.size(), 0);
#pragma omp parallel
  {
    std::vector<int> index;
    std::vector<double> distance2;
#pragma omp for schedule(static)
    for (ptrdiff_t i = 0; i < n; ++i) {
      if (tree.SearchHybrid(moved[i], reach, 1, index, distance2) > 0) {
        nearest[i] = index[0];
        nearest2[i] = distance2[0];
      }
    }
  }
  Correspondences out;
  double error2 = 0;
  for (size_t i = 0; i < moved.size(); ++i) {
    if (nearest[i] < 0) continue;
    out.pairs.emplace_back(i, nearest[i]);
    error2 += nearest2[i];
  }
  if (!out.pairs.empty()) {
    out.fitness = static_cast<double>(out.pairs.size()) / moved.size();
    out.rmse = std::sqrt(error2 / out.pairs.size());
  }
  return out;
}

// One Gauss-Newton step of sum ((p + w x p + t - q) . n)^2 over the correspondences, as a
// transform (rotation about z, then y, then x, as Open3D composes it); identity when the
// system is singular.
Eigen::Matrix4d pointToPlaneStep(const std::vector<Eigen::Vector3d>& moved,
                                 const open3d::geometry::PointCloud& target,
                                 const Correspondences& matched) {
  Matrix6d JTJ = Matrix6d::Zero();
  Vector6d JTr = Vector6d::Zero();
  for (const auto& [i, j] : matched.pairs) {
    const Eigen::Vector3d& p = moved[i];
    const Eigen::Vector3d& q = target.points_[j];
    const Eigen::Vector3d& n = target.normals_[j];
    Vector6d J;
    J << p.cross(n), n;
    const double r = (p - q).dot(n);
    JTJ.noalias() += J * J.transpose();
    JTr.noalias() += J * r;
  }
  const double det = JTJ.determinant();
  if (!std::isfinite(det) || std::fabs(det) < 1e-6) return Eigen::Matrix4d::Identity();
  const Vector6d x = JTJ.ldlt().solve(-JTr);
  Eigen::Matrix4d step = Eigen::Matrix4d::Identity();
  step.block<3, 3>(0, 0) = (Eigen::AngleAxisd(x(2), Eigen::Vector3d::UnitZ()) *
                            Eigen::AngleAxisd(x(1), Eigen::Vector3d::UnitY()) *
                            Eigen::AngleAxisd(x(0), Eigen::Vector3d::UnitX()))
                               .matrix();
  step.block<3, 1>(0, 3) = x.tail<3>();
  return step;
}

void transform(std::vector<Eigen::Vector3d>& points, const Eigen::Matrix4d& T) {
  const Eigen::Matrix3d R = T.block<3, 3>(0, 0);
  const Eigen::Vector3d t = T.block<3, 1>(0, 3);
  for (auto& p : points) p = R * p + t;
}

}  // namespace

IcpFit icpPointToPlane(const std::vector<Eigen::Vector3d>& source,
                       const open3d::geometry::PointCloud& target,
                       const open3d::geometry::KDTreeFlann& tree, double reach,
                       const Eigen::Matrix4d& initial, int max_iterations, double tolerance) {
  IcpFit fit;
  fit.T_target_source = initial;
  std::vector<Eigen::Vector3d> moved = source;
  transform(moved, initial);
  Correspondences matched = correspond(moved, tree, reach);
  for (int iteration = 0; iteration < max_iterations && !matched.pairs.empty(); ++iteration) {
    const Eigen::Matrix4d step = pointToPlaneStep(moved, target, matched);
    fit.T_target_source = step * fit.T_target_source;
    transform(moved, step);
    const Correspondences before = std::move(matched);
    matched = correspond(moved, tree, reach);
    if (std::fabs(before.fitness - matched.fitness) < tolerance &&
        std::fabs(before.rmse - matched.rmse) < tolerance) {
      break;
    }
  }
  fit.matched = matched.pairs.size();
  fit.rmse = matched.rmse;
  return fit;
}

}  // namespace stereomap::align
