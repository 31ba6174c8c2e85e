#include "onboard/posegraph/sparse_lm.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <stdexcept>

#include "common/worker_pool.hpp"
#include "onboard/posegraph/detail/block_cholesky.hpp"

namespace stereomap::posegraph {

using detail::BlockLayout;
using detail::Cholesky;

namespace {

using Clock = std::chrono::steady_clock;

double secondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

// One thread's share of the normal equations: H's stored values, the gradient J^T r, the cost.
struct Accumulator {
  std::vector<double> values, gradient;
  double cost = 0;
  void reset(const BlockLayout& layout) {
    values.assign(layout.nonzeros(), 0.0);
    gradient.assign(layout.size(), 0.0);
    cost = 0;
  }
};

template <int M, int K>
void accumulateEdges(const GraphProblem& problem, const BlockLayout& layout, size_t begin,
                     size_t end, Accumulator* out) {
  const bool exact_hessian = problem.weights() == Weights::kIsotropic;
  using Jacobian = Eigen::Matrix<double, M, K, Eigen::RowMajor>;
  using Block = Eigen::Matrix<double, K, K>;
  Eigen::Matrix<double, M, 1> r;
  Jacobian Ji, Jj;
  Eigen::Matrix<double, K, K, Eigen::RowMajor> Si, Sj;
  auto add = [&](int J, int slot, const Block& block, bool diagonal) {
    for (int c = 0; c < K; ++c) {
      double* column = out->values.data() + layout.position(J, slot, 0, c);
      const int rows = diagonal ? c + 1 : K;
      for (int row = 0; row < rows; ++row) column[row] += block(row, c);
    }
  };
  for (size_t e = begin; e < end; ++e) {
    const ProblemEdge& edge = problem.edges()[e];
    const auto& slots = layout.edges[e];
    problem.evaluate(edge, r.data(), Ji.data(), Jj.data());
    if (exact_hessian) problem.curvature(edge, Si.data(), Sj.data());
    out->cost += 0.5 * r.squaredNorm();
    if (slots.a >= 0) {
      add(slots.a, layout.diagonal_slot[slots.a],
          exact_hessian ? Block(Ji.transpose() * Ji + Si) : Block(Ji.transpose() * Ji), true);
      Eigen::Map<Eigen::Matrix<double, K, 1>>(out->gradient.data() + slots.a * K) +=
          Ji.transpose() * r;
    }
    if (slots.b >= 0) {
      add(slots.b, layout.diagonal_slot[slots.b],
          exact_hessian ? Block(Jj.transpose() * Jj + Sj) : Block(Jj.transpose() * Jj), true);
      Eigen::Map<Eigen::Matrix<double, K, 1>>(out->gradient.data() + slots.b * K) +=
          Jj.transpose() * r;
    }
    if (slots.slot >= 0) {
      if (slots.a < slots.b) {
        add(slots.b, slots.slot, Ji.transpose() * Jj, false);
      } else {
        add(slots.a, slots.slot, Jj.transpose() * Ji, false);
      }
    }
  }
}

void accumulate(const GraphProblem& problem, const BlockLayout& layout, size_t begin, size_t end,
                Accumulator* out) {
  const bool file = problem.weights() == Weights::kFile;
  if (problem.dimension() == 3) {
    file ? accumulateEdges<6, 6>(problem, layout, begin, end, out)
         : accumulateEdges<12, 6>(problem, layout, begin, end, out);
  } else {
    file ? accumulateEdges<3, 3>(problem, layout, begin, end, out)
         : accumulateEdges<6, 3>(problem, layout, begin, end, out);
  }
}

}  // namespace

SparseLMSummary solveSparseLM(GraphProblem& problem, const SparseLMOptions& options) {
  const auto start = Clock::now();
  SparseLMSummary summary;
  const BlockLayout layout(problem, problem.tangentSize());
  summary.initial_cost = summary.final_cost = problem.cost();
  if (layout.size() == 0 || problem.edges().empty()) {
    summary.converged = true;
    summary.termination = "nothing moves (every vertex is fixed)";
    summary.seconds = secondsSince(start);
    return summary;
  }
  if (!std::isfinite(summary.initial_cost)) {
    summary.termination = "the cost is not finite at the start (numbers too large for squares)";
    summary.seconds = secondsSince(start);
    return summary;
  }
  common::WorkerPool pool(1);
  Cholesky cholesky(layout, options.ordering, options.threads > 1 ? &pool : nullptr);
  summary.factor_nonzeros = cholesky.factorNonzeros();
  Accumulator halves[2];

  auto linearise = [&] {
    const auto begin = Clock::now();
    const size_t n = problem.edges().size(), middle = n / 2;
    halves[0].reset(layout);
    halves[1].reset(layout);
    // The same two halves with one thread or two: the sums, and so the result, do not depend
    // on the threads.
    auto first = [&] { accumulate(problem, layout, 0, middle, &halves[0]); };
    auto second = [&] { accumulate(problem, layout, middle, n, &halves[1]); };
    if (options.threads > 1) {
      pool.runPair(first, second);
    } else {
      first();
      second();
    }
    for (size_t v = 0; v < halves[0].values.size(); ++v) halves[0].values[v] += halves[1].values[v];
    for (size_t v = 0; v < halves[0].gradient.size(); ++v) {
      halves[0].gradient[v] += halves[1].gradient[v];
    }
    halves[0].cost += halves[1].cost;
    summary.evaluate_seconds += secondsSince(begin);
  };

  linearise();
  double cost = halves[0].cost;
  std::vector<double> hessian = halves[0].values, gradient = halves[0].gradient;
  double lambda = options.initial_lambda, nu = 2.0;
  std::vector<double> step, minus_gradient(gradient.size()), damping(layout.size());
  std::vector<ProblemPose> saved;
  const int k = layout.k;
  summary.termination = "the iteration limit";
  for (int iteration = 0; iteration < options.max_iterations; ++iteration) {
    const double largest =
        std::abs(*std::max_element(gradient.begin(), gradient.end(),
                                   [](double a, double b) { return std::abs(a) < std::abs(b); }));
    if (largest <= options.gradient_tolerance) {
      summary.converged = true;
      summary.termination = "the gradient vanished";
      break;
    }
    // Marquardt: H + lambda diag(H), the diagonal kept within a double's reach.
    double* values = cholesky.values();
    std::copy(hessian.begin(), hessian.end(), values);
    for (int J = 0; J < layout.blocks; ++J) {
      for (int c = 0; c < k; ++c) {
        const int at = layout.diagonal(J, c);
        damping[J * k + c] = lambda * std::clamp(hessian[at], 1e-6, 1e32);
        values[at] += damping[J * k + c];
      }
    }
    for (size_t v = 0; v < gradient.size(); ++v) minus_gradient[v] = -gradient[v];
    ++summary.iterations;
    const auto factorise_start = Clock::now();
    const bool solved = cholesky.solve(minus_gradient, 1, &step);
    summary.factorise_seconds += secondsSince(factorise_start);
    double predicted = 0;
    if (solved) {
      for (size_t v = 0; v < step.size(); ++v) {
        predicted += 0.5 * (step[v] * minus_gradient[v] + damping[v] * step[v] * step[v]);
      }
    }
    if (solved && predicted >= 0 && predicted <= options.function_tolerance * cost) {
      summary.converged = true;
      summary.termination = "the cost stopped falling";
      break;
    }
    if (!solved || !(predicted > 0)) {
      lambda *= nu;
      nu *= 2;
      if (lambda > 1e16) {
        summary.termination = "no step lowers the cost";
        break;
      }
      continue;
    }
    saved = problem.poses();
    for (int v = 0; v < problem.size(); ++v) {
      if (layout.block_of[v] >= 0) problem.retract(v, step.data() + layout.block_of[v] * k);
    }
    linearise();
    const double new_cost = halves[0].cost;
    const double rho = (cost - new_cost) / predicted;
    if (std::isfinite(new_cost) && rho > 1e-3) {
      const double decrease = cost - new_cost;
      cost = new_cost;
      hessian = halves[0].values;
      gradient = halves[0].gradient;
      lambda *= std::max(1.0 / 3.0, 1.0 - std::pow(2.0 * rho - 1.0, 3));
      nu = 2.0;
      if (decrease <= options.function_tolerance * (cost + decrease)) {
        summary.converged = true;
        summary.termination = "the cost stopped falling";
        break;
      }
    } else {
      problem.poses() = saved;
      lambda *= nu;
      nu *= 2;
      if (lambda > 1e16) {
        summary.termination = "no step lowers the cost";
        break;
      }
    }
  }
  summary.final_cost = cost;
  summary.seconds = secondsSince(start);
  return summary;
}

}  // namespace stereomap::posegraph
