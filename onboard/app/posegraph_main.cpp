// stereomap-posegraph: solves a pose graph in g2o format (the field's benchmark graphs, or a
// flight's keyframe graph from stereomap-onboard --graph-out) and reports its cost in each
// convention the field uses.
#include <CLI/CLI.hpp>

#include <chrono>
#include <cstdio>

#include "common/cli.hpp"
#include "onboard/posegraph/certificate.hpp"
#include "onboard/posegraph/chordal.hpp"
#include "onboard/posegraph/g2o.hpp"
#include "onboard/posegraph/graph_problem.hpp"
#include "onboard/posegraph/sparse_lm.hpp"

namespace {

using namespace stereomap::posegraph;

void printCosts(const char* when, const GraphProblem& problem) {
  char ceres[64] = "n/a (an information matrix is indefinite)";
  if (problem.indefiniteEdges() == 0) {
    std::snprintf(ceres, sizeof(ceres), "%.9g", problem.ceresHalfSum());
  }
  std::printf("%s: SE-Sync f %.9g, g2o chi2 %.9g, Ceres half sum %s\n", when, problem.seSyncF(),
              problem.g2oChi2(), ceres);
}

// The reader's warnings, the first few whole and the rest counted (a graph may have thousands).
void printWarnings(const std::vector<std::string>& warnings) {
  constexpr size_t kShown = 5;
  for (size_t k = 0; k < warnings.size() && k < kShown; ++k) {
    std::fprintf(stderr, "warning: %s\n", warnings[k].c_str());
  }
  if (warnings.size() > kShown) {
    std::fprintf(stderr, "warning: %zu more edges like these\n", warnings.size() - kShown);
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "stereomap-posegraph: solve a pose graph in g2o format (VERTEX_SE3:QUAT, EDGE_SE3:QUAT, "
      "VERTEX_SE2, EDGE_SE2, FIX) and print its cost in each convention: SE-Sync's f, g2o's "
      "chi2, Ceres' half sum (../shared/data/posegraph/README.md)"};
  std::string input, output, weights = "file", init = "chordal", ordering = "auto",
                             indefinite = "refuse", certify = "auto";
  int max_iterations = 100, threads = 2;
  app.add_option("graph", input, "The graph, a g2o file")->required()->check(CLI::ExistingFile);
  app.add_option("--out", output, "Write the solved graph here (g2o, the vertices moved)");
  app.add_option("--weights", weights,
                 "file: the file's full information on Ceres' error (its example's objective, "
                 "whitened by L^T); isotropic: SE-Sync's kappa and tau and its objective f")
      ->check(CLI::IsMember({"file", "isotropic"}))
      ->capture_default_str();
  app.add_option("--indefinite", indefinite,
                 "An edge whose whole information matrix is indefinite (its translation and "
                 "rotation blocks positive definite, the coupling too large), with --weights "
                 "file: refuse (the error names the line), or nearest (the nearest positive "
                 "definite matrix, a warning naming each line). --weights isotropic reads such "
                 "an edge as it is: it uses only the blocks")
      ->check(CLI::IsMember({"refuse", "nearest"}))
      ->capture_default_str();
  app.add_option("--certify", certify,
                 "With --weights isotropic: prove the solution is SE-Sync's global optimum "
                 "(its certificate S + 1e-3 I positive definite), or say it is not. auto: yes "
                 "for --weights isotropic; no: skip")
      ->check(CLI::IsMember({"auto", "no"}))
      ->capture_default_str();
  app.add_option("--init", init,
                 "chordal: the chordal relaxation of the rotations, then the translations (needs "
                 "no vertex line; reaches the global optimum where a bad start would not); file: "
                 "the file's vertices")
      ->check(CLI::IsMember({"file", "chordal"}))
      ->capture_default_str();
  app.add_option("--max-iterations", max_iterations, "Levenberg-Marquardt steps at most")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  app.add_option("--threads", threads,
                 "Threads evaluating the edges and factorising (1 or 2; the same result)")
      ->check(CLI::Range(1, 2))
      ->capture_default_str();
  app.add_option("--ordering", ordering,
                 "Fill-reducing ordering of the sparse Cholesky's blocks: auto (CHOLMOD's "
                 "choice by fill), amd, nesdis (nested dissection), metis")
      ->check(CLI::IsMember({"auto", "amd", "nesdis", "metis"}))
      ->capture_default_str();
  if (auto exit_code = stereomap::common::parseCommandLine(app, argc, argv)) return *exit_code;

  G2oReadOptions read;
  read.information = weights == "isotropic"    ? InformationUse::kBlocks
                     : indefinite == "nearest" ? InformationUse::kNearest
                                               : InformationUse::kWhole;
  auto graph = readG2o(input, read);
  if (!graph) {
    std::fprintf(stderr, "%s\n", graph.error().message.c_str());
    return 1;
  }
  printWarnings(graph->warnings);
  if (init == "file" && !graph->has_estimates) {
    std::fprintf(stderr,
                 "%s has no vertex lines, so no estimates to start from: use --init chordal\n",
                 input.c_str());
    return 1;
  }
  GraphProblem problem(*graph, weights == "file" ? Weights::kFile : Weights::kIsotropic);
  std::printf("%s: SE(%d), %d poses, %zu edges, %d piece%s (each held by one fixed vertex)\n",
              input.c_str(), problem.dimension(), problem.size(), problem.edges().size(),
              problem.pieces(), problem.pieces() == 1 ? "" : "s");
  const auto solve_start = std::chrono::steady_clock::now();
  if (init == "chordal") {
    if (auto status = chordalInitialise(problem); !status) {
      std::fprintf(stderr, "%s\n", status.error().message.c_str());
      return 1;
    }
  }
  printCosts(init == "chordal" ? "chordal start" : "file's start", problem);
  SparseLMOptions options;
  options.max_iterations = max_iterations;
  options.threads = threads;
  options.ordering = ordering == "amd"      ? FillOrdering::kAmd
                     : ordering == "nesdis" ? FillOrdering::kNestedDissection
                     : ordering == "metis"  ? FillOrdering::kMetis
                                            : FillOrdering::kAuto;
  const SparseLMSummary summary = solveSparseLM(problem, options);
  const double solve_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - solve_start).count();
  std::printf(
      "solved: %d iterations, %s; %.3f s (factorising %.3f s, evaluating %.3f s), "
      "%ld nonzeros in the factor\n",
      summary.iterations, summary.termination.c_str(), solve_seconds, summary.factorise_seconds,
      summary.evaluate_seconds, summary.factor_nonzeros);
  printCosts("solved", problem);
  if (weights == "isotropic" && certify == "auto" && !summary.converged) {
    std::printf("not certified: the solver did not converge (%s)\n", summary.termination.c_str());
  } else if (weights == "isotropic" && certify == "auto") {
    const Certificate certificate = certifyOptimum(problem);
    if (certificate.global) {
      std::printf(
          "certified: the global optimum of SE-Sync's f (S + %g I is positive definite; "
          "%.3f s)\n",
          certificate.eta, certificate.seconds);
    } else {
      std::printf("not certified: %s (%.3f s)\n", certificate.why_not.c_str(), certificate.seconds);
    }
  }
  if (!output.empty()) {
    if (auto written = writeG2o(output, problem.solved(*graph)); !written) {
      std::fprintf(stderr, "%s\n", written.error().message.c_str());
      return 1;
    }
    std::printf("wrote %s\n", output.c_str());
  }
  std::printf("posegraph %s: %d poses, %zu edges, SE-Sync f %.9g, g2o chi2 %.9g, %.3f s\n",
              input.c_str(), problem.size(), problem.edges().size(), problem.seSyncF(),
              problem.g2oChi2(), solve_seconds);
  return summary.converged ? 0 : 1;
}
