// A pose graph read from a g2o file, as a least-squares problem over SE(3) (or SE(2), planar)
// poses, in one of the two objectives the field compares optimisers on
// (../shared/data/posegraph/README.md), with analytic Jacobians for a Gauss-Newton solver
// (sparse_lm.hpp) and the cost in each convention the field reports.
//
//   GraphProblem problem(*readG2o(path), Weights::kIsotropic);
//   chordalInitialise(problem);           // chordal.hpp
//   solveSparseLM(problem);               // sparse_lm.hpp
//   problem.seSyncF(); problem.g2oChi2(); problem.ceresHalfSum();
//
// Objectives (poses T_i = (R_i, t_i), edge i->j measuring (R~, t~) with information Omega):
// - Weights::kFile: the file's full information on the error Ceres' `pose_graph_3d` (and
//   `pose_graph_2d`) example defines: e = [R_i^T (t_j - t_i) - t~ ; 2 vec(q~ q_ij^-1)] (2D:
//   the angle difference), cost 1/2 sum e^T Omega e. The information is whitened by L^T
//   (Omega = L L^T); the example whitens by L, which weights by L^T L instead (ceres-solver
//   issues 449, 924: the same for a diagonal Omega, not otherwise).
// - Weights::kIsotropic: SE-Sync's f = sum kappa |R_j - R_i R~|_F^2 + tau |t_j - t_i - R_i t~|^2,
//   kappa and tau from each edge's information (3D: tau = 3 / tr(Omega_t^-1),
//   kappa = 3 / (2 tr(Omega_R^-1)); 2D: kappa = Omega_theta, tau = 2 / tr(Omega_t^-1)).
// Poses move by right perturbations: R <- R Exp(d_theta), t <- t + d_t; an SE(2) problem's
// tangent is (d_psi about z, d_x, d_y).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "onboard/posegraph/g2o.hpp"

namespace stereomap::posegraph {

enum class Weights { kFile, kIsotropic };

struct ProblemPose {
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
};

struct ProblemEdge {
  int i = 0, j = 0;  // vertex indices
  Eigen::Matrix3d R_meas;
  Eigen::Vector3d t_meas;
  Eigen::Quaterniond q_meas;
  Mat6 information;  // g2o's order (translation, rotation); 2D at rows/columns 0, 1, 5
  Eigen::Matrix<double, 6, 6> whitening;  // kFile: L^T (its top-left 3x3 in 2D)
  double kappa = 0, tau = 0;              // kIsotropic
};

class GraphProblem {
 public:
  static constexpr int kMaxResiduals = 12;
  static constexpr int kMaxTangent = 6;

  // Vertices in the graph's order; every connected piece has one fixed vertex: a vertex a FIX
  // line names, else the piece's first (the gauge). The poses start at the file's estimates.
  // Weights::kFile needs every edge's whole information positive definite (none `indefinite`).
  GraphProblem(const G2oGraph& graph, Weights weights);

  int dimension() const { return dimension_; }
  Weights weights() const { return weights_; }
  int tangentSize() const { return dimension_ == 3 ? 6 : 3; }
  int residualSize() const;
  int size() const { return static_cast<int>(poses_.size()); }
  int pieces() const { return pieces_; }

  const std::vector<ProblemEdge>& edges() const { return edges_; }
  const std::vector<ProblemPose>& poses() const { return poses_; }
  std::vector<ProblemPose>& poses() { return poses_; }
  bool fixed(int vertex) const { return fixed_[vertex]; }
  // The connected piece of each vertex (0 .. pieces()-1).
  const std::vector<int>& piece() const { return piece_; }

  // Residual r (residualSize()) and, when not null, the Jacobians (residualSize() x
  // tangentSize(), row-major) with respect to the perturbations of vertices i and j.
  void evaluate(const ProblemEdge& edge, double* r, double* J_i, double* J_j) const;
  // SE-Sync's objective is far from linear in the rotations (|R Exp(d) - M|_F bends with d) and
  // its residuals are not small, so Gauss-Newton alone converges slowly on it (linearly, the
  // cost falling by a constant factor per step). These are the terms Gauss-Newton leaves out of
  // the Hessian, sum r_k d2r_k (tangentSize() squared, row-major, for vertices i and j); zero
  // for Weights::kFile, whose error is nearly linear near the optimum.
  void curvature(const ProblemEdge& edge, double* S_i, double* S_j) const;
  // The cost the solver minimises: 1/2 sum |r|^2.
  double cost() const;
  // Moves vertex v by the tangent step `delta` (tangentSize() values).
  void retract(int v, const double* delta);

  // The costs in each convention at the current poses (README's definitions), whatever
  // objective is being minimised.
  double seSyncF() const;
  double g2oChi2() const;
  // NaN when an edge's information is indefinite (read as InformationUse::kBlocks): the file's
  // objective is not defined there.
  double ceresHalfSum() const;
  int indefiniteEdges() const { return indefinite_edges_; }

  // The graph with its vertices at the current poses (for writing).
  G2oGraph solved(const G2oGraph& read) const;

 private:
  int residualSize(Weights weights) const;
  void evaluateAs(Weights weights, const ProblemEdge& edge, double* r, double* J_i,
                  double* J_j) const;
  double costAs(Weights weights) const;

  int dimension_ = 3;
  Weights weights_;
  int pieces_ = 0;
  int indefinite_edges_ = 0;
  std::vector<ProblemPose> poses_;
  std::vector<bool> fixed_;
  std::vector<int> piece_;
  std::vector<ProblemEdge> edges_;
};

}  // namespace stereomap::posegraph
