// Fuzz target: g2o pose graphs as stereomap-posegraph reads them (onboard/posegraph/g2o), then,
// for small graphs, the solver on what was read.
// A graph that is read holds finite unit quaternions and symmetric positive definite
// information (read for SE-Sync's weights: its blocks; read as the nearest: all of it); written and
// read again it is the same graph to the bit; the chordal start and a few Levenberg-Marquardt steps
// run on it with either weighting without a crash, and a start that succeeds is finite.
#include <Eigen/Cholesky>
#include <cmath>

#include "onboard/posegraph/certificate.hpp"
#include "onboard/posegraph/chordal.hpp"
#include "onboard/posegraph/g2o.hpp"
#include "onboard/posegraph/sparse_lm.hpp"
#include "tests/fuzz/fuzz_input.hpp"

namespace {

using namespace stereomap::posegraph;

// SE(3) numbers read back to the bit; an SE(2) angle is written from the rotation it is held
// as (atan2), so it reads back to its last bit or so.
bool sameRigid(const stereomap::common::Rigid3& a, const stereomap::common::Rigid3& b,
               int dimension) {
  if (a.translation != b.translation) return false;
  if (dimension == 3) return a.rotation.coeffs() == b.rotation.coeffs();
  return a.rotation.angularDistance(b.rotation) < 1e-14;
}

void checkGraph(const G2oGraph& graph) {
  for (const auto& vertex : graph.vertices) {
    if (!vertex.T_world_vertex.translation.allFinite() ||
        std::abs(vertex.T_world_vertex.rotation.norm() - 1.0) > 1e-9) {
      __builtin_trap();
    }
  }
  for (const auto& edge : graph.edges) {
    if (!edge.information.allFinite() || edge.information != edge.information.transpose() ||
        std::abs(edge.T_from_to.rotation.norm() - 1.0) > 1e-9) {
      __builtin_trap();
    }
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  stereomap::fuzz::FuzzInput in(data, size);
  const std::string text(in.restText());
  // Read as SE-Sync's weights read it (the blocks alone) and as the nearest positive definite
  // matrix: every edge's blocks are positive definite, and the nearest matrix is too.
  if (const auto blocks = parseG2o(text, "fuzz", {InformationUse::kBlocks})) {
    checkGraph(*blocks);
    for (const auto& edge : blocks->edges) {
      const int t = blocks->dimension == 3 ? 3 : 2;
      if (Eigen::LLT<Eigen::MatrixXd>(edge.information.topLeftCorner(t, t)).info() !=
          Eigen::Success) {
        __builtin_trap();
      }
    }
    if (blocks->vertices.size() <= 64 && blocks->edges.size() <= 256) {
      GraphProblem problem(*blocks, Weights::kIsotropic);
      if (chordalInitialise(problem)) certifyOptimum(problem);
    }
  }
  if (const auto nearest = parseG2o(text, "fuzz", {InformationUse::kNearest})) {
    checkGraph(*nearest);
    for (const auto& edge : nearest->edges) {
      if (edge.indefinite) __builtin_trap();
      if (nearest->dimension == 3 && Eigen::LLT<Mat6>(edge.information).info() != Eigen::Success) {
        __builtin_trap();
      }
    }
  }
  const auto read = parseG2o(text, "fuzz");
  if (!read) return 0;
  checkGraph(*read);
  const auto again = parseG2o(formatG2o(*read), "again");
  if (!again || again->dimension != read->dimension ||
      again->vertices.size() != read->vertices.size() ||
      again->edges.size() != read->edges.size() || again->fixed != read->fixed) {
    __builtin_trap();
  }
  for (size_t v = 0; v < read->vertices.size(); ++v) {
    if (again->vertices[v].id != read->vertices[v].id ||
        !sameRigid(again->vertices[v].T_world_vertex, read->vertices[v].T_world_vertex,
                   read->dimension)) {
      __builtin_trap();
    }
  }
  for (size_t e = 0; e < read->edges.size(); ++e) {
    const auto& a = again->edges[e];
    const auto& b = read->edges[e];
    if (a.from != b.from || a.to != b.to || !sameRigid(a.T_from_to, b.T_from_to, read->dimension) ||
        a.information != b.information) {
      __builtin_trap();
    }
  }
  if (read->vertices.size() > 64 || read->edges.size() > 256) return 0;
  for (const Weights weights : {Weights::kFile, Weights::kIsotropic}) {
    GraphProblem problem(*read, weights);
    if (chordalInitialise(problem)) {
      for (const auto& pose : problem.poses()) {
        if (!pose.R.allFinite() || !pose.t.allFinite()) __builtin_trap();
      }
    }
    SparseLMOptions options;
    options.max_iterations = 5;
    options.threads = 1;
    solveSparseLM(problem, options);
  }
  return 0;
}
