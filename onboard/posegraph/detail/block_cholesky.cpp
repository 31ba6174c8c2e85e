#include "onboard/posegraph/detail/block_cholesky.hpp"

#include <suitesparse/cholmod.h>

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace stereomap::posegraph::detail {

BlockLayout::BlockLayout(const GraphProblem& problem, int block_size) : k(block_size) {
  block_of.assign(problem.size(), -1);
  for (int v = 0; v < problem.size(); ++v) {
    if (!problem.fixed(v)) block_of[v] = blocks++;
  }
  std::vector<std::vector<int>> rows_of(blocks);
  for (const auto& edge : problem.edges()) {
    const int a = block_of[edge.i], b = block_of[edge.j];
    if (a >= 0 && b >= 0) rows_of[std::max(a, b)].push_back(std::min(a, b));
  }
  diagonal_slot.resize(blocks);
  for (int J = 0; J < blocks; ++J) {
    auto& list = rows_of[J];
    std::sort(list.begin(), list.end());
    list.erase(std::unique(list.begin(), list.end()), list.end());
    diagonal_slot[J] = static_cast<int>(list.size());
    list.push_back(J);
  }
  column_start.assign(blocks * k + 1, 0);
  for (int J = 0; J < blocks; ++J) {
    for (int c = 0; c < k; ++c) {
      const int col = J * k + c;
      column_start[col + 1] = column_start[col] + diagonal_slot[J] * k + c + 1;
      for (const int I : rows_of[J]) {
        for (int r = 0; r < (I == J ? c + 1 : k); ++r) row.push_back(I * k + r);
      }
    }
  }
  for (const auto& edge : problem.edges()) {
    EdgeSlots slots{block_of[edge.i], block_of[edge.j], -1};
    if (slots.a >= 0 && slots.b >= 0) {
      const auto& list = rows_of[std::max(slots.a, slots.b)];
      slots.slot = static_cast<int>(
          std::lower_bound(list.begin(), list.end(), std::min(slots.a, slots.b)) - list.begin());
    }
    edges.push_back(slots);
  }
}

Cholesky::Cholesky(const BlockLayout& layout, FillOrdering ordering) : common_(new cholmod_common) {
  cholmod_start(common_);
  common_->supernodal = CHOLMOD_SUPERNODAL;
  common_->quick_return_if_not_posdef = 1;
  common_->print = 0;  // a matrix that is not positive definite is an answer, not a warning
  if (ordering != FillOrdering::kAuto) {
    common_->nmethods = 1;
    common_->method[0].ordering = ordering == FillOrdering::kAmd     ? CHOLMOD_AMD
                                  : ordering == FillOrdering::kMetis ? CHOLMOD_METIS
                                                                     : CHOLMOD_NESDIS;
    common_->postorder = 1;
  }
  const int n = layout.size();
  matrix_ = cholmod_allocate_sparse(n, n, layout.nonzeros(), /*sorted=*/1, /*packed=*/1,
                                    /*stype=*/1, CHOLMOD_REAL, common_);
  if (matrix_) {
    std::copy(layout.column_start.begin(), layout.column_start.end(),
              static_cast<int*>(matrix_->p));
    std::copy(layout.row.begin(), layout.row.end(), static_cast<int*>(matrix_->i));
    std::fill_n(static_cast<double*>(matrix_->x), layout.nonzeros(), 0.0);
    factor_ = cholmod_analyze(matrix_, common_);
  }
  if (!matrix_ || !factor_) {
    release();
    throw std::runtime_error("CHOLMOD cannot analyse the pose graph's system (out of memory)");
  }
}

Cholesky::~Cholesky() { release(); }

void Cholesky::release() {
  if (!common_) return;
  cholmod_free_factor(&factor_, common_);
  cholmod_free_sparse(&matrix_, common_);
  cholmod_finish(common_);
  delete common_;
  common_ = nullptr;
}

double* Cholesky::values() { return static_cast<double*>(matrix_->x); }

long Cholesky::factorNonzeros() const { return static_cast<long>(common_->lnz); }

bool Cholesky::solve(const std::vector<double>& b, int columns, std::vector<double>* x) {
  if (!cholmod_factorize(matrix_, factor_, common_) || common_->status == CHOLMOD_NOT_POSDEF) {
    return false;
  }
  const int n = static_cast<int>(matrix_->nrow);
  cholmod_dense rhs{};
  rhs.nrow = n;
  rhs.ncol = columns;
  rhs.nzmax = static_cast<size_t>(n) * columns;
  rhs.d = n;
  rhs.x = const_cast<double*>(b.data());
  rhs.xtype = CHOLMOD_REAL;
  rhs.dtype = CHOLMOD_DOUBLE;
  cholmod_dense* solution = cholmod_solve(CHOLMOD_A, factor_, &rhs, common_);
  if (!solution) return false;
  const double* s = static_cast<const double*>(solution->x);
  x->assign(s, s + rhs.nzmax);
  cholmod_free_dense(&solution, common_);
  return std::all_of(x->begin(), x->end(), [](double v) { return std::isfinite(v); });
}

}  // namespace stereomap::posegraph::detail
