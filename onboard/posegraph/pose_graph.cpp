#include "onboard/posegraph/pose_graph.hpp"

#include <ceres/ceres.h>

#include <Eigen/Cholesky>
#include <chrono>

namespace stereomap::posegraph {

RelativePoseError::RelativePoseError(const common::Rigid3& T_i_j, const Mat6& information)
    : measured_q_(T_i_j.rotation.normalized()), measured_t_(T_i_j.translation) {
  const Eigen::LLT<Mat6> llt(information);
  sqrt_information_ = llt.matrixL().transpose();
}

int PoseGraph::addVertex(const common::Rigid3& T_world_vertex) {
  poses_.push_back({T_world_vertex.rotation.normalized(), T_world_vertex.translation});
  fixed_.push_back(poses_.size() == 1);
  return size() - 1;
}

common::Status PoseGraph::addEdge(const Edge& edge) {
  if (edge.from < 0 || edge.from >= size() || edge.to < 0 || edge.to >= size()) {
    return common::makeError(common::ErrorCode::kInvalidArgument,
                             "pose graph: an edge names a vertex that is not there");
  }
  if (edge.from == edge.to) {
    return common::makeError(common::ErrorCode::kInvalidArgument,
                             "pose graph: an edge from a vertex to itself");
  }
  if (!edge.information.allFinite() || !edge.information.isApprox(edge.information.transpose()) ||
      Eigen::LLT<Mat6>(edge.information).info() != Eigen::Success) {
    return common::makeError(
        common::ErrorCode::kInvalidArgument,
        "pose graph: an information matrix must be finite, symmetric and positive definite");
  }
  if (!common::isUnitQuaternion(edge.T_from_to.rotation) ||
      !edge.T_from_to.translation.allFinite()) {
    return common::makeError(common::ErrorCode::kInvalidArgument,
                             "pose graph: an edge's pose is not a rigid transform");
  }
  edges_.push_back(edge);
  rejected_.push_back(false);
  return common::Ok{};
}

void PoseGraph::setFixed(int vertex, bool fixed) { fixed_.at(vertex) = fixed; }

void PoseGraph::setPose(int vertex, const common::Rigid3& T_world_vertex) {
  poses_.at(vertex) = {T_world_vertex.rotation.normalized(), T_world_vertex.translation};
}

double PoseGraph::edgeCost(const Edge& edge) const {
  const RelativePoseError error(edge.T_from_to, edge.information);
  const auto& a = poses_.at(edge.from);
  const auto& b = poses_.at(edge.to);
  Vec6 r;
  error(a.rotation.coeffs().data(), a.translation.data(), b.rotation.coeffs().data(),
        b.translation.data(), r.data());
  return r.squaredNorm();
}

SolveReport PoseGraph::optimise(const SolveOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  SolveReport report = solveOnce(options);
  const double initial_cost = report.initial_cost;
  int rejected = 0;
  for (int round = 0; round < 3 && options.reject_chi2 > 0; ++round) {
    int newly = 0;
    for (size_t e = 0; e < edges_.size(); ++e) {
      if (rejected_[e] || edges_[e].kind == EdgeKind::kOdometry) continue;
      if (edgeCost(edges_[e]) > options.reject_chi2) {
        rejected_[e] = true;
        ++newly;
      }
    }
    if (newly == 0) break;
    rejected += newly;
    const int iterations = report.iterations;
    report = solveOnce(options);
    report.iterations += iterations;
  }
  report.initial_cost = initial_cost;
  report.rejected_edges = rejected;
  report.milliseconds =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  return report;
}

SolveReport PoseGraph::solveOnce(const SolveOptions& options) {
  SolveReport report;
  if (edges_.empty()) return report;
  const int first_moving = options.window > 0 ? std::max(0, size() - options.window) : 0;
  auto moves = [&](int v) { return v >= first_moving && !fixed_[v]; };

  ceres::Problem::Options problem_options;
  problem_options.manifold_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(problem_options);
  ceres::EigenQuaternionManifold quaternion_manifold;
  ceres::HuberLoss robust(options.robust_sigma);
  int moving_edges = 0;
  for (size_t e = 0; e < edges_.size(); ++e) {
    const Edge& edge = edges_[e];
    if (rejected_[e]) continue;
    if (!moves(edge.from) && !moves(edge.to)) continue;  // nothing of it can change
    ++moving_edges;
    auto* cost = new ceres::AutoDiffCostFunction<RelativePoseError, 6, 4, 3, 4, 3>(
        new RelativePoseError(edge.T_from_to, edge.information));
    auto& a = poses_[edge.from];
    auto& b = poses_[edge.to];
    problem.AddResidualBlock(cost, edge.kind == EdgeKind::kOdometry ? nullptr : &robust,
                             a.rotation.coeffs().data(), a.translation.data(),
                             b.rotation.coeffs().data(), b.translation.data());
  }
  if (moving_edges == 0) return report;
  for (int v = 0; v < size(); ++v) {
    double* q = poses_[v].rotation.coeffs().data();
    if (!problem.HasParameterBlock(q)) continue;
    problem.SetManifold(q, &quaternion_manifold);
    if (!moves(v)) {
      problem.SetParameterBlockConstant(q);
      problem.SetParameterBlockConstant(poses_[v].translation.data());
    }
  }

  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  solver.max_num_iterations = options.max_iterations;
  solver.function_tolerance = 1e-12;
  solver.gradient_tolerance = 1e-12;
  solver.parameter_tolerance = 1e-12;
  solver.num_threads = 1;
  ceres::Solver::Summary summary;
  ceres::Solve(solver, &problem, &summary);
  for (auto& pose : poses_) pose.rotation.normalize();

  report.iterations = static_cast<int>(summary.iterations.size());
  report.initial_cost = summary.initial_cost;
  report.final_cost = summary.final_cost;
  report.converged = summary.termination_type == ceres::CONVERGENCE;
  return report;
}

G2oGraph toG2o(const PoseGraph& graph) {
  G2oGraph out;
  out.dimension = 3;
  out.has_estimates = true;
  for (int v = 0; v < graph.size(); ++v) {
    out.vertices.push_back({v, graph.pose(v)});
    if (graph.fixed(v)) out.fixed.push_back(v);
  }
  for (size_t e = 0; e < graph.edges().size(); ++e) {
    if (graph.rejected(e)) continue;
    const Edge& edge = graph.edges()[e];
    const Eigen::Matrix3d R = edge.T_from_to.rotation.normalized().toRotationMatrix();
    Mat6 N = Mat6::Zero();  // rows (rotation, translation) of ours, columns the file's
    N.topRightCorner<3, 3>() = -R.transpose();
    N.bottomLeftCorner<3, 3>() = R.transpose();
    Mat6 information = N.transpose() * edge.information * N;
    information = 0.5 * (information + information.transpose());
    out.edges.push_back({edge.from, edge.to, edge.T_from_to, information, 0});
  }
  return out;
}

}  // namespace stereomap::posegraph
