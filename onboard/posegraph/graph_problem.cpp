#include "onboard/posegraph/graph_problem.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
#include <cmath>
#include <limits>
#include <numeric>
#include <optional>
#include <unordered_map>

namespace stereomap::posegraph {

namespace {

Eigen::Matrix3d skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

Eigen::Matrix3d expSO3(const Eigen::Vector3d& w) {
  const double theta = w.norm();
  if (theta < 1e-12) return Eigen::Matrix3d::Identity() + skew(w);
  return Eigen::AngleAxisd(theta, w / theta).toRotationMatrix();
}

Eigen::Matrix3d rotZ(double psi) {
  return Eigen::AngleAxisd(psi, Eigen::Vector3d::UnitZ()).toRotationMatrix();
}

// The planar part of a rotation about z, and dR/dpsi at psi = 0 (right perturbation).
Eigen::Matrix2d planar(const Eigen::Matrix3d& R) { return R.topLeftCorner<2, 2>(); }
const Eigen::Matrix2d kJz = (Eigen::Matrix2d() << 0, -1, 1, 0).finished();

double angleOf(const Eigen::Matrix2d& R) { return std::atan2(R(1, 0), R(0, 0)); }

// The vector part of the rotation's quaternion, taken the short way round (w >= 0).
Eigen::Quaterniond shortQuaternion(const Eigen::Matrix3d& R) {
  Eigen::Quaterniond q(R);
  if (q.w() < 0) q.coeffs() = -q.coeffs();
  return q;
}

int findRoot(std::vector<int>& parent, int v) {
  while (parent[v] != v) v = parent[v] = parent[parent[v]];
  return v;
}

}  // namespace

GraphProblem::GraphProblem(const G2oGraph& graph, Weights weights)
    : dimension_(graph.dimension), weights_(weights) {
  std::unordered_map<int64_t, int> index;
  index.reserve(graph.vertices.size());
  for (const auto& vertex : graph.vertices) {
    index.emplace(vertex.id, static_cast<int>(poses_.size()));
    poses_.push_back({vertex.T_world_vertex.rotation.normalized().toRotationMatrix(),
                      vertex.T_world_vertex.translation});
  }
  std::vector<int> parent(poses_.size());
  std::iota(parent.begin(), parent.end(), 0);
  for (const auto& read : graph.edges) {
    ProblemEdge edge;
    edge.i = index.at(read.from);
    edge.j = index.at(read.to);
    edge.q_meas = read.T_from_to.rotation.normalized();
    edge.R_meas = edge.q_meas.toRotationMatrix();
    edge.t_meas = read.T_from_to.translation;
    edge.information = read.information;
    edge.whitening.setZero();
    if (dimension_ == 3) {
      // An indefinite matrix (read as InformationUse::kBlocks) has no whitening: the file's
      // objective is not defined on it, and ceresHalfSum says so.
      if (!read.indefinite)
        edge.whitening = Eigen::LLT<Mat6>(read.information).matrixL().transpose();
      edge.tau = 3.0 / read.information.topLeftCorner<3, 3>().inverse().trace();
      edge.kappa = 3.0 / (2.0 * read.information.bottomRightCorner<3, 3>().inverse().trace());
    } else {
      Eigen::Matrix3d omega;
      for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) omega(r, c) = read.information(kSe2Places[r], kSe2Places[c]);
      }
      if (!read.indefinite) {
        edge.whitening.topLeftCorner<3, 3>() =
            Eigen::LLT<Eigen::Matrix3d>(omega).matrixL().transpose();
      }
      edge.kappa = omega(2, 2);
      edge.tau = 2.0 / omega.topLeftCorner<2, 2>().inverse().trace();
    }
    indefinite_edges_ += read.indefinite ? 1 : 0;
    parent[findRoot(parent, edge.i)] = findRoot(parent, edge.j);
    edges_.push_back(edge);
  }
  // Each connected piece is held by one vertex: one a FIX line names, else its first.
  fixed_.assign(poses_.size(), false);
  std::vector<bool> anchored(poses_.size(), false);
  for (const int64_t id : graph.fixed) {
    const int v = index.at(id);
    fixed_[v] = true;
    anchored[findRoot(parent, v)] = true;
  }
  piece_.assign(poses_.size(), -1);
  std::vector<int> piece_of_root(poses_.size(), -1);
  for (int v = 0; v < size(); ++v) {
    const int root = findRoot(parent, v);
    if (piece_of_root[root] < 0) {
      piece_of_root[root] = pieces_++;
      if (!anchored[root]) fixed_[v] = true;
    }
    piece_[v] = piece_of_root[root];
  }
}

int GraphProblem::residualSize() const { return residualSize(weights_); }

int GraphProblem::residualSize(Weights weights) const {
  if (weights == Weights::kFile) return dimension_ == 3 ? 6 : 3;
  return dimension_ == 3 ? 12 : 6;
}

void GraphProblem::evaluate(const ProblemEdge& edge, double* r, double* J_i, double* J_j) const {
  evaluateAs(weights_, edge, r, J_i, J_j);
}

void GraphProblem::evaluateAs(Weights weights, const ProblemEdge& edge, double* r, double* J_i,
                              double* J_j) const {
  const ProblemPose& a = poses_[edge.i];
  const ProblemPose& b = poses_[edge.j];
  const int m = residualSize(weights), k = tangentSize();
  Eigen::Map<Eigen::VectorXd> residual(r, m);
  using RowMajor = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
  std::optional<Eigen::Map<RowMajor>> Ji, Jj;
  if (J_i) Ji.emplace(J_i, m, k);
  if (J_j) Jj.emplace(J_j, m, k);
  if (Ji) Ji->setZero();
  if (Jj) Jj->setZero();

  if (dimension_ == 3 && weights == Weights::kFile) {
    const Eigen::Vector3d p_ab = a.R.transpose() * (b.t - a.t);
    const Eigen::Quaterniond dq =
        shortQuaternion(edge.R_meas * (a.R.transpose() * b.R).transpose());
    Eigen::Matrix<double, 6, 1> e;
    e << p_ab - edge.t_meas, 2.0 * dq.vec();
    residual = edge.whitening * e;
    if (!Ji) return;
    const Eigen::Matrix3d W = Eigen::Matrix3d::Identity() * dq.w();
    Eigen::Matrix<double, 6, 6> de_i = Eigen::Matrix<double, 6, 6>::Zero(), de_j = de_i;
    de_i.block<3, 3>(0, 0) = skew(p_ab);
    de_i.block<3, 3>(0, 3) = -a.R.transpose();
    de_i.block<3, 3>(3, 0) = W + skew(dq.vec());
    de_j.block<3, 3>(0, 3) = a.R.transpose();
    de_j.block<3, 3>(3, 0) = -(W - skew(dq.vec())) * edge.R_meas;
    *Ji = edge.whitening * de_i;
    *Jj = edge.whitening * de_j;
    return;
  }
  if (dimension_ == 3) {
    const double sk = std::sqrt(edge.kappa), st = std::sqrt(edge.tau);
    const Eigen::Matrix3d dR = b.R - a.R * edge.R_meas;
    residual.head<9>() = sk * Eigen::Map<const Eigen::Matrix<double, 9, 1>>(dR.data());
    residual.tail<3>() = st * (b.t - a.t - a.R * edge.t_meas);
    if (!Ji) return;
    for (int axis = 0; axis < 3; ++axis) {
      const Eigen::Matrix3d E = skew(Eigen::Vector3d::Unit(axis));
      const Eigen::Matrix3d di = -sk * a.R * E * edge.R_meas, dj = sk * b.R * E;
      Ji->block<9, 1>(0, axis) = Eigen::Map<const Eigen::Matrix<double, 9, 1>>(di.data());
      Jj->block<9, 1>(0, axis) = Eigen::Map<const Eigen::Matrix<double, 9, 1>>(dj.data());
    }
    Ji->block<3, 3>(9, 0) = st * a.R * skew(edge.t_meas);
    Ji->block<3, 3>(9, 3) = -st * Eigen::Matrix3d::Identity();
    Jj->block<3, 3>(9, 3) = st * Eigen::Matrix3d::Identity();
    return;
  }
  const Eigen::Matrix2d Ra = planar(a.R), Rb = planar(b.R), Rm = planar(edge.R_meas);
  const Eigen::Vector2d d = (b.t - a.t).head<2>(), tm = edge.t_meas.head<2>();
  if (weights == Weights::kFile) {
    Eigen::Vector3d e;
    e << Ra.transpose() * d - tm, angleOf(Rm.transpose() * Ra.transpose() * Rb);
    residual = edge.whitening.topLeftCorner<3, 3>() * e;
    if (!Ji) return;
    Eigen::Matrix3d de_i = Eigen::Matrix3d::Zero(), de_j = Eigen::Matrix3d::Zero();
    de_i.block<2, 1>(0, 0) = (Ra * kJz).transpose() * d;
    de_i.block<2, 2>(0, 1) = -Ra.transpose();
    de_i(2, 0) = -1;
    de_j.block<2, 2>(0, 1) = Ra.transpose();
    de_j(2, 0) = 1;
    *Ji = edge.whitening.topLeftCorner<3, 3>() * de_i;
    *Jj = edge.whitening.topLeftCorner<3, 3>() * de_j;
    return;
  }
  const double sk = std::sqrt(edge.kappa), st = std::sqrt(edge.tau);
  const Eigen::Matrix2d dR = Rb - Ra * Rm;
  residual.head<4>() = sk * Eigen::Map<const Eigen::Vector4d>(dR.data());
  residual.tail<2>() = st * (d - Ra * tm);
  if (!Ji) return;
  const Eigen::Matrix2d di = -sk * Ra * kJz * Rm, dj = sk * Rb * kJz;
  Ji->block<4, 1>(0, 0) = Eigen::Map<const Eigen::Vector4d>(di.data());
  Jj->block<4, 1>(0, 0) = Eigen::Map<const Eigen::Vector4d>(dj.data());
  Ji->block<2, 1>(4, 0) = -st * Ra * kJz * tm;
  Ji->block<2, 2>(4, 1) = -st * Eigen::Matrix2d::Identity();
  Jj->block<2, 2>(4, 1) = st * Eigen::Matrix2d::Identity();
}

void GraphProblem::curvature(const ProblemEdge& edge, double* S_i, double* S_j) const {
  const int k = tangentSize();
  std::fill_n(S_i, k * k, 0.0);
  std::fill_n(S_j, k * k, 0.0);
  if (weights_ == Weights::kFile) return;
  const ProblemPose& a = poses_[edge.i];
  const ProblemPose& b = poses_[edge.j];
  if (dimension_ == 2) {
    // d2 Rz(d)/dd2 = -I at d = 0.
    const Eigen::Matrix2d Ra = planar(a.R), Rb = planar(b.R), Rm = planar(edge.R_meas);
    const Eigen::Matrix2d D = Rb - Ra * Rm;
    const Eigen::Vector2d d = (b.t - a.t).head<2>() - Ra * edge.t_meas.head<2>();
    S_j[0] = -edge.kappa * (Rb.transpose() * D).trace();
    S_i[0] = edge.kappa * (D.transpose() * Ra * Rm).trace() +
             edge.tau * d.dot(Ra * edge.t_meas.head<2>());
    return;
  }
  // The second derivative of R Exp(d) at 0 along (e_a, e_b) is R Sym_ab with
  // Sym_ab = (e_b e_a^T + e_a e_b^T) / 2 - delta_ab I, so <P, Sym_ab> = sym(P)_ab - delta_ab tr P.
  auto contract = [](const Eigen::Matrix3d& P) -> Eigen::Matrix3d {
    return 0.5 * (P + P.transpose()) - P.trace() * Eigen::Matrix3d::Identity();
  };
  const Eigen::Matrix3d D = b.R - a.R * edge.R_meas;
  const Eigen::Vector3d u = a.R.transpose() * (b.t - a.t - a.R * edge.t_meas);
  const Eigen::Matrix3d Sj = edge.kappa * contract(b.R.transpose() * D);
  const Eigen::Matrix3d Si = -edge.kappa * contract(a.R.transpose() * D * edge.R_meas.transpose()) -
                             edge.tau * contract(u * edge.t_meas.transpose());
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) {
      S_i[r * k + c] = Si(r, c);
      S_j[r * k + c] = Sj(r, c);
    }
  }
}

double GraphProblem::cost() const { return costAs(weights_); }

double GraphProblem::costAs(Weights weights) const {
  double sum = 0;
  double r[kMaxResiduals];
  const int m = residualSize(weights);
  for (const auto& edge : edges_) {
    evaluateAs(weights, edge, r, nullptr, nullptr);
    for (int k = 0; k < m; ++k) sum += r[k] * r[k];
  }
  return 0.5 * sum;
}

void GraphProblem::retract(int v, const double* delta) {
  ProblemPose& pose = poses_[v];
  if (dimension_ == 3) {
    pose.R = pose.R * expSO3(Eigen::Vector3d(delta[0], delta[1], delta[2]));
    pose.R = Eigen::Quaterniond(pose.R).normalized().toRotationMatrix();  // stays a rotation
    pose.t += Eigen::Vector3d(delta[3], delta[4], delta[5]);
    return;
  }
  pose.R = rotZ(angleOf(planar(pose.R)) + delta[0]);
  pose.t += Eigen::Vector3d(delta[1], delta[2], 0.0);
}

double GraphProblem::seSyncF() const {
  double f = 0;
  for (const auto& edge : edges_) {
    const ProblemPose& a = poses_[edge.i];
    const ProblemPose& b = poses_[edge.j];
    f += edge.kappa * (b.R - a.R * edge.R_meas).squaredNorm() +
         edge.tau * (b.t - a.t - a.R * edge.t_meas).squaredNorm();
  }
  return f;
}

double GraphProblem::g2oChi2() const {
  double chi2 = 0;
  for (const auto& edge : edges_) {
    const ProblemPose& a = poses_[edge.i];
    const ProblemPose& b = poses_[edge.j];
    const Eigen::Matrix3d R_err = edge.R_meas.transpose() * a.R.transpose() * b.R;
    const Eigen::Vector3d t_err =
        edge.R_meas.transpose() * (a.R.transpose() * (b.t - a.t) - edge.t_meas);
    Eigen::Matrix<double, 6, 1> e = Eigen::Matrix<double, 6, 1>::Zero();
    if (dimension_ == 3) {
      e << t_err, shortQuaternion(R_err).vec();
    } else {
      e << t_err.x(), t_err.y(), 0, 0, 0, angleOf(planar(R_err));
    }
    chi2 += e.dot(edge.information * e);
  }
  return chi2;
}

double GraphProblem::ceresHalfSum() const {
  return indefinite_edges_ > 0 ? std::numeric_limits<double>::quiet_NaN() : costAs(Weights::kFile);
}

G2oGraph GraphProblem::solved(const G2oGraph& read) const {
  G2oGraph out = read;
  out.has_estimates = true;
  for (size_t v = 0; v < out.vertices.size(); ++v) {
    out.vertices[v].T_world_vertex = {Eigen::Quaterniond(poses_[v].R).normalized(), poses_[v].t};
  }
  return out;
}

}  // namespace stereomap::posegraph
