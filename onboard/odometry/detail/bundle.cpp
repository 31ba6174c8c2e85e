#include "onboard/odometry/detail/bundle.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Geometry>

#include <cmath>
#include <limits>

#include "onboard/odometry/detail/rotation.hpp"

namespace stereomap::odometry::detail {

namespace {

using Mat23 = Eigen::Matrix<double, 2, 3>;
using Mat26 = Eigen::Matrix<double, 2, 6>;
using Mat63 = Eigen::Matrix<double, 6, 3>;

Eigen::Matrix3d skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

// A step that puts a point behind a camera that saw it costs as much as this error (px), so
// that hiding an observation never pays.
constexpr double kBehindPenaltyPx = 1000.0;

// One observation's residual and Jacobians (pose as a left perturbation [rotation,
// translation] of camera-from-world; point; offset).
struct Linearised {
  Eigen::Vector2d r = Eigen::Vector2d::Zero();
  Mat26 J_pose = Mat26::Zero();
  Mat23 J_point = Mat23::Zero();
  bool valid = false;
};

Linearised linearise(const camera::StereoCamera& cam, const BundleProblem& p,
                     const BundleObservation& o, bool jacobians) {
  Linearised l;
  const common::Rigid3& T = p.T_camera_world[static_cast<size_t>(o.frame)];
  const Eigen::Vector3d c = T * p.points[static_cast<size_t>(o.point)];  // left camera frame
  const Eigen::Vector3d q = o.right ? Eigen::Vector3d(c.x() - cam.baseline, c.y(), c.z()) : c;
  if (q.z() < 1e-3) return l;
  const double iz = 1.0 / q.z();
  l.valid = true;
  l.r = Eigen::Vector2d(cam.fx * q.x() * iz + cam.cx + (o.right ? p.right_offset : 0.0) - o.u,
                        cam.fy * q.y() * iz + cam.cy - o.v);
  if (!jacobians) return l;
  Mat23 J_q;
  J_q << cam.fx * iz, 0, -cam.fx * q.x() * iz * iz, 0, cam.fy * iz, -cam.fy * q.y() * iz * iz;
  l.J_pose.leftCols<3>() = -J_q * skew(c);
  l.J_pose.rightCols<3>() = J_q;
  l.J_point = J_q * T.rotation.toRotationMatrix();
  return l;
}

// Huber weight of a residual of norm n, and its robust cost (half squared inside).
double huberWeight(double n, double k) { return n <= k ? 1.0 : k / n; }
double huberCost(double n, double k) { return n <= k ? 0.5 * n * n : k * (n - 0.5 * k); }

double cost(const camera::StereoCamera& cam, const BundleProblem& p, double offset0, double k) {
  double total = 0;
  for (const auto& o : p.observations) {
    const Linearised l = linearise(cam, p, o, false);
    total += huberCost(l.valid ? l.r.norm() : kBehindPenaltyPx, k);
  }
  if (p.right_offset_sigma > 0) {
    const double d = (p.right_offset - offset0) / p.right_offset_sigma;
    total += 0.5 * d * d;
  }
  return total;
}

// Per point: its normal-equation block, gradient, coupling to each observing pose (6x3) and
// to the offset (1x3).
struct PointBlock {
  Eigen::Matrix3d H = Eigen::Matrix3d::Zero();
  Eigen::Vector3d b = Eigen::Vector3d::Zero();
  std::vector<std::pair<int, Mat63>> poses;
  Eigen::RowVector3d offset = Eigen::RowVector3d::Zero();
  Eigen::Matrix3d H_inv = Eigen::Matrix3d::Zero();
};

// The camera system with the points eliminated (Schur complement), damped by lambda; `off` is
// the offset's index (< 0: none). Leaves each block's damped inverse in H_inv.
void eliminatePoints(const Eigen::MatrixXd& Hcc, const Eigen::VectorXd& bc,
                     std::vector<PointBlock>& blocks, double lambda, int off, Eigen::MatrixXd& S,
                     Eigen::VectorXd& rhs) {
  S = Hcc;
  S.diagonal() += lambda * Hcc.diagonal().cwiseMax(1e-9);
  rhs = bc;
  std::vector<Mat63> WH;
  for (auto& block : blocks) {
    Eigen::Matrix3d H = block.H;
    H.diagonal() += lambda * H.diagonal().cwiseMax(1e-9) + Eigen::Vector3d::Constant(1e-9);
    block.H_inv = H.inverse();
    // S -= H_cp H_pp^-1 H_pc, block by block over the observing poses and the offset.
    WH.resize(block.poses.size());
    for (size_t x = 0; x < block.poses.size(); ++x) {
      WH[x] = block.poses[x].second * block.H_inv;
      const int a = 6 * (block.poses[x].first - 1);
      rhs.segment<6>(a) -= WH[x] * block.b;
      for (size_t y = 0; y < block.poses.size(); ++y) {
        S.block<6, 6>(a, 6 * (block.poses[y].first - 1)) -=
            WH[x] * block.poses[y].second.transpose();
      }
      if (off >= 0) {
        const Eigen::Matrix<double, 6, 1> c = WH[x] * block.offset.transpose();
        S.block<6, 1>(a, off) -= c;
        S.block<1, 6>(off, a) -= c.transpose();
      }
    }
    if (off >= 0) {
      const Eigen::RowVector3d VH = block.offset * block.H_inv;
      S(off, off) -= VH.dot(block.offset);
      rhs(off) -= VH.dot(block.b);
    }
  }
}

}  // namespace

BundleSummary adjustBundle(const camera::StereoCamera& cam, BundleProblem& p,
                           const BundleOptions& options) {
  const int frames = static_cast<int>(p.T_camera_world.size());
  const size_t points = p.points.size();
  const bool with_offset = p.right_offset_sigma > 0;
  // Reduced (camera) system: poses 1..frames-1, then the offset.
  const int m = 6 * (frames - 1) + (with_offset ? 1 : 0);
  const int off = with_offset ? m - 1 : -1;
  const double offset0 = p.right_offset;
  const double k = options.huber_px;
  double offset_information = with_offset ? 1.0 / (p.right_offset_sigma * p.right_offset_sigma) : 0;

  BundleSummary summary;
  summary.initial_cost = summary.final_cost = cost(cam, p, offset0, k);
  double lambda = 1e-4;
  std::vector<PointBlock> blocks(points);
  Eigen::MatrixXd S;
  Eigen::VectorXd rhs;
  for (int iteration = 0; iteration < options.iterations && m > 0; ++iteration) {
    Eigen::MatrixXd Hcc = Eigen::MatrixXd::Zero(m, m);
    Eigen::VectorXd bc = Eigen::VectorXd::Zero(m);
    for (auto& block : blocks) block = PointBlock{};
    for (const auto& o : p.observations) {
      const Linearised l = linearise(cam, p, o, true);
      if (!l.valid) continue;
      const double w = huberWeight(l.r.norm(), k);
      PointBlock& block = blocks[static_cast<size_t>(o.point)];
      block.H += w * l.J_point.transpose() * l.J_point;
      block.b -= w * l.J_point.transpose() * l.r;
      if (o.frame > 0) {
        const int a = 6 * (o.frame - 1);
        Hcc.block<6, 6>(a, a) += w * l.J_pose.transpose() * l.J_pose;
        bc.segment<6>(a) -= w * l.J_pose.transpose() * l.r;
        const Mat63 W = w * l.J_pose.transpose() * l.J_point;
        if (!block.poses.empty() && block.poses.back().first == o.frame) {
          block.poses.back().second += W;
        } else {
          block.poses.emplace_back(o.frame, W);
        }
        if (with_offset && o.right) Hcc.block<6, 1>(a, off) += w * l.J_pose.row(0).transpose();
      }
      if (with_offset && o.right) {
        Hcc(off, off) += w;
        bc(off) -= w * l.r.x();
        block.offset += w * l.J_point.row(0);
      }
    }
    if (with_offset) {
      Hcc.row(off).head(off) = Hcc.col(off).head(off).transpose();
      if (iteration == 0) {
        // How well the window alone determines the offset: its marginal deviation, with the
        // poses and points free. Too weak (little motion, one depth): hold it.
        eliminatePoints(Hcc, bc, blocks, 0.0, off, S, rhs);
        const Eigen::VectorXd e = Eigen::VectorXd::Unit(m, off);
        const double variance = S.ldlt().solve(e)(off);
        summary.offset_sigma_px = variance > 0 && std::isfinite(variance)
                                      ? std::sqrt(variance)
                                      : std::numeric_limits<double>::infinity();
        if (!(summary.offset_sigma_px <= options.offset_gate_px)) offset_information = 1e12;
      }
      Hcc(off, off) += offset_information;
      bc(off) -= (p.right_offset - offset0) * offset_information;
    }

    // Levenberg-Marquardt: damp, eliminate the points, solve, keep the step if it helps.
    bool improved = false;
    for (int attempt = 0; attempt < 5 && !improved; ++attempt) {
      eliminatePoints(Hcc, bc, blocks, lambda, off, S, rhs);
      const Eigen::VectorXd dc = S.ldlt().solve(rhs);
      if (!dc.allFinite()) {
        lambda *= 10;
        continue;
      }
      // Back-substitute the points and try the step.
      std::vector<common::Rigid3> poses = p.T_camera_world;
      std::vector<common::Vec3> moved = p.points;
      for (int f = 1; f < frames; ++f) {
        const Eigen::Matrix<double, 6, 1> xi = dc.segment<6>(6 * (f - 1));
        auto& T = poses[static_cast<size_t>(f)];
        const common::Quat dq = quatOf(xi.head<3>());
        T.rotation = (dq * T.rotation).normalized();
        T.translation = dq * T.translation + xi.tail<3>();
      }
      for (size_t j = 0; j < points; ++j) {
        const PointBlock& block = blocks[j];
        Eigen::Vector3d b = block.b;
        for (const auto& [frame, W] : block.poses)
          b -= W.transpose() * dc.segment<6>(6 * (frame - 1));
        if (with_offset) b -= block.offset.transpose() * dc(off);
        moved[j] += block.H_inv * b;
      }
      std::swap(poses, p.T_camera_world);
      std::swap(moved, p.points);
      const double before_offset = p.right_offset;
      if (with_offset) p.right_offset += dc(off);
      const double c = cost(cam, p, offset0, k);
      if (c < summary.final_cost) {
        summary.final_cost = c;
        lambda = std::max(lambda / 10, 1e-8);
        improved = true;
      } else {  // undo
        std::swap(poses, p.T_camera_world);
        std::swap(moved, p.points);
        p.right_offset = before_offset;
        lambda *= 10;
      }
    }
    if (!improved) break;
    ++summary.iterations;
  }
  return summary;
}

}  // namespace stereomap::odometry::detail
