#include "onboard/landing/pad_pose.hpp"

#include <ceres/ceres.h>

#include <cmath>
#include <memory>
#include <opencv2/calib3d.hpp>

#include "onboard/camera/cv_pose.hpp"
#include "onboard/landing/deck_filter.hpp"
#include "onboard/landing/pad_detector.hpp"

namespace stereomap::landing {

using common::Quat;
using common::Rigid3;
using common::Vec3;

namespace {

// One of the two cameras' view of pad points under (q, t): the point in the left camera is
// R q * P + t, shifted by the baseline for the right one.
struct PadProjector {
  PadProjector(double shift, const camera::StereoCamera& camera)
      : shift(shift), fx(camera.fx), fy(camera.fy), cx(camera.cx), cy(camera.cy) {}

  template <typename T>
  bool operator()(const T* q, const T* t, const Vec3& P, Eigen::Matrix<T, 2, 1>& uv) const {
    const Eigen::Map<const Eigen::Quaternion<T>> Q(q);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> translation(t);
    Eigen::Matrix<T, 3, 1> p = Q * P.cast<T>() + translation;
    p.x() -= T(shift);
    if (p.z() <= T(1e-6)) return false;
    uv << T(fx) * p.x() / p.z() + T(cx), T(fy) * p.y() / p.z() + T(cy);
    return true;
  }

  double shift, fx, fy, cx, cy;
};

// One corner seen by one camera: its reprojection error (pixels).
struct CornerError {
  template <typename T>
  bool operator()(const T* q, const T* t, T* residual) const {
    Eigen::Matrix<T, 2, 1> uv;
    if (!projector(q, t, P, uv)) return false;
    residual[0] = uv.x() - T(seen.x);
    residual[1] = uv.y() - T(seen.y);
    return true;
  }

  cv::Point2d seen;
  Vec3 P;
  PadProjector projector;
};

// One sub-pixel point on edge k seen by one camera: its distance (pixels) from the line
// through the projections of the edge's two pad corners.
struct EdgeError {
  template <typename T>
  bool operator()(const T* q, const T* t, T* residual) const {
    Eigen::Matrix<T, 2, 1> a, b;
    if (!projector(q, t, A, a) || !projector(q, t, B, b)) return false;
    const Eigen::Matrix<T, 2, 1> d = b - a;
    const T length = d.norm();
    if (length < T(1e-9)) return false;
    residual[0] = (d.x() * (T(seen.y) - a.y()) - d.y() * (T(seen.x) - a.x())) / length;
    return true;
  }

  cv::Point2f seen;
  Vec3 A, B;
  PadProjector projector;
};

double rmsOf(const Rigid3& T_camera_pad, const std::array<cv::Point2d, 8>& image,
             const camera::StereoCamera& camera, double shift) {
  double squared = 0;
  for (int k = 0; k < 8; ++k) {
    Vec3 p = T_camera_pad * padModel()[k];
    p.x() -= shift;
    const auto uv = camera.project(p);
    if (!uv) return 1e9;
    squared += (Eigen::Vector2d(image[k].x, image[k].y) - *uv).squaredNorm();
  }
  return std::sqrt(squared / 8);
}

// A start refined on the edge points (or the corners), its problem kept for the covariance.
// The loss is shared by every residual (one allocation, not one per edge point).
struct Refined {
  Refined(const Rigid3& start, double huber_px)
      : q(start.rotation), t(start.translation), loss(huber_px) {
    ceres::Problem::Options problem_options;
    problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
    problem = std::make_unique<ceres::Problem>(problem_options);
  }
  Refined(const Refined&) = delete;
  Refined& operator=(const Refined&) = delete;

  Rigid3 pose() const { return {q.normalized(), t}; }

  Eigen::Quaterniond q;
  Vec3 t;
  ceres::HuberLoss loss;
  std::unique_ptr<ceres::Problem> problem;  // its parameter blocks are q and t above
  double cost = 0;
  int residuals = 0;
};

std::unique_ptr<Refined> refine(const Rigid3& start, const PadView& left,
                                const std::optional<PadView>& right,
                                const camera::StereoCamera& camera, const PadPoseOptions& options) {
  auto out = std::make_unique<Refined>(start, options.huber_px);
  ceres::Problem& problem = *out->problem;
  double* q = out->q.coeffs().data();
  double* t = out->t.data();
  auto add = [&](const PadView& view, double shift) {
    bool edges = true;
    for (const auto& side : view.edges) edges = edges && side.size() >= 2;
    if (!edges) {
      for (int k = 0; k < 8; ++k) {
        problem.AddResidualBlock(
            new ceres::AutoDiffCostFunction<CornerError, 2, 4, 3>(
                new CornerError{view.corners[k], padModel()[k], {shift, camera}}),
            &out->loss, q, t);
        out->residuals += 2;
      }
      return;
    }
    for (int k = 0; k < 8; ++k) {
      for (const cv::Point2f& point : view.edges[k]) {
        problem.AddResidualBlock(
            new ceres::AutoDiffCostFunction<EdgeError, 1, 4, 3>(
                new EdgeError{point, padModel()[k], padModel()[(k + 1) % 8], {shift, camera}}),
            &out->loss, q, t);
        ++out->residuals;
      }
    }
  };
  add(left, 0.0);
  if (right) add(*right, camera.baseline);
  problem.SetManifold(q, new ceres::EigenQuaternionManifold);
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::DENSE_QR;
  solver.max_num_iterations = 50;
  ceres::Solver::Summary summary;
  ceres::Solve(solver, &problem, &summary);
  out->cost = summary.final_cost;
  return out;
}

// The pose's covariance (rotation, translation in the tangent space), for the chosen start
// only: it costs as much as the solve.
Eigen::Matrix<double, 6, 6> covarianceOf(Refined& refined) {
  double* q = refined.q.coeffs().data();
  double* t = refined.t.data();
  ceres::Covariance::Options covariance_options;
  ceres::Covariance covariance(covariance_options);
  const std::vector<std::pair<const double*, const double*>> blocks = {{q, q}, {q, t}, {t, t}};
  if (!covariance.Compute(blocks, refined.problem.get()))
    return Eigen::Matrix<double, 6, 6>::Zero();
  Eigen::Matrix<double, 6, 6, Eigen::RowMajor> c;
  const std::vector<const double*> order = {q, t};
  if (!covariance.GetCovarianceMatrixInTangentSpace(order, c.data())) {
    return Eigen::Matrix<double, 6, 6>::Zero();
  }
  // Unit pixel noise in the solve; scaled by the residuals' own variance (no less than a tenth
  // of a pixel: a perfect fit is not a perfect measurement).
  const double variance = std::max(2.0 * refined.cost / std::max(refined.residuals - 6, 1), 0.01);
  return c * variance;
}

}  // namespace

std::optional<Rigid3> patentLinearPose(const std::array<cv::Point2d, 8>& image,
                                       const camera::StereoCamera& camera) {
  // Centred image coordinates in units of the focal length (so f = 1 below).
  std::array<double, 8> xd{}, yd{};
  for (int k = 0; k < 8; ++k) {
    xd[k] = (image[k].x - camera.cx) / camera.fx;
    yd[k] = (image[k].y - camera.cy) / camera.fy;
  }
  // x_d (p4 x_w + p5 y_w + ty) = y_d (p1 x_w + p2 y_w + tx), z_w = 0: unknowns
  // (p1, p2, tx, p4, p5) / ty.
  Eigen::Matrix<double, 8, 5> A;
  Eigen::Matrix<double, 8, 1> b;
  for (int k = 0; k < 8; ++k) {
    const double x = padModel()[k].x(), y = padModel()[k].y();
    A.row(k) << yd[k] * x, yd[k] * y, yd[k], -xd[k] * x, -xd[k] * y;
    b(k) = xd[k];
  }
  const Eigen::Matrix<double, 5, 1> a = A.colPivHouseholderQr().solve(b);
  const double a1 = a(0), a2 = a(1), a3 = a(2), a4 = a(3), a5 = a(4);
  // |ty| from the unit norm of the rotation's rows (Tsai's coplanar formula).
  const double S = a1 * a1 + a2 * a2 + a4 * a4 + a5 * a5;
  const double det = a1 * a5 - a4 * a2;
  double ty2;
  if (std::abs(det) > 1e-12) {
    ty2 = (S - std::sqrt(std::max(S * S - 4 * det * det, 0.0))) / (2 * det * det);
  } else {
    const double row = std::max(a1 * a1 + a2 * a2, a4 * a4 + a5 * a5);
    if (row < 1e-12) return std::nullopt;
    ty2 = 1.0 / row;
  }
  double ty = std::sqrt(ty2);
  // The sign of ty: the corner farthest from the image centre must come out on its side.
  int far = 0;
  for (int k = 1; k < 8; ++k) {
    if (xd[k] * xd[k] + yd[k] * yd[k] > xd[far] * xd[far] + yd[far] * yd[far]) far = k;
  }
  {
    const double x = (a1 * padModel()[far].x() + a2 * padModel()[far].y() + a3) * ty;
    const double y = (a4 * padModel()[far].x() + a5 * padModel()[far].y()) * ty + ty;
    if (x * xd[far] < 0 || y * yd[far] < 0) ty = -ty;
  }
  const double r1 = a1 * ty, r2 = a2 * ty, tx = a3 * ty, r4 = a4 * ty, r5 = a5 * ty;
  double r3 = std::sqrt(std::max(1 - r1 * r1 - r2 * r2, 0.0));
  double r6 = std::sqrt(std::max(1 - r4 * r4 - r5 * r5, 0.0));
  if (r1 * r4 + r2 * r5 > 0) r6 = -r6;
  Eigen::Matrix3d R;
  R.row(0) << r1, r2, r3;
  R.row(1) << r4, r5, r6;
  R.row(2) = R.row(0).cross(R.row(1));
  // f and tz from y_d (r7 x + r8 y + tz) = f (r4 x + r5 y + ty); a negative f means the
  // third column's sign was wrong (Tsai).
  auto solveFTz = [&](const Eigen::Matrix3d& rotation) {
    Eigen::Matrix<double, 8, 2> M;
    Eigen::Matrix<double, 8, 1> rhs;
    for (int k = 0; k < 8; ++k) {
      const double x = padModel()[k].x(), y = padModel()[k].y();
      M.row(k) << rotation(1, 0) * x + rotation(1, 1) * y + ty, -yd[k];
      rhs(k) = yd[k] * (rotation(2, 0) * x + rotation(2, 1) * y);
    }
    return Eigen::Vector2d(M.colPivHouseholderQr().solve(rhs));
  };
  if (solveFTz(R)(0) < 0) {
    R(0, 2) = -R(0, 2);
    R(1, 2) = -R(1, 2);
    R(2, 0) = -R(2, 0);
    R(2, 1) = -R(2, 1);
  }
  // tz with the known intrinsics (f = 1 here), from both image coordinates.
  double num = 0, den = 0;
  for (int k = 0; k < 8; ++k) {
    const double x = padModel()[k].x(), y = padModel()[k].y();
    const double X = R(0, 0) * x + R(0, 1) * y + tx, Y = R(1, 0) * x + R(1, 1) * y + ty;
    const double Zp = R(2, 0) * x + R(2, 1) * y;
    num += xd[k] * (X - xd[k] * Zp) + yd[k] * (Y - yd[k] * Zp);
    den += xd[k] * xd[k] + yd[k] * yd[k];
  }
  if (den < 1e-12) return std::nullopt;
  const double tz = num / den;
  // The linear step's rows are orthonormal only without noise: the nearest rotation.
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(R, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d rotation = svd.matrixU() * svd.matrixV().transpose();
  if (rotation.determinant() < 0) return std::nullopt;
  if (!std::isfinite(tz) || tz <= 0) return std::nullopt;
  return Rigid3{Quat(rotation), Vec3(tx, ty, tz)};
}

PadPose estimatePadPose(const std::array<cv::Point2d, 8>& left,
                        const std::optional<std::array<cv::Point2d, 8>>& right,
                        const camera::StereoCamera& camera, const PadPoseOptions& options) {
  return estimatePadPose(PadView{left, {}},
                         right ? std::optional(PadView{*right, {}}) : std::nullopt, camera,
                         options);
}

PadPose estimatePadPose(const PadView& left_view, const std::optional<PadView>& right_view,
                        const camera::StereoCamera& camera, const PadPoseOptions& options) {
  const std::array<cv::Point2d, 8>& left = left_view.corners;
  const std::optional<std::array<cv::Point2d, 8>> right =
      right_view ? std::optional(right_view->corners) : std::nullopt;
  PadPose result;
  if (options.mode == PoseMode::kPatent) {
    const auto linear = patentLinearPose(left, camera);
    if (!linear) {
      result.reason = "the linear solution is degenerate";
      return result;
    }
    result.T_camera_pad = *linear;
    result.rms_px = rmsOf(*linear, left, camera, 0.0);
  } else {
    std::vector<cv::Point3d> object;
    for (const Vec3& p : padModel()) object.emplace_back(p.x(), p.y(), p.z());
    const std::vector<cv::Point2d> image(left.begin(), left.end());
    const cv::Matx33d K(camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1);
    std::vector<cv::Mat> rvecs, tvecs;
    cv::solvePnPGeneric(object, image, K, cv::noArray(), rvecs, tvecs, false, cv::SOLVEPNP_IPPE);
    std::unique_ptr<Refined> best;
    for (size_t i = 0; i < rvecs.size(); ++i) {
      const Rigid3 start = camera::rigidFromRvecTvec(rvecs[i], tvecs[i]);
      if (start.translation.z() <= 0) continue;
      auto refined = refine(start, left_view, right_view, camera, options);
      if (!best || refined->cost < best->cost) best = std::move(refined);
    }
    if (!best) {
      result.reason = "no pose in front of the camera fits the corners";
      return result;
    }
    result.T_camera_pad = best->pose();
    result.covariance = covarianceOf(*best);
    result.stereo = right.has_value();
    const double rms_left = rmsOf(best->pose(), left, camera, 0.0);
    result.rms_px =
        right ? std::sqrt(0.5 * (rms_left * rms_left +
                                 std::pow(rmsOf(best->pose(), *right, camera, camera.baseline), 2)))
              : rms_left;
  }
  result.euler_deg = eulerZyx(result.T_camera_pad.rotation) * 180.0 / M_PI;
  if (!(result.rms_px <= options.max_rms_px)) {
    result.reason = "reprojection error " + std::to_string(result.rms_px).substr(0, 5) +
                    " px is above " + std::to_string(options.max_rms_px).substr(0, 4) + " px";
    return result;
  }
  result.ok = true;
  return result;
}

}  // namespace stereomap::landing
