// The sparse symmetric systems of a pose graph: the pattern of k x k blocks its edges make
// (one block per free vertex, one per pair of free vertices an edge joins), stored as an upper
// triangle in compressed columns, and a Cholesky factorisation of it in dense k x k blocks,
// analysed once and factorised again for every new set of values. Used by the Gauss-Newton
// solver (6 x 6 or 3 x 3 blocks) and the chordal initialisation (3 x 3 and 1 x 1).
//
// Why not CHOLMOD's numeric factorisation: a pose graph's factor is made of small dense blocks.
// CHOLMOD's supernodal code hands them to BLAS a few rows at a time and its simplicial code
// works entry by entry; a block factor whose every update (source block, target block) is
// listed once in the analysis runs a fixed-size k x k product per update. CHOLMOD still
// chooses the fill-reducing ordering, on the graph of blocks.
#pragma once

#include <vector>

#include "common/worker_pool.hpp"
#include "onboard/posegraph/graph_problem.hpp"
#include "onboard/posegraph/sparse_lm.hpp"

namespace stereomap::posegraph::detail {

// Entry (r, c) of block (I, J), I <= J, sits at position(J, slot, r, c), where slot is I's
// place among the blocks of block column J (sorted, the diagonal last).
struct BlockLayout {
  struct EdgeSlots {
    int a = -1, b = -1;  // blocks of the edge's vertices i and j (-1: fixed)
    int slot = -1;       // of the off-diagonal block (min(a, b), max(a, b)); -1: none
  };

  BlockLayout(const GraphProblem& problem, int k);

  int k = 0;
  int blocks = 0;
  std::vector<int> block_of;  // vertex -> block, -1 when fixed
  std::vector<int> column_start, row;
  std::vector<EdgeSlots> edges;    // per edge of the problem
  std::vector<int> diagonal_slot;  // per block column

  int size() const { return blocks * k; }
  int nonzeros() const { return column_start.back(); }
  int position(int J, int slot, int r, int c) const {
    return column_start[J * k + c] + slot * k + r;
  }
  int diagonal(int J, int c) const { return position(J, diagonal_slot[J], c, c); }
};

// The matrix of a layout and its block factor L (A = P L L^T P^T, P a permutation of blocks).
class Cholesky {
 public:
  // Throws std::runtime_error when the factor would not fit in memory. With a pool, two
  // disjoint subtrees of the elimination tree are factorised at once (the result is the same
  // to the bit: every column is computed by the same operations in the same order).
  Cholesky(const BlockLayout& layout, FillOrdering ordering, common::WorkerPool* pool = nullptr);

  double* values() { return upper_.data(); }  // the upper triangle, in the layout's order
  long factorNonzeros() const { return factor_nonzeros_; }

  // Factorises the matrix as it is now and solves it for the `columns` right-hand sides in `b`
  // (column-major, size() rows); false when it is not positive definite or the solution is
  // not finite.
  bool solve(const std::vector<double>& b, int columns, std::vector<double>* x);

 private:
  // Block target -= block a * block b^T, blocks by their slots.
  struct Update {
    int target, a, b;
  };
  void splitForTwoThreads();
  template <int K>
  void applyUpdates(long begin, long end);
  template <int K>
  bool factoriseColumn(int j, bool split);
  template <int K>
  bool factorise();
  template <int K>
  void substitute(double* y) const;

  int k_ = 0, blocks_ = 0;
  long factor_nonzeros_ = 0;
  std::vector<double> upper_;
  std::vector<int> order_;         // block column of L -> block of the layout
  std::vector<int> column_start_;  // block column of L -> its first slot; slot 0 the diagonal
  std::vector<int> rows_;          // slot -> block row of L, ascending within a column
  std::vector<double> factor_;     // k * k values per slot, column-major
  std::vector<std::pair<long, long>> load_;  // (factor_ index, upper_ index)
  std::vector<long> update_start_;           // block column of L -> its first update
  std::vector<Update> updates_;
  common::WorkerPool* pool_;
  std::vector<int> subtrees_[2], top_;  // columns of each thread's subtrees, then the rest
  std::vector<long> update_split_;      // column -> its first update of the second thread
};

}  // namespace stereomap::posegraph::detail
