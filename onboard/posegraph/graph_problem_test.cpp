#include "onboard/posegraph/graph_problem.hpp"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <random>

namespace stereomap::posegraph {
namespace {

common::Rigid3 randomPose(std::mt19937& random, int dimension) {
  std::normal_distribution<double> normal;
  if (dimension == 2) {
    return {Eigen::Quaterniond(Eigen::AngleAxisd(2 * normal(random), Eigen::Vector3d::UnitZ())),
            Eigen::Vector3d(normal(random), normal(random), 0)};
  }
  return {Eigen::Quaterniond(normal(random), normal(random), normal(random), normal(random))
              .normalized(),
          Eigen::Vector3d(normal(random), normal(random), normal(random))};
}

// Two vertices far from agreeing with their edge (large residuals: the curvature matters) and
// an information matrix with off-diagonal terms.
G2oGraph twoVertexGraph(std::mt19937& random, int dimension) {
  G2oGraph graph;
  graph.dimension = dimension;
  graph.has_estimates = true;
  graph.vertices = {{0, randomPose(random, dimension)}, {1, randomPose(random, dimension)}};
  G2oEdge edge;
  edge.from = 0;
  edge.to = 1;
  edge.T_from_to = randomPose(random, dimension);
  Mat6 A = Mat6::Random();
  edge.information = A * A.transpose() + Mat6::Identity();
  if (dimension == 2) {
    Mat6 planar = Mat6::Zero();
    for (int r : kSe2Places) {
      for (int c : kSe2Places) planar(r, c) = edge.information(r, c);
    }
    edge.information = planar;
  }
  graph.edges = {edge};
  return graph;
}

// 1/2 |r|^2 of the edge with both vertices moved by (d_i, d_j).
double moved(const GraphProblem& problem, const Eigen::VectorXd& d_i, const Eigen::VectorXd& d_j) {
  GraphProblem copy = problem;
  copy.retract(0, d_i.data());
  copy.retract(1, d_j.data());
  return copy.cost();
}

class GraphProblemTest : public ::testing::TestWithParam<std::tuple<int, Weights>> {};

TEST_P(GraphProblemTest, JacobiansAreTheResidualsDerivatives) {
  const auto [dimension, weights] = GetParam();
  std::mt19937 random(7);
  for (int trial = 0; trial < 20; ++trial) {
    GraphProblem problem(twoVertexGraph(random, dimension), weights);
    const int m = problem.residualSize(), k = problem.tangentSize();
    Eigen::VectorXd r(m);
    Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> Ji(m, k), Jj(m, k);
    problem.evaluate(problem.edges()[0], r.data(), Ji.data(), Jj.data());
    const double h = 1e-6;
    for (int vertex = 0; vertex < 2; ++vertex) {
      for (int axis = 0; axis < k; ++axis) {
        Eigen::VectorXd numeric(m);
        for (int sign : {1, -1}) {
          GraphProblem copy = problem;
          Eigen::VectorXd d = Eigen::VectorXd::Zero(k);
          d[axis] = sign * h;
          copy.retract(vertex, d.data());
          Eigen::VectorXd r_moved(m);
          copy.evaluate(copy.edges()[0], r_moved.data(), nullptr, nullptr);
          numeric = sign > 0 ? r_moved : Eigen::VectorXd((numeric - r_moved) / (2 * h));
        }
        const Eigen::VectorXd analytic =
            vertex == 0 ? Eigen::VectorXd(Ji.col(axis)) : Eigen::VectorXd(Jj.col(axis));
        EXPECT_LT((numeric - analytic).norm(), 1e-6 * (1 + analytic.norm()))
            << "vertex " << vertex << " axis " << axis << "\nnumeric " << numeric.transpose()
            << "\nanalytic " << analytic.transpose();
      }
    }
  }
}

// J^T J + the curvature terms is the Hessian of 1/2 |r|^2 in each vertex's own tangent.
TEST_P(GraphProblemTest, CurvatureCompletesTheHessian) {
  const auto [dimension, weights] = GetParam();
  if (weights == Weights::kFile)
    GTEST_SKIP() << "Gauss-Newton's Hessian alone for the file's weights";
  std::mt19937 random(11);
  for (int trial = 0; trial < 10; ++trial) {
    GraphProblem problem(twoVertexGraph(random, dimension), weights);
    const int m = problem.residualSize(), k = problem.tangentSize();
    Eigen::VectorXd r(m);
    using RowMajor = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
    RowMajor Ji(m, k), Jj(m, k), Si(k, k), Sj(k, k);
    problem.evaluate(problem.edges()[0], r.data(), Ji.data(), Jj.data());
    problem.curvature(problem.edges()[0], Si.data(), Sj.data());
    const double h = 1e-4;
    for (int vertex = 0; vertex < 2; ++vertex) {
      const RowMajor exact =
          vertex == 0 ? RowMajor(Ji.transpose() * Ji + Si) : RowMajor(Jj.transpose() * Jj + Sj);
      for (int a = 0; a < k; ++a) {
        for (int b = 0; b < k; ++b) {
          double second = 0;
          for (int sa : {1, -1}) {
            for (int sb : {1, -1}) {
              Eigen::VectorXd d = Eigen::VectorXd::Zero(k), zero = d;
              d[a] += sa * h;
              d[b] += sb * h;
              second += sa * sb * (vertex == 0 ? moved(problem, d, zero) : moved(problem, zero, d));
            }
          }
          second /= 4 * h * h;
          EXPECT_NEAR(second, exact(a, b), 1e-4 * (1 + std::abs(exact(a, b))))
              << "vertex " << vertex << " (" << a << ", " << b << ")";
        }
      }
    }
  }
}

INSTANTIATE_TEST_SUITE_P(DimensionsAndWeights, GraphProblemTest,
                         ::testing::Combine(::testing::Values(2, 3),
                                            ::testing::Values(Weights::kFile,
                                                              Weights::kIsotropic)));

// The conventions of ../shared/data/posegraph/README.md on one edge, by hand.
TEST(GraphProblemCosts, EachConventionIsTheReadmes) {
  G2oGraph graph;
  graph.has_estimates = true;
  const double angle = 0.2;
  graph.vertices = {{0, {}},
                    {1,
                     {Eigen::Quaterniond(Eigen::AngleAxisd(angle, Eigen::Vector3d::UnitZ())),
                      Eigen::Vector3d(1, 0.5, 0)}}};
  G2oEdge edge;
  edge.from = 0;
  edge.to = 1;
  edge.T_from_to.translation = Eigen::Vector3d(1, 0, 0);
  edge.information = Mat6::Identity();
  edge.information.diagonal() << 2, 2, 2, 8, 8, 8;
  graph.edges = {edge};
  const GraphProblem problem(graph, Weights::kFile);
  // Translation error 0.5 in y; rotation error `angle` about z.
  const double half = std::sin(angle / 2);
  EXPECT_NEAR(problem.g2oChi2(), 2 * (0.5 * 0.5) + 8 * half * half, 1e-12)
      << "g2o: the measured frame's translation error and the quaternion's vector part";
  EXPECT_NEAR(problem.ceresHalfSum(), 0.5 * (2 * 0.25 + 8 * 4 * half * half), 1e-12)
      << "Ceres: twice the vector part, half the sum";
  // SE-Sync: tau = 3 / tr(Omega_t^-1) = 2, kappa = 3 / (2 tr(Omega_R^-1)) = 4.
  const double chordal = 2 * (2 - 2 * std::cos(angle));  // |Rz(a) - I|_F^2
  EXPECT_NEAR(problem.seSyncF(), 4 * chordal + 2 * 0.25, 1e-12);
}

TEST(GraphProblemPieces, EachPieceIsHeldByOneVertexAndFixLinesChooseIt) {
  G2oGraph graph;
  graph.has_estimates = true;
  for (int id = 0; id < 5; ++id) graph.vertices.push_back({id, {}});
  G2oEdge edge;
  edge.information = Mat6::Identity();
  edge.from = 0, edge.to = 1;
  graph.edges.push_back(edge);
  edge.from = 2, edge.to = 3;
  graph.edges.push_back(edge);
  graph.fixed = {3};
  const GraphProblem problem(graph, Weights::kFile);
  EXPECT_EQ(problem.pieces(), 3);
  EXPECT_TRUE(problem.fixed(0));
  EXPECT_FALSE(problem.fixed(1));
  EXPECT_FALSE(problem.fixed(2)) << "its piece has vertex 3, named by FIX";
  EXPECT_TRUE(problem.fixed(3));
  EXPECT_TRUE(problem.fixed(4)) << "alone, it is its own piece";
}

}  // namespace
}  // namespace stereomap::posegraph
