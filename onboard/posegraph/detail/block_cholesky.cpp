#include "onboard/posegraph/detail/block_cholesky.hpp"

#include <suitesparse/cholmod.h>

#include <Eigen/Cholesky>

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

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

namespace {

// A fill-reducing order of the graph of blocks (block column of L -> block), by CHOLMOD.
std::vector<int> fillReducingOrder(const BlockLayout& layout, FillOrdering ordering) {
  const int n = layout.blocks, k = layout.k;
  std::vector<int> start(n + 1, 0), rows;
  for (int J = 0; J < n; ++J) {
    const int first = layout.column_start[J * k];
    for (int slot = 0; slot <= layout.diagonal_slot[J]; ++slot) {
      rows.push_back(layout.row[first + slot * k] / k);
    }
    start[J + 1] = static_cast<int>(rows.size());
  }
  cholmod_common common;
  cholmod_start(&common);
  common.supernodal = CHOLMOD_SIMPLICIAL;
  common.print = 0;
  if (ordering != FillOrdering::kAuto) {
    common.nmethods = 1;
    common.method[0].ordering = ordering == FillOrdering::kAmd     ? CHOLMOD_AMD
                                : ordering == FillOrdering::kMetis ? CHOLMOD_METIS
                                                                   : CHOLMOD_NESDIS;
  }
  cholmod_sparse pattern{};
  pattern.nrow = pattern.ncol = n;
  pattern.nzmax = rows.size();
  pattern.p = start.data();
  pattern.i = rows.data();
  pattern.stype = 1;
  pattern.itype = CHOLMOD_INT;
  pattern.xtype = CHOLMOD_PATTERN;
  pattern.dtype = CHOLMOD_DOUBLE;
  pattern.sorted = 1;
  pattern.packed = 1;
  cholmod_factor* symbolic = cholmod_analyze(&pattern, &common);
  std::vector<int> order;
  if (symbolic) {
    const int* perm = static_cast<const int*>(symbolic->Perm);
    order.assign(perm, perm + n);
    cholmod_free_factor(&symbolic, &common);
  }
  cholmod_finish(&common);
  if (order.empty()) {
    throw std::runtime_error("CHOLMOD cannot order the pose graph's system (out of memory)");
  }
  return order;
}

// Beyond these the factor would take gigabytes: such a graph is refused, not swapped.
constexpr long kMaxFactorValues = 1L << 28;
constexpr long kMaxUpdates = 1L << 28;
// A column's products shared by two threads only when they are this many (a hand-over costs
// microseconds; a 6x6 product some 50 ns).
constexpr long kUpdatesWorthAThread = 2048;

}  // namespace

Cholesky::Cholesky(const BlockLayout& layout, FillOrdering ordering, common::WorkerPool* pool)
    : k_(layout.k), blocks_(layout.blocks), upper_(layout.nonzeros(), 0.0), pool_(pool) {
  if (k_ != 1 && k_ != 3 && k_ != 6) throw std::invalid_argument("blocks of 1, 3 or 6 only");
  if (blocks_ == 0) {
    column_start_.assign(1, 0);
    update_start_.assign(1, 0);
    return;
  }
  order_ = fillReducingOrder(layout, ordering);
  std::vector<int> column_of(blocks_);
  for (int j = 0; j < blocks_; ++j) column_of[order_[j]] = j;
  // The layout's blocks below the diagonal, in the order's numbering.
  std::vector<std::vector<int>> below(blocks_);
  for (int J = 0; J < blocks_; ++J) {
    const int first = layout.column_start[J * k_];
    for (int slot = 0; slot < layout.diagonal_slot[J]; ++slot) {
      const int a = column_of[layout.row[first + slot * k_] / k_], b = column_of[J];
      below[std::min(a, b)].push_back(std::max(a, b));
    }
  }
  // The factor's pattern: a column's own blocks and its children's in the elimination tree.
  std::vector<std::vector<int>> children(blocks_);
  std::vector<int> mark(blocks_, -1), column;
  column_start_.assign(1, 0);
  for (int j = 0; j < blocks_; ++j) {
    column.assign(1, j);
    mark[j] = j;
    auto add = [&](int i) {
      if (mark[i] != j) {
        mark[i] = j;
        column.push_back(i);
      }
    };
    for (const int i : below[j]) add(i);
    for (const int child : children[j]) {
      for (int slot = column_start_[child] + 1; slot < column_start_[child + 1]; ++slot) {
        if (rows_[slot] != j) add(rows_[slot]);
      }
    }
    std::sort(column.begin(), column.end());
    if (column.size() > 1) children[column[1]].push_back(j);
    rows_.insert(rows_.end(), column.begin(), column.end());
    column_start_.push_back(static_cast<int>(rows_.size()));
    const long off_diagonal = static_cast<long>(column.size()) - 1;
    factor_nonzeros_ += k_ * (k_ + 1) / 2 + off_diagonal * k_ * k_;
  }
  // Every update a block column receives: from each earlier column c holding its row j, the
  // product of c's blocks at rows i >= j and at row j.
  long update_count = 0;
  std::vector<std::vector<std::pair<int, int>>> sources(blocks_);  // row -> (column, slot)
  for (int c = 0; c < blocks_; ++c) {
    const long m = column_start_[c + 1] - column_start_[c] - 1;
    update_count += m * (m + 1) / 2;
    for (int slot = column_start_[c] + 1; slot < column_start_[c + 1]; ++slot) {
      sources[rows_[slot]].emplace_back(c, slot);
    }
  }
  const long values = static_cast<long>(rows_.size()) * k_ * k_;
  if (values > kMaxFactorValues || update_count > kMaxUpdates) {
    throw std::runtime_error("the pose graph's factor is too dense to hold (" +
                             std::to_string(values) + " values, " + std::to_string(update_count) +
                             " block products)");
  }
  factor_.assign(values, 0.0);
  updates_.reserve(update_count);
  update_start_.assign(1, 0);
  std::vector<int> slot_of(blocks_, -1);
  for (int j = 0; j < blocks_; ++j) {
    for (int slot = column_start_[j]; slot < column_start_[j + 1]; ++slot) {
      slot_of[rows_[slot]] = slot;
    }
    for (const auto& [c, at_j] : sources[j]) {
      for (int slot = at_j; slot < column_start_[c + 1]; ++slot) {
        updates_.push_back({slot_of[rows_[slot]], slot, at_j});
      }
    }
    update_start_.push_back(static_cast<long>(updates_.size()));
  }
  // Where each stored value of the layout goes: a diagonal block to both of its triangles, a
  // block above the diagonal transposed when the order puts its row after its column.
  const int kk = k_ * k_;
  for (int J = 0; J < blocks_; ++J) {
    for (int c = 0; c < k_; ++c) {
      const int col = J * k_ + c;
      for (int at = layout.column_start[col]; at < layout.column_start[col + 1]; ++at) {
        const int I = layout.row[at] / k_, r = layout.row[at] % k_;
        const int i = column_of[I], j = column_of[J];
        if (i == j) {
          const long diagonal = static_cast<long>(column_start_[j]) * kk;
          load_.emplace_back(diagonal + c * k_ + r, at);
          if (r != c) load_.emplace_back(diagonal + r * k_ + c, at);
          continue;
        }
        const int lower = std::min(i, j), upper = std::max(i, j);
        const int* first = rows_.data() + column_start_[lower];
        const int* last = rows_.data() + column_start_[lower + 1];
        const long slot = std::lower_bound(first, last, upper) - rows_.data();
        // Block (upper, lower) of L's matrix is A(I, J) when i > j, else its transpose.
        load_.emplace_back(slot * kk + (i > j ? c * k_ + r : r * k_ + c), at);
      }
    }
  }
  if (pool_) splitForTwoThreads();
}

void Cholesky::splitForTwoThreads() {
  // A column's work: the products it receives, and its own blocks; a subtree's, its columns'.
  std::vector<double> work(blocks_, 0.0);
  std::vector<std::vector<int>> children(blocks_);
  std::vector<int> roots;
  for (int j = 0; j < blocks_; ++j) {
    work[j] += static_cast<double>(update_start_[j + 1] - update_start_[j]) +
               (column_start_[j + 1] - column_start_[j]);
    const bool has_parent = column_start_[j + 1] - column_start_[j] > 1;
    if (has_parent) {
      const int parent = rows_[column_start_[j] + 1];
      work[parent] += work[j];  // a parent comes after its children
      children[parent].push_back(j);
    } else {
      roots.push_back(j);
    }
  }
  // Open the heaviest subtree into its children (its root joins the columns done after) until
  // no subtree holds more than a quarter of what the subtrees hold, then deal them out to the
  // two threads, heaviest first, each to the lighter.
  std::vector<int> open = roots, top;
  double total = 0;
  for (const int root : roots) total += work[root];
  for (;;) {
    const auto heaviest =
        std::max_element(open.begin(), open.end(), [&](int a, int b) { return work[a] < work[b]; });
    if (heaviest == open.end()) break;
    double held = 0;
    for (const int root : open) held += work[root];
    if (work[*heaviest] <= held / 4 || held < total / 2) break;
    const int node = *heaviest;
    open.erase(heaviest);
    top.push_back(node);
    open.insert(open.end(), children[node].begin(), children[node].end());
  }
  std::sort(open.begin(), open.end(), [&](int a, int b) { return work[a] > work[b]; });
  double load[2] = {0, 0};
  std::vector<int> stack;
  for (const int root : open) {
    const int thread = load[0] <= load[1] ? 0 : 1;
    load[thread] += work[root];
    for (stack.assign(1, root); !stack.empty();) {
      const int node = stack.back();
      stack.pop_back();
      subtrees_[thread].push_back(node);
      stack.insert(stack.end(), children[node].begin(), children[node].end());
    }
  }
  // The columns of a subtree in ascending order: children before their parents.
  for (auto& columns : subtrees_) std::sort(columns.begin(), columns.end());
  // Opened roots, after every subtree: ascending order is their tree order too.
  top_ = std::move(top);
  std::sort(top_.begin(), top_.end());
  // The columns done after hold the densest part of the factor (the last separators, half
  // the work on the data graphs): each of their products goes to one block of the column, so
  // the products of a column are split by their target, in two halves of about equal count,
  // each target's in their own order (the same sums to the bit).
  update_split_.assign(update_start_.begin() + 1, update_start_.end());
  std::vector<long> count;
  for (const int j : top_) {
    const long begin = update_start_[j], end = update_start_[j + 1];
    if (end - begin < kUpdatesWorthAThread) continue;
    count.assign(column_start_[j + 1] - column_start_[j] + 1, 0);
    for (long u = begin; u < end; ++u) ++count[updates_[u].target - column_start_[j]];
    int middle = 0;
    for (long sum = 0; sum < (end - begin) / 2;) sum += count[middle++];
    const int first_second = column_start_[j] + middle;
    update_split_[j] =
        std::stable_partition(updates_.begin() + begin, updates_.begin() + end,
                              [&](const Update& update) { return update.target < first_second; }) -
        updates_.begin();
  }
}

template <int K>
void Cholesky::applyUpdates(long begin, long end) {
  using Block = Eigen::Matrix<double, K, K>;
  constexpr int kk = K * K;
  double* f = factor_.data();
  for (long u = begin; u < end; ++u) {
    const Update& update = updates_[u];
    Eigen::Map<Block>(f + static_cast<long>(update.target) * kk).noalias() -=
        Eigen::Map<const Block>(f + static_cast<long>(update.a) * kk) *
        Eigen::Map<const Block>(f + static_cast<long>(update.b) * kk).transpose();
  }
}

template <int K>
bool Cholesky::factoriseColumn(int j, bool split) {
  using Block = Eigen::Matrix<double, K, K>;
  constexpr int kk = K * K;
  double* f = factor_.data();
  const long begin = update_start_[j], end = update_start_[j + 1];
  if (split && update_split_[j] < end) {
    pool_->runPair([&] { applyUpdates<K>(begin, update_split_[j]); },
                   [&] { applyUpdates<K>(update_split_[j], end); });
  } else {
    applyUpdates<K>(begin, end);
  }
  Eigen::Map<Block> diagonal(f + static_cast<long>(column_start_[j]) * kk);
  const Eigen::LLT<Block> llt(diagonal);
  if (llt.info() != Eigen::Success) return false;
  diagonal = llt.matrixL();
  // Blocks below: X L_jj^T = A, so X = A L_jj^-T.
  const Block inverse_transposed =
      diagonal.template triangularView<Eigen::Lower>().solve(Block::Identity()).transpose();
  for (int slot = column_start_[j] + 1; slot < column_start_[j + 1]; ++slot) {
    Eigen::Map<Block> block(f + static_cast<long>(slot) * kk);
    const Block product = block * inverse_transposed;
    block = product;
  }
  return true;
}

template <int K>
bool Cholesky::factorise() {
  std::fill(factor_.begin(), factor_.end(), 0.0);
  for (const auto& [to, from] : load_) factor_[to] = upper_[from];
  if (!pool_) {
    for (int j = 0; j < blocks_; ++j) {
      if (!factoriseColumn<K>(j, false)) return false;
    }
    return true;
  }
  bool definite[2] = {true, true};
  auto subtrees = [&](int thread) {
    for (const int j : subtrees_[thread]) {
      if (!(definite[thread] = factoriseColumn<K>(j, false))) return;
    }
  };
  pool_->runPair([&] { subtrees(0); }, [&] { subtrees(1); });
  if (!definite[0] || !definite[1]) return false;
  for (const int j : top_) {
    if (!factoriseColumn<K>(j, true)) return false;
  }
  return true;
}

template <int K>
void Cholesky::substitute(double* y) const {
  using Block = Eigen::Matrix<double, K, K>;
  using Vector = Eigen::Matrix<double, K, 1>;
  constexpr int kk = K * K;
  auto block = [&](int slot) {
    return Eigen::Map<const Block>(factor_.data() + static_cast<long>(slot) * kk);
  };
  for (int j = 0; j < blocks_; ++j) {  // L z = y
    Eigen::Map<Vector> yj(y + j * K);
    yj = block(column_start_[j]).template triangularView<Eigen::Lower>().solve(yj);
    for (int slot = column_start_[j] + 1; slot < column_start_[j + 1]; ++slot) {
      Eigen::Map<Vector>(y + rows_[slot] * K) -= block(slot) * yj;
    }
  }
  for (int j = blocks_ - 1; j >= 0; --j) {  // L^T x = z
    Eigen::Map<Vector> yj(y + j * K);
    for (int slot = column_start_[j] + 1; slot < column_start_[j + 1]; ++slot) {
      yj -= block(slot).transpose() * Eigen::Map<const Vector>(y + rows_[slot] * K);
    }
    yj = block(column_start_[j]).transpose().template triangularView<Eigen::Upper>().solve(yj);
  }
}

bool Cholesky::solve(const std::vector<double>& b, int columns, std::vector<double>* x) {
  const bool factorised = k_ == 1 ? factorise<1>() : k_ == 3 ? factorise<3>() : factorise<6>();
  if (!factorised) return false;
  const long n = static_cast<long>(blocks_) * k_;
  x->assign(n * columns, 0.0);
  std::vector<double> y(n);
  for (int column = 0; column < columns; ++column) {
    const double* in = b.data() + column * n;
    double* out = x->data() + column * n;
    for (int j = 0; j < blocks_; ++j) std::copy_n(in + order_[j] * k_, k_, y.data() + j * k_);
    k_ == 1 ? substitute<1>(y.data()) : k_ == 3 ? substitute<3>(y.data()) : substitute<6>(y.data());
    for (int j = 0; j < blocks_; ++j) std::copy_n(y.data() + j * k_, k_, out + order_[j] * k_);
  }
  return std::all_of(x->begin(), x->end(), [](double v) { return std::isfinite(v); });
}

}  // namespace stereomap::posegraph::detail
