#include "onboard/posegraph/certificate.hpp"

#include <Eigen/CholmodSupport>
#include <Eigen/SparseCore>
#include <chrono>
#include <cstdio>
#include <vector>

namespace stereomap::posegraph {

namespace {

using Triplet = Eigen::Triplet<double>;
using Sparse = Eigen::SparseMatrix<double>;

// The indices of X's columns: t_i at i, R_i's d columns after all the translations.
struct Layout {
  int n = 0, d = 3;
  int t(int i) const { return i; }
  int r(int i, int k) const { return n + d * i + k; }
  int size() const { return n * (d + 1); }
};

// Each edge's terms of tr(M X^T X): kappa |R_j - R_i R~|_F^2 gives kappa I at (R_i, R_i) and
// (R_j, R_j) and -kappa R~ at (R_i, R_j); tau |t_j - t_i - R_i t~|^2 is tau v v^T with v = 1 at
// t_j, -1 at t_i and -t~ at R_i's columns.
void addEdge(const Layout& at, const ProblemEdge& edge, std::vector<Triplet>* m) {
  const int d = at.d;
  const Eigen::MatrixXd R = edge.R_meas.topLeftCorner(d, d);
  for (int k = 0; k < d; ++k) {
    m->emplace_back(at.r(edge.i, k), at.r(edge.i, k), edge.kappa);
    m->emplace_back(at.r(edge.j, k), at.r(edge.j, k), edge.kappa);
    for (int l = 0; l < d; ++l) {
      m->emplace_back(at.r(edge.i, k), at.r(edge.j, l), -edge.kappa * R(k, l));
      m->emplace_back(at.r(edge.j, l), at.r(edge.i, k), -edge.kappa * R(k, l));
    }
  }
  std::vector<std::pair<int, double>> v = {{at.t(edge.j), 1.0}, {at.t(edge.i), -1.0}};
  for (int k = 0; k < d; ++k) v.emplace_back(at.r(edge.i, k), -edge.t_meas(k));
  for (const auto& [a, va] : v) {
    for (const auto& [b, vb] : v) m->emplace_back(a, b, edge.tau * va * vb);
  }
}

}  // namespace

Certificate certifyOptimum(const GraphProblem& problem, double eta) {
  const auto start = std::chrono::steady_clock::now();
  const Layout at{problem.size(), problem.dimension()};
  const int d = at.d;
  std::vector<Triplet> entries;
  entries.reserve(problem.edges().size() * (4 * d * d + 2 * d + 9));
  for (const auto& edge : problem.edges()) addEdge(at, edge, &entries);
  Sparse M(at.size(), at.size());
  M.setFromTriplets(entries.begin(), entries.end());

  // X^T (N x d): row t_i is t_i^T, rows R_i's columns are R_i^T's rows.
  Eigen::MatrixXd Xt = Eigen::MatrixXd::Zero(at.size(), d);
  for (int i = 0; i < at.n; ++i) {
    const ProblemPose& pose = problem.poses()[i];
    Xt.row(at.t(i)) = pose.t.head(d).transpose();
    for (int k = 0; k < d; ++k) Xt.row(at.r(i, k)) = pose.R.topLeftCorner(d, d).col(k).transpose();
  }
  const Eigen::MatrixXd MXt = M * Xt;
  entries.clear();
  for (int i = 0; i < at.n; ++i) {
    const Eigen::MatrixXd P =
        MXt.middleRows(at.r(i, 0), d) * Xt.middleRows(at.r(i, 0), d).transpose();
    const Eigen::MatrixXd lambda = 0.5 * (P + P.transpose());
    for (int k = 0; k < d; ++k) {
      for (int l = 0; l < d; ++l) entries.emplace_back(at.r(i, k), at.r(i, l), -lambda(k, l));
    }
  }
  Sparse minus_lambda(at.size(), at.size());
  minus_lambda.setFromTriplets(entries.begin(), entries.end());
  const Sparse S = M + minus_lambda;

  Eigen::CholmodSupernodalLLT<Sparse, Eigen::Lower> cholesky;
  cholesky.cholmod().print = 0;  // "not positive definite" is an answer here, not a warning
  cholesky.setShift(eta);
  cholesky.compute(S);
  Certificate certificate;
  certificate.eta = eta;
  certificate.global = cholesky.info() == Eigen::Success;
  if (!certificate.global) {
    char text[200];
    std::snprintf(text, sizeof(text),
                  "S + %g I is not positive definite: S has a direction of negative curvature, "
                  "so a lower f exists or the solver has not converged",
                  eta);
    certificate.why_not = text;
  }
  certificate.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return certificate;
}

}  // namespace stereomap::posegraph
