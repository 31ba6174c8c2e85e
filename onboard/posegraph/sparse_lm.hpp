// Levenberg-Marquardt for a GraphProblem (graph_problem.hpp), made for graphs of thousands of
// poses: the edges' analytic Jacobians evaluated on both cores straight into the blocks of the
// normal equations (no Jacobian matrix), one symbolic analysis and a Cholesky factorisation in
// dense k x k blocks per iteration (detail/block_cholesky.hpp; two subtrees of the elimination
// tree at once, then the last separators' products split between the threads), the
// fill-reducing ordering CHOLMOD's (docs/BENCHMARKS.md).
//
//   const SparseLMSummary summary = solveSparseLM(problem);   // moves problem.poses()
#pragma once

#include <string>

#include "onboard/posegraph/graph_problem.hpp"

namespace stereomap::posegraph {

enum class FillOrdering { kAuto, kAmd, kNestedDissection, kMetis };

struct SparseLMOptions {
  int max_iterations = 100;
  // Converged when an accepted step lowers the cost by less than this share of it, or the
  // gradient's largest entry is below gradient_tolerance.
  double function_tolerance = 1e-12;
  double gradient_tolerance = 1e-12;
  // Marquardt's damping, relative to the diagonal, at the start: small, for a start near the
  // optimum (chordal); a worse start costs a few refused steps (measured on the four graphs of
  // ../shared/data/posegraph: 87 steps in all from 1e-8, 111 from 1e-4).
  double initial_lambda = 1e-8;
  int threads = 2;  // edge evaluation and factorisation; 1: the calling thread alone
  // Of the graph's blocks. kAuto: CHOLMOD tries AMD, then METIS and nested dissection when AMD
  // fills much, and keeps the ordering with the least fill.
  FillOrdering ordering = FillOrdering::kAuto;
};

struct SparseLMSummary {
  int iterations = 0;                       // steps tried, taken or not
  double initial_cost = 0, final_cost = 0;  // 1/2 sum |r|^2
  bool converged = false;
  std::string termination;  // why it stopped, in words
  double seconds = 0, factorise_seconds = 0, evaluate_seconds = 0;
  long factor_nonzeros = 0;
};

SparseLMSummary solveSparseLM(GraphProblem& problem, const SparseLMOptions& options = {});

}  // namespace stereomap::posegraph
