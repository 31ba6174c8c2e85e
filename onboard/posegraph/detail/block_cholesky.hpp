// The sparse symmetric systems of a pose graph: the pattern of k x k blocks its edges make
// (one block per free vertex, one per pair of free vertices an edge joins), stored as CHOLMOD's
// upper triangle in compressed columns, and a supernodal Cholesky factorisation of it, analysed
// once and factorised again for every new set of values. Used by the Gauss-Newton solver
// (6 x 6 or 3 x 3 blocks) and the chordal initialisation (3 x 3 and 1 x 1).
#pragma once

#include <vector>

#include "onboard/posegraph/graph_problem.hpp"
#include "onboard/posegraph/sparse_lm.hpp"

struct cholmod_common_struct;
struct cholmod_sparse_struct;
struct cholmod_factor_struct;

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

// CHOLMOD's workspace, the matrix of a layout and its factor, released together.
class Cholesky {
 public:
  Cholesky(const BlockLayout& layout, FillOrdering ordering);
  ~Cholesky();
  Cholesky(const Cholesky&) = delete;
  Cholesky& operator=(const Cholesky&) = delete;

  double* values();  // the stored upper triangle, in the layout's order
  long factorNonzeros() const;

  // Factorises the matrix as it is now and solves it for the `columns` right-hand sides in `b`
  // (column-major, size() rows); false when it is not positive definite or the solution is
  // not finite.
  bool solve(const std::vector<double>& b, int columns, std::vector<double>* x);

 private:
  void release();
  cholmod_common_struct* common_;
  cholmod_sparse_struct* matrix_ = nullptr;
  cholmod_factor_struct* factor_ = nullptr;
};

}  // namespace stereomap::posegraph::detail
