#include "onboard/posegraph/g2o.hpp"

#include <gtest/gtest.h>

#include <Eigen/Cholesky>

#include <cmath>

namespace stereomap::posegraph {
namespace {

const std::string kInformation3 = " 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 4 0 0 4 0 4";
const std::string kInformation2 = " 10 0 0 10 0 5";

std::string edge3(int from, int to, const std::string& pose = "1 0 0 0 0 0 1") {
  return "EDGE_SE3:QUAT " + std::to_string(from) + " " + std::to_string(to) + " " + pose +
         kInformation3 + "\n";
}

TEST(G2o, ReadsSe3VerticesEdgesAndFix) {
  const std::string text =
      "# a comment\n"
      "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"
      "\n"
      "VERTEX_SE3:QUAT 7 1 2 3 0 0 0.7071068 0.7071068\n" +
      edge3(0, 7, "1 2 3 0 0 0.7071068 0.7071068") + "FIX 0\n";
  auto graph = parseG2o(text);
  ASSERT_TRUE(graph) << graph.error().message;
  EXPECT_EQ(graph->dimension, 3);
  EXPECT_TRUE(graph->has_estimates);
  ASSERT_EQ(graph->vertices.size(), 2u);
  EXPECT_EQ(graph->vertices[1].id, 7);
  EXPECT_NEAR(graph->vertices[1].T_world_vertex.rotation.norm(), 1.0, 1e-15) << "normalised";
  EXPECT_EQ(graph->vertices[1].T_world_vertex.translation, Eigen::Vector3d(1, 2, 3));
  ASSERT_EQ(graph->edges.size(), 1u);
  EXPECT_EQ(graph->edges[0].line, 5);
  EXPECT_EQ(graph->edges[0].information(3, 3), 4.0);
  EXPECT_EQ(graph->edges[0].information(0, 0), 1.0);
  EXPECT_EQ(graph->fixed, std::vector<int64_t>{0});
}

TEST(G2o, ReadsSe2WithItsInformationAtThePlanarPlaces) {
  auto graph = parseG2o(
      "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 1.5707963\nEDGE_SE2 0 1 1 0 1.5707963 10 1 2 20 3 "
      "30\n");
  ASSERT_TRUE(graph) << graph.error().message;
  EXPECT_EQ(graph->dimension, 2);
  const Mat6& info = graph->edges[0].information;
  EXPECT_EQ(info(0, 0), 10);
  EXPECT_EQ(info(0, 1), 1);
  EXPECT_EQ(info(1, 0), 1);
  EXPECT_EQ(info(0, 5), 2);
  EXPECT_EQ(info(1, 1), 20);
  EXPECT_EQ(info(1, 5), 3);
  EXPECT_EQ(info(5, 5), 30);
  EXPECT_EQ(info(2, 2), 0);
  const Eigen::Matrix3d R = graph->vertices[1].T_world_vertex.rotation.toRotationMatrix();
  EXPECT_NEAR(std::atan2(R(1, 0), R(0, 0)), 1.5707963, 1e-12);
}

TEST(G2o, AGraphOfEdgesAloneGetsItsVerticesFromTheEdges) {
  auto graph = parseG2o(edge3(3, 5) + edge3(5, 9));
  ASSERT_TRUE(graph) << graph.error().message;
  EXPECT_FALSE(graph->has_estimates);
  ASSERT_EQ(graph->vertices.size(), 3u);
  EXPECT_EQ(graph->vertices[0].id, 3);
  EXPECT_EQ(graph->vertices[2].id, 9);
}

TEST(G2o, WrittenGraphsReadBackExactly) {
  const std::string text =
      "VERTEX_SE3:QUAT 0 0.1 -2.5e-7 3 0.1 0.2 0.3 0.9273618495495703\n"
      "VERTEX_SE3:QUAT 1 1 2 3 0 0 0 1\n" +
      edge3(0, 1, "0.3333333333333333 2 3 0 0 0.19866933079506122 0.9800665778412416") + "FIX 1\n";
  auto graph = parseG2o(text);
  ASSERT_TRUE(graph) << graph.error().message;
  auto again = parseG2o(formatG2o(*graph));
  ASSERT_TRUE(again) << again.error().message;
  EXPECT_EQ(formatG2o(*again), formatG2o(*graph));
  EXPECT_EQ(again->vertices[0].T_world_vertex.translation,
            graph->vertices[0].T_world_vertex.translation);
  EXPECT_EQ(again->vertices[0].T_world_vertex.rotation.coeffs(),
            graph->vertices[0].T_world_vertex.rotation.coeffs());
  EXPECT_EQ(again->edges[0].information, graph->edges[0].information);
  EXPECT_EQ(again->fixed, graph->fixed);
}

// An edge whose information is indefinite only through the coupling of translation and rotation
// (as 5,021 of cubicle.g2o's 16,869 edges are): the file's weights refuse it and name both ways
// to read it; SE-Sync's isotropic weights, which use only the blocks, read it as written; the
// nearest positive definite matrix is used with a warning naming the line.
TEST(G2o, AnEdgeIndefiniteOnlyThroughItsCouplingIsReadAsTheWeightingAllows) {
  const std::string coupled =
      "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
      "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 10 0 0 0 0 0 10 0 0 0 0 10 1000 0 0 10 0 0 10 0 10\n";
  auto whole = parseG2o(coupled, "c.g2o");
  ASSERT_FALSE(whole);
  EXPECT_NE(whole.error().message.find("c.g2o line 3: the information matrix is not positive "
                                       "definite (only through its coupling"),
            std::string::npos)
      << whole.error().message;
  EXPECT_NE(whole.error().message.find("--weights isotropic"), std::string::npos);
  EXPECT_NE(whole.error().message.find("--indefinite nearest"), std::string::npos);

  auto blocks = parseG2o(coupled, "c.g2o", {InformationUse::kBlocks});
  ASSERT_TRUE(blocks) << blocks.error().message;
  ASSERT_EQ(blocks->edges.size(), 1u);
  EXPECT_TRUE(blocks->edges[0].indefinite);
  EXPECT_EQ(blocks->edges[0].information(2, 3), 1000.0);  // kept as written
  EXPECT_TRUE(blocks->warnings.empty());
  auto again = parseG2o(formatG2o(*blocks), "again", {InformationUse::kBlocks});
  ASSERT_TRUE(again);
  EXPECT_EQ(again->edges[0].information, blocks->edges[0].information);

  auto nearest = parseG2o(coupled, "c.g2o", {InformationUse::kNearest});
  ASSERT_TRUE(nearest) << nearest.error().message;
  const Mat6& information = nearest->edges[0].information;
  EXPECT_FALSE(nearest->edges[0].indefinite);
  EXPECT_EQ(Eigen::LLT<Mat6>(information).info(), Eigen::Success);
  EXPECT_EQ(information, information.transpose());
  ASSERT_EQ(nearest->warnings.size(), 1u);
  EXPECT_EQ(nearest->warnings[0].rfind("c.g2o line 3: the information matrix is not positive "
                                       "definite; its nearest positive definite matrix is used",
                                       0),
            0u)
      << nearest->warnings[0];
  // A positive definite edge is read as written in every mode, without a warning.
  auto plain =
      parseG2o("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n" + edge3(0, 1),
               "p.g2o", {InformationUse::kNearest});
  ASSERT_TRUE(plain);
  EXPECT_TRUE(plain->warnings.empty());
  EXPECT_FALSE(plain->edges[0].indefinite);
}

// Each bad file is refused with the line and the fault named.
TEST(G2o, BadInputIsRefusedNamingTheLine) {
  const std::string v0 = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n",
                    v1 = "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n";
  struct Case {
    std::string text, expected;
  };
  const std::vector<Case> cases = {
      {v0 + v1 + "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 1 0\n", "line 3: EDGE_SE3:QUAT takes 30"},
      {v0 + "VERTEX_SE3:QUAT 1 nan 0 0 0 0 0 1\n", "line 2: field 3 'nan' is not a finite"},
      {v0 + "VERTEX_SE3:QUAT 1 1e999 0 0 0 0 0 1\n", "line 2: field 3 '1e999'"},
      {v0 + "VERTEX_SE3:QUAT x 0 0 0 0 0 0 1\n", "line 2: 'x' is not a vertex id"},
      {v0 + "VERTEX_SE3:QUAT 1 0 0 0 0 0 0 2\n", "line 2: the quaternion"},
      {v0 + v0, "line 2: vertex 0 is defined again (first on line 1)"},
      {v0 + v1 + edge3(0, 0), "line 3: an edge from vertex 0 to itself"},
      {v0 + v1 + edge3(0, 4), "line 3: vertex 4 is not defined"},
      {v0 + v1 + "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 -4 0 0 4 0 4\n",
       "line 3: the information matrix's rotation block is not positive definite"},
      {v0 + v1 + "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 0 0 0 0 0 0 1 0 0 0 0 1 0 0 0 4 0 0 4 0 4\n",
       "line 3: the information matrix's translation block is not positive definite"},
      {"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 10 0 0 10 0 0\n",
       "line 3: the information matrix's rotation block is not positive definite"},
      {v0 + "VERTEX_SE2 1 0 0 0\n", "line 2: an SE(2) line in a file of SE(3) lines"},
      {v0 + "EDGE_SE3_PRIOR 0 1 2\n", "line 2: unknown line 'EDGE_SE3_PRIOR'"},
      {v0 + "FIX 9\n", "FIX names vertex 9"},
      {"# nothing\n\n", "no vertex and no edge"},
  };
  for (const auto& bad : cases) {
    auto graph = parseG2o(bad.text, "f.g2o");
    ASSERT_FALSE(graph) << bad.text;
    EXPECT_EQ(graph.error().code, common::ErrorCode::kInvalidArgument);
    EXPECT_NE(graph.error().message.find(bad.expected), std::string::npos)
        << graph.error().message << "\n expected: " << bad.expected;
    EXPECT_EQ(graph.error().message.rfind("f.g2o", 0), 0u) << graph.error().message;
  }
}

TEST(G2o, ADeviceIsRefusedBeforeItIsRead) {
  auto graph = readG2o("/dev/zero");  // would never end
  ASSERT_FALSE(graph);
  EXPECT_NE(graph.error().message.find("not a regular file"), std::string::npos);
}

TEST(G2o, BinaryBytesAreEscapedInTheError) {
  auto graph = parseG2o(std::string("\x01\xff\x1b[31m 1 2\n", 12), "f.g2o");
  ASSERT_FALSE(graph);
  EXPECT_NE(graph.error().message.find("'\\x01\\xff\\x1b[31m'"), std::string::npos)
      << graph.error().message;
}

TEST(G2o, AMissingFileIsNotFound) {
  auto graph = readG2o("/nonexistent/graph.g2o");
  ASSERT_FALSE(graph);
  EXPECT_EQ(graph.error().code, common::ErrorCode::kNotFound);
}

}  // namespace
}  // namespace stereomap::posegraph
