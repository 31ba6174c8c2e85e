// Whether a pose graph's solution is the global optimum of SE-Sync's objective f, proved as
// SE-Sync proves it (Rosen et al., IJRR 2019, theorem 7 and its verification, section 4.2):
// f is tr(M X^T X) over X = [t_1 .. t_n | R_1 .. R_n]; with Lambda the symmetric diagonal
// blocks of M X^T X at the rotations, the certificate S = M - diag(0, Lambda) is positive
// semidefinite exactly when X is a global optimum (the relaxation is tight). The test, as in
// SE-Sync: a Cholesky factorisation of S + eta I succeeds. A local solver stopped at a worse
// minimum or a saddle fails it: S then has an eigenvalue below -eta.
//
//   GraphProblem problem(graph, Weights::kIsotropic);
//   chordalInitialise(problem); solveSparseLM(problem);
//   const Certificate certificate = certifyOptimum(problem);   // certificate.global
#pragma once

#include <string>

#include "onboard/posegraph/graph_problem.hpp"

namespace stereomap::posegraph {

struct Certificate {
  bool global = false;  // S + eta I is positive definite: the poses are the global optimum
  double eta = 0;       // the tolerance: S's smallest eigenvalue is at least -eta
  std::string why_not;  // when not: where the factorisation stopped
  double seconds = 0;
};

// SE-Sync's default tolerance (its min_eig_num_tol).
inline constexpr double kCertificateTolerance = 1e-3;

// For the isotropic objective (Weights::kIsotropic: kappa and tau) at the problem's poses.
Certificate certifyOptimum(const GraphProblem& problem, double eta = kCertificateTolerance);

}  // namespace stereomap::posegraph
