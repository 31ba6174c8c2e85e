#include "onboard/posegraph/detail/block_cholesky.hpp"

#include <gtest/gtest.h>

#include <Eigen/Cholesky>
#include <random>

namespace stereomap::posegraph::detail {
namespace {

// A graph of `n` vertices (the first fixed): a chain and `loops` random edges between them.
GraphProblem randomProblem(int n, int loops, uint32_t seed) {
  std::mt19937 random(seed);
  G2oGraph graph;
  graph.has_estimates = true;
  for (int v = 0; v < n; ++v) graph.vertices.push_back({v, {}});
  auto edge = [&](int a, int b) {
    G2oEdge e;
    e.from = a;
    e.to = b;
    e.information = Mat6::Identity();
    graph.edges.push_back(e);
  };
  for (int v = 0; v + 1 < n; ++v) edge(v, v + 1);
  std::uniform_int_distribution<int> vertex(0, n - 1);
  for (int l = 0; l < loops; ++l) {
    const int a = vertex(random), b = vertex(random);
    if (a != b) edge(a, b);
  }
  return GraphProblem(graph, Weights::kFile);
}

// Random values in the layout's pattern, made positive definite by a dominant diagonal (or
// with one negative diagonal entry), and the same matrix dense.
Eigen::MatrixXd fill(const BlockLayout& layout, double* values, uint32_t seed, bool definite) {
  std::mt19937 random(seed);
  std::uniform_real_distribution<double> entry(-1.0, 1.0);
  const int n = layout.size();
  Eigen::MatrixXd dense = Eigen::MatrixXd::Zero(n, n);
  for (int col = 0; col < n; ++col) {
    for (int at = layout.column_start[col]; at < layout.column_start[col + 1]; ++at) {
      const int row = layout.row[at];
      values[at] = entry(random);
      dense(row, col) = dense(col, row) = values[at];
    }
  }
  for (int col = 0; col < n; ++col) {
    const double sum = dense.col(col).cwiseAbs().sum();
    const double diagonal = definite || col != n / 2 ? sum + 1.0 : -1.0;
    const int at = layout.column_start[col + 1] - 1;  // the diagonal is the column's last
    values[at] = dense(col, col) = diagonal;
  }
  return dense;
}

class BlockCholeskyTest : public ::testing::TestWithParam<std::tuple<int, FillOrdering>> {};

TEST_P(BlockCholeskyTest, SolvesAsTheDenseFactorDoes) {
  const auto [k, ordering] = GetParam();
  for (uint32_t seed : {1u, 2u, 3u}) {
    const GraphProblem problem = randomProblem(60, 90, seed);
    const BlockLayout layout(problem, k);
    Cholesky cholesky(layout, ordering);
    const Eigen::MatrixXd dense = fill(layout, cholesky.values(), seed, true);
    const int n = layout.size();
    std::mt19937 random(seed);
    std::normal_distribution<double> normal;
    std::vector<double> b(static_cast<size_t>(n) * 3), x;
    for (double& value : b) value = normal(random);
    ASSERT_TRUE(cholesky.solve(b, 3, &x));
    const Eigen::MatrixXd expected =
        dense.llt().solve(Eigen::Map<const Eigen::MatrixXd>(b.data(), n, 3));
    const Eigen::Map<const Eigen::MatrixXd> got(x.data(), n, 3);
    EXPECT_LT((got - expected).cwiseAbs().maxCoeff(), 1e-10) << "seed " << seed;
    // Every entry below the diagonal counted once, fill included: at least A's own.
    EXPECT_GE(cholesky.factorNonzeros(), static_cast<long>(layout.nonzeros()));
    // New values, the same analysis.
    fill(layout, cholesky.values(), seed + 10, true);
    ASSERT_TRUE(cholesky.solve(b, 3, &x));
  }
}

TEST_P(BlockCholeskyTest, AMatrixThatIsNotPositiveDefiniteIsRefused) {
  const auto [k, ordering] = GetParam();
  const GraphProblem problem = randomProblem(30, 40, 7);
  const BlockLayout layout(problem, k);
  Cholesky cholesky(layout, ordering);
  fill(layout, cholesky.values(), 7, false);
  std::vector<double> b(layout.size(), 1.0), x;
  EXPECT_FALSE(cholesky.solve(b, 1, &x));
  // A NaN is refused, not solved into numbers.
  fill(layout, cholesky.values(), 7, true);
  cholesky.values()[0] = std::nan("");
  EXPECT_FALSE(cholesky.solve(b, 1, &x));
}

INSTANTIATE_TEST_SUITE_P(
    BlocksAndOrderings, BlockCholeskyTest,
    ::testing::Combine(::testing::Values(1, 3, 6),
                       ::testing::Values(FillOrdering::kAuto, FillOrdering::kAmd,
                                         FillOrdering::kNestedDissection, FillOrdering::kMetis)));

TEST(BlockCholesky, TwoPiecesAndNothingToSolve) {
  // Two chains with no edge between them: two trees in the elimination forest.
  G2oGraph graph;
  graph.has_estimates = true;
  for (int v = 0; v < 10; ++v) graph.vertices.push_back({v, {}});
  for (int v = 0; v + 1 < 10; ++v) {
    if (v == 4) continue;
    G2oEdge e;
    e.from = v;
    e.to = v + 1;
    e.information = Mat6::Identity();
    graph.edges.push_back(e);
  }
  const GraphProblem problem(graph, Weights::kFile);
  const BlockLayout layout(problem, 6);
  EXPECT_EQ(layout.blocks, 8);  // each piece's first vertex is fixed
  Cholesky cholesky(layout, FillOrdering::kAuto);
  const Eigen::MatrixXd dense = fill(layout, cholesky.values(), 3, true);
  std::vector<double> b(layout.size(), 1.0), x;
  ASSERT_TRUE(cholesky.solve(b, 1, &x));
  const Eigen::VectorXd expected = dense.llt().solve(Eigen::VectorXd::Ones(layout.size()));
  EXPECT_LT((Eigen::Map<const Eigen::VectorXd>(x.data(), x.size()) - expected).norm(), 1e-10);

  G2oGraph single;
  single.vertices.push_back({0, {}});
  const GraphProblem nothing(single, Weights::kFile);
  const BlockLayout empty(nothing, 6);
  Cholesky none(empty, FillOrdering::kAuto);
  EXPECT_TRUE(none.solve({}, 1, &x));
  EXPECT_TRUE(x.empty());
}

}  // namespace
}  // namespace stereomap::posegraph::detail
