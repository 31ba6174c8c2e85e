#include "onboard/posegraph/chordal.hpp"

#include <Eigen/SVD>

#include "onboard/posegraph/detail/block_cholesky.hpp"

namespace stereomap::posegraph {

namespace {

using detail::BlockLayout;
using detail::Cholesky;

// The rotation nearest (Frobenius) to a 3x3 matrix.
Eigen::Matrix3d nearestRotation(const Eigen::Matrix3d& M) {
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(M, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d D = Eigen::Matrix3d::Identity();
  D(2, 2) = (svd.matrixU() * svd.matrixV().transpose()).determinant() < 0 ? -1 : 1;
  return svd.matrixU() * D * svd.matrixV().transpose();
}

// Adds the 3 x 3 block `value` at block (a, b) of the layout's upper triangle (a, b >= 0).
void addBlock(const BlockLayout& layout, double* values, int a, int b, int slot,
              const Eigen::Matrix3d& value) {
  const int k = 3;
  if (a > b) {
    addBlock(layout, values, b, a, slot, value.transpose());
    return;
  }
  for (int c = 0; c < k; ++c) {
    for (int r = 0; r < (a == b ? c + 1 : k); ++r)
      values[layout.position(b, slot, r, c)] += value(r, c);
  }
}

}  // namespace

common::Status chordalInitialise(GraphProblem& problem) {
  auto& poses = problem.poses();
  const FillOrdering ordering = FillOrdering::kAuto;
  // Rotations, row by row: row rho of R_j - R_i R~ is y_j^T - y_i^T R~ with y_v = R_v's row rho
  // as a column, so each row is the same 3x3-block system with its own right-hand side.
  {
    const BlockLayout layout(problem, 3);
    if (layout.size() > 0) {
      Cholesky cholesky(layout, ordering);
      double* values = cholesky.values();
      std::vector<double> b(static_cast<size_t>(layout.size()) * 3, 0.0);
      auto rhs = [&](int block, const Eigen::Matrix3d& columns) {
        for (int rho = 0; rho < 3; ++rho) {
          for (int r = 0; r < 3; ++r) b[rho * layout.size() + block * 3 + r] += columns(r, rho);
        }
      };
      const Eigen::Matrix3d I = Eigen::Matrix3d::Identity();
      for (size_t e = 0; e < problem.edges().size(); ++e) {
        const ProblemEdge& edge = problem.edges()[e];
        const auto& slots = layout.edges[e];
        const Eigen::Matrix3d& M = edge.R_meas;
        const double kappa = edge.kappa;
        // kappa |y_j - M^T y_i|^2: blocks (j,j) and (i,i) kappa I, (i,j) -kappa M.
        if (slots.a >= 0)
          addBlock(layout, values, slots.a, slots.a, layout.diagonal_slot[slots.a], kappa * I);
        if (slots.b >= 0)
          addBlock(layout, values, slots.b, slots.b, layout.diagonal_slot[slots.b], kappa * I);
        if (slots.slot >= 0) addBlock(layout, values, slots.a, slots.b, slots.slot, -kappa * M);
        // A fixed end moves to the right-hand side; its y's are the columns of R^T.
        if (slots.a < 0 && slots.b >= 0)
          rhs(slots.b, kappa * M.transpose() * poses[edge.i].R.transpose());
        if (slots.b < 0 && slots.a >= 0) rhs(slots.a, kappa * M * poses[edge.j].R.transpose());
      }
      std::vector<double> y;
      if (!cholesky.solve(b, 3, &y)) {
        return common::makeError(common::ErrorCode::kInvalidArgument,
                                 "chordal initialisation: the rotations are not determined");
      }
      for (int v = 0; v < problem.size(); ++v) {
        const int block = layout.block_of[v];
        if (block < 0) continue;
        Eigen::Matrix3d R;
        for (int rho = 0; rho < 3; ++rho) {
          for (int c = 0; c < 3; ++c) R(rho, c) = y[rho * layout.size() + block * 3 + c];
        }
        R = nearestRotation(R);
        if (problem.dimension() == 2) {
          R = Eigen::AngleAxisd(std::atan2(R(1, 0), R(0, 0)), Eigen::Vector3d::UnitZ())
                  .toRotationMatrix();
        }
        poses[v].R = R;
      }
    }
  }
  // Translations with those rotations: a weighted graph Laplacian, x, y and z at once.
  const BlockLayout layout(problem, 1);
  if (layout.size() == 0) return common::Ok{};
  Cholesky cholesky(layout, ordering);
  double* values = cholesky.values();
  const int n = layout.size();
  std::vector<double> b(static_cast<size_t>(n) * 3, 0.0);
  auto rhs = [&](int block, const Eigen::Vector3d& v) {
    for (int axis = 0; axis < 3; ++axis) b[axis * n + block] += v[axis];
  };
  for (size_t e = 0; e < problem.edges().size(); ++e) {
    const ProblemEdge& edge = problem.edges()[e];
    const auto& slots = layout.edges[e];
    const double tau = edge.tau;
    const Eigen::Vector3d step = poses[edge.i].R * edge.t_meas;  // t_j - t_i should be this
    if (slots.a >= 0) {
      values[layout.diagonal(slots.a, 0)] += tau;
      rhs(slots.a, -tau * step);
      if (slots.b < 0) rhs(slots.a, tau * poses[edge.j].t);
    }
    if (slots.b >= 0) {
      values[layout.diagonal(slots.b, 0)] += tau;
      rhs(slots.b, tau * step);
      if (slots.a < 0) rhs(slots.b, tau * poses[edge.i].t);
    }
    if (slots.slot >= 0)
      values[layout.position(std::max(slots.a, slots.b), slots.slot, 0, 0)] -= tau;
  }
  std::vector<double> t;
  if (!cholesky.solve(b, 3, &t)) {
    return common::makeError(common::ErrorCode::kInvalidArgument,
                             "chordal initialisation: the translations are not determined");
  }
  for (int v = 0; v < problem.size(); ++v) {
    const int block = layout.block_of[v];
    if (block >= 0) poses[v].t = Eigen::Vector3d(t[block], t[n + block], t[2 * n + block]);
  }
  return common::Ok{};
}

}  // namespace stereomap::posegraph
