#include "onboard/odometry/detail/refine.hpp"

#include <ceres/ceres.h>

#include "onboard/odometry/detail/reprojection.hpp"

namespace stereomap::odometry::detail {

namespace {

// A fixed point (the reference frame's) seen from the pose being refined.
struct Reprojection {
  Reprojection(const camera::StereoCamera& c, const common::Vec3& p, double u, double v, double bx)
      : residual(c, u, v, bx), point(p) {}
  template <typename T>
  bool operator()(const T* angle_axis, const T* t, T* out) const {
    const T p[3] = {T(point.x()), T(point.y()), T(point.z())};
    residual(angle_axis, t, p, out);
    return true;
  }
  PinholeResidual residual;
  common::Vec3 point;
};

struct Prior {
  Prior(const Eigen::Vector3d& aa, const Eigen::Vector3d& t, double sr, double st)
      : aa(aa), t(t), sr(sr), st(st) {}
  template <typename T>
  bool operator()(const T* angle_axis, const T* translation, T* residual) const {
    for (int i = 0; i < 3; ++i) {
      residual[i] = (angle_axis[i] - T(aa[i])) / T(sr);
      residual[3 + i] = (translation[i] - T(t[i])) / T(st);
    }
    return true;
  }
  Eigen::Vector3d aa, t;
  double sr, st;
};

}  // namespace

std::optional<Eigen::Vector2d> project(const camera::StereoCamera& camera, const common::Vec3& p,
                                       bool right) {
  if (p.z() <= 1e-6) return std::nullopt;
  const double x = p.x() - (right ? camera.baseline : 0.0);
  return Eigen::Vector2d(camera.fx * x / p.z() + camera.cx, camera.fy * p.y() / p.z() + camera.cy);
}

RefineResult refinePose(const camera::StereoCamera& camera,
                        const std::vector<Observation>& observations, const common::Rigid3& initial,
                        const common::Rigid3& prior, const RefineOptions& options) {
  Eigen::Vector3d angle_axis = angleAxisOf(initial.rotation);
  Eigen::Vector3d translation = initial.translation;
  ceres::Problem::Options problem_options;
  problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(problem_options);
  ceres::HuberLoss huber(options.huber_px);
  for (const auto& o : observations) {
    problem.AddResidualBlock(new ceres::AutoDiffCostFunction<Reprojection, 2, 3, 3>(
                                 new Reprojection(camera, o.point, o.left.x(), o.left.y(), 0.0)),
                             &huber, angle_axis.data(), translation.data());
    if (o.right) {
      problem.AddResidualBlock(
          new ceres::AutoDiffCostFunction<Reprojection, 2, 3, 3>(
              new Reprojection(camera, o.point, o.right->x(), o.right->y(), camera.baseline)),
          &huber, angle_axis.data(), translation.data());
    }
  }
  if (options.prior_rotation_rad > 0 && options.prior_translation_m > 0) {
    problem.AddResidualBlock(new ceres::AutoDiffCostFunction<Prior, 6, 3, 3>(new Prior(
                                 angleAxisOf(prior.rotation), prior.translation,
                                 options.prior_rotation_rad, options.prior_translation_m)),
                             nullptr, angle_axis.data(), translation.data());
  }
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::DENSE_QR;
  solver.max_num_iterations = options.max_iterations;
  solver.num_threads = 1;
  solver.logging_type = ceres::SILENT;
  ceres::Solver::Summary summary;
  ceres::Solve(solver, &problem, &summary);

  RefineResult result;
  result.T_current_reference.rotation = quatOf(angle_axis);
  result.T_current_reference.translation = translation;
  const size_t residuals = static_cast<size_t>(summary.num_residuals);
  result.rms_px =
      residuals > 0 ? std::sqrt(2.0 * summary.final_cost / static_cast<double>(residuals)) : 0;
  if (options.covariance) {
    ceres::Covariance::Options covariance_options;
    covariance_options.algorithm_type = ceres::DENSE_SVD;
    covariance_options.null_space_rank = -1;
    ceres::Covariance covariance(covariance_options);
    const std::vector<std::pair<const double*, const double*>> blocks = {
        {angle_axis.data(), angle_axis.data()},
        {angle_axis.data(), translation.data()},
        {translation.data(), translation.data()}};
    if (covariance.Compute(blocks, &problem)) {
      double rr[9], rt[9], tt[9];
      covariance.GetCovarianceBlock(angle_axis.data(), angle_axis.data(), rr);
      covariance.GetCovarianceBlock(angle_axis.data(), translation.data(), rt);
      covariance.GetCovarianceBlock(translation.data(), translation.data(), tt);
      // Pixel noise: the fit's own residual level (at least 0.3 px).
      const double sigma2 = std::max(result.rms_px * result.rms_px, 0.09);
      for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
          result.covariance(i, j) = rr[3 * i + j] * sigma2;
          result.covariance(i, 3 + j) = rt[3 * i + j] * sigma2;
          result.covariance(3 + j, i) = rt[3 * i + j] * sigma2;
          result.covariance(3 + i, 3 + j) = tt[3 * i + j] * sigma2;
        }
      }
    }
  }
  return result;
}

}  // namespace stereomap::odometry::detail
