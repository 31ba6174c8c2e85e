// An SE(3) pose graph solved with Ceres (the pose-graph paper, section 3 of
// ../shared/PAPERS.md): vertices are poses T_world_vertex, edges relative measurements
// T_i_j with an information matrix, the error of an edge e_ij = log(T_ij^-1 T_i^-1 T_j)
// (rotation first), its cost e^T Omega e. Loop and join edges get a robust (Huber) loss and
// are set aside when they still disagree after a solve: one wrong closure cannot bend the graph.
//
//   PoseGraph graph;                           // vertex 0 holds the gauge (fixed)
//   const int a = graph.addVertex(T_world_a), b = graph.addVertex(T_world_b);
//   graph.addEdge({a, b, T_a_b, information, EdgeKind::kOdometry});
//   graph.optimise();                          // batch; {.window = 20}: only the last 20 move
#pragma once

#include <vector>

#include "common/geometry.hpp"
#include "common/result.hpp"
#include "onboard/posegraph/g2o.hpp"
#include "onboard/posegraph/se3.hpp"

namespace stereomap::posegraph {

enum class EdgeKind { kOdometry, kLoop, kJoin };

struct Edge {
  int from = 0, to = 0;
  common::Rigid3 T_from_to;             // the measured pose of `to` in `from`'s frame
  Mat6 information = Mat6::Identity();  // (rotation, translation), symmetric positive definite
  EdgeKind kind = EdgeKind::kOdometry;
};

struct SolveOptions {
  int max_iterations = 100;
  // Only the newest `window` vertices move (0: all but the fixed ones): incremental use.
  int window = 0;
  // Huber threshold on the whitened error of loop and join edges (in standard deviations).
  double robust_sigma = 3.0;
  // After a solve, loop and join edges whose cost e^T Omega e is still above this (the 99.9 %
  // point of chi-square with 6 degrees of freedom) are set aside as wrong and the graph is
  // solved again without them (0: keep every edge). Huber alone still gives way by its
  // threshold times the stiffness of the rest.
  double reject_chi2 = 22.46;
};

struct SolveReport {
  int iterations = 0;
  int rejected_edges = 0;  // set aside by this solve
  double initial_cost = 0, final_cost = 0;
  bool converged = false;
  double milliseconds = 0;
};

class PoseGraph {
 public:
  // Returns the new vertex's id (0, 1, 2, ...). The first vertex is fixed: the gauge.
  int addVertex(const common::Rigid3& T_world_vertex);
  // Refuses unknown vertices, an edge from a vertex to itself, and an information matrix
  // that is not finite, symmetric and positive definite.
  common::Status addEdge(const Edge& edge);
  void setFixed(int vertex, bool fixed);
  bool fixed(int vertex) const { return fixed_.at(vertex); }

  SolveReport optimise(const SolveOptions& options = {});

  int size() const { return static_cast<int>(poses_.size()); }
  const common::Rigid3& pose(int vertex) const { return poses_.at(vertex); }
  void setPose(int vertex, const common::Rigid3& T_world_vertex);
  const std::vector<Edge>& edges() const { return edges_; }
  bool rejected(size_t edge) const { return rejected_.at(edge); }
  // e^T Omega e of one edge at the current poses.
  double edgeCost(const Edge& edge) const;

 private:
  std::vector<common::Rigid3> poses_;
  std::vector<bool> fixed_;
  std::vector<Edge> edges_;
  std::vector<bool> rejected_;

  SolveReport solveOnce(const SolveOptions& options);
};

// The graph as a g2o file holds it (stereomap-posegraph and other tools solve it again): the
// vertices at their current poses, fixed ones on FIX lines, the edges not set aside. The
// information is carried over to the error the file's readers use (Ceres' example, SE-Sync,
// GTSAM: e = [R_i^T (t_j - t_i) - t~ ; rotation angle-axis of R~ R_ij^T], translation first),
// which is, to first order, this graph's e = log(T~^-1 T_ij) turned by
// N = [0, -R~^T; R~^T, 0]: the file's information is N^T Omega N. So the file's optimum is this
// graph's (near it by the errors' second order); the robust loss is not in the file.
G2oGraph toG2o(const PoseGraph& graph);

// The error of one edge, as Ceres sees it: 6 residuals sqrt(Omega) * log(T_ij^-1 T_i^-1 T_j)
// over the blocks (q_i, t_i, q_j, t_j), quaternions in Eigen's order (x, y, z, w). Public for
// the Jacobian test.
struct RelativePoseError {
  RelativePoseError(const common::Rigid3& T_i_j, const Mat6& information);

  template <typename T>
  bool operator()(const T* q_i, const T* t_i, const T* q_j, const T* t_j, T* residual) const {
    const Eigen::Map<const Eigen::Quaternion<T>> Q_i(q_i), Q_j(q_j);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> P_i(t_i), P_j(t_j);
    const Eigen::Quaternion<T> Q_i_inv = Q_i.conjugate();
    // T_i^-1 T_j, then T_ij^-1 times that.
    const Eigen::Quaternion<T> q_rel = Q_i_inv * Q_j;
    const Eigen::Matrix<T, 3, 1> t_rel = Q_i_inv * (P_j - P_i);
    const Eigen::Quaternion<T> q_meas_inv = measured_q_.conjugate().template cast<T>();
    const Eigen::Quaternion<T> q_err = q_meas_inv * q_rel;
    const Eigen::Matrix<T, 3, 1> t_err = q_meas_inv * (t_rel - measured_t_.template cast<T>());
    Eigen::Map<Eigen::Matrix<T, 6, 1>> r(residual);
    r = sqrt_information_.template cast<T>() * se3Log(q_err, t_err);
    return true;
  }

 private:
  Eigen::Quaterniond measured_q_;
  Eigen::Vector3d measured_t_;
  Mat6 sqrt_information_;  // L^T with Omega = L L^T
};

}  // namespace stereomap::posegraph
