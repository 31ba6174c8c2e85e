// stereomap-bench-g2o: the field's standard pose graphs (../shared/data/posegraph) solved by
// stereomap's optimiser and, side by side in the same run, by the configuration of Ceres' own
// `pose_graph_3d` example (autodiff error term, quaternion manifold, SPARSE_NORMAL_CHOLESKY, the
// first pose fixed, 200 iterations at most, started from the file's vertices; written here from
// its description, not copied). Figures for docs/BENCHMARKS.md (issue 41):
// - isotropic weights: SE-Sync's f against the certified optimum f* of the README;
// - the file's weights: the cost 1/2 sum e^T Omega e (Ceres' error) of both solutions, and the
//   time of both, alternating, repeated.
#include <ceres/ceres.h>
#include <CLI/CLI.hpp>

#include <Eigen/Cholesky>
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <map>

#include "common/cli.hpp"
#include "onboard/posegraph/certificate.hpp"
#include "onboard/posegraph/chordal.hpp"
#include "onboard/posegraph/g2o.hpp"
#include "onboard/posegraph/graph_problem.hpp"
#include "onboard/posegraph/sparse_lm.hpp"

using namespace stereomap::posegraph;

namespace {

using Clock = std::chrono::steady_clock;

double secondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

// The example's error term: [R_a^T (p_b - p_a) - p_ab ; 2 vec(q_ab q_est^-1)], multiplied by
// the lower Cholesky factor L of the information, as the example does.
struct ExampleError {
  ExampleError(const G2oEdge& edge)
      : q_ab(edge.T_from_to.rotation),
        p_ab(edge.T_from_to.translation),
        sqrt_information(Eigen::LLT<Mat6>(edge.information).matrixL()) {}

  template <typename T>
  bool operator()(const T* p_a_ptr, const T* q_a_ptr, const T* p_b_ptr, const T* q_b_ptr,
                  T* residual_ptr) const {
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> p_a(p_a_ptr), p_b(p_b_ptr);
    const Eigen::Map<const Eigen::Quaternion<T>> q_a(q_a_ptr), q_b(q_b_ptr);
    const Eigen::Quaternion<T> q_a_inverse = q_a.conjugate();
    const Eigen::Quaternion<T> q_estimated = q_a_inverse * q_b;
    const Eigen::Matrix<T, 3, 1> p_estimated = q_a_inverse * (p_b - p_a);
    const Eigen::Quaternion<T> delta = q_ab.template cast<T>() * q_estimated.conjugate();
    Eigen::Map<Eigen::Matrix<T, 6, 1>> residual(residual_ptr);
    residual.template head<3>() = p_estimated - p_ab.template cast<T>();
    residual.template tail<3>() = T(2.0) * delta.vec();
    residual.applyOnTheLeft(sqrt_information.template cast<T>());
    return true;
  }

  Eigen::Quaterniond q_ab;
  Eigen::Vector3d p_ab;
  Mat6 sqrt_information;
};

struct ExampleRun {
  double seconds = 0, cost = 0;  // the example's own report (whitened by L)
  int iterations = 0;
  G2oGraph solved;
};

ExampleRun runExample(const G2oGraph& graph) {
  ExampleRun run;
  const auto start = Clock::now();
  // Poses in a map by id, as the example keeps them; the first is fixed.
  struct Pose {
    Eigen::Vector3d p;
    Eigen::Quaterniond q;
  };
  std::map<int64_t, Pose> poses;
  for (const auto& vertex : graph.vertices) {
    poses[vertex.id] = {vertex.T_world_vertex.translation, vertex.T_world_vertex.rotation};
  }
  ceres::Problem problem;
  ceres::Manifold* quaternion_manifold = new ceres::EigenQuaternionManifold;
  for (const auto& edge : graph.edges) {
    Pose& a = poses.at(edge.from);
    Pose& b = poses.at(edge.to);
    problem.AddResidualBlock(
        new ceres::AutoDiffCostFunction<ExampleError, 6, 3, 4, 3, 4>(new ExampleError(edge)),
        nullptr, a.p.data(), a.q.coeffs().data(), b.p.data(), b.q.coeffs().data());
    problem.SetManifold(a.q.coeffs().data(), quaternion_manifold);
    problem.SetManifold(b.q.coeffs().data(), quaternion_manifold);
  }
  problem.SetParameterBlockConstant(poses.begin()->second.p.data());
  problem.SetParameterBlockConstant(poses.begin()->second.q.coeffs().data());
  ceres::Solver::Options options;
  options.max_num_iterations = 200;
  options.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem, &summary);
  run.seconds = secondsSince(start);
  run.cost = summary.final_cost;
  run.iterations = static_cast<int>(summary.iterations.size());
  run.solved = graph;
  for (auto& vertex : run.solved.vertices) {
    const Pose& pose = poses.at(vertex.id);
    vertex.T_world_vertex = {pose.q.normalized(), pose.p};
  }
  return run;
}

struct OursRun {
  double seconds = 0;
  int iterations = 0;
  double ceres_half_sum = 0, se_sync_f = 0;
  bool certified = false;  // kIsotropic: SE-Sync's certificate of the global optimum
};

OursRun runOurs(const G2oGraph& graph, Weights weights) {
  OursRun run;
  const auto start = Clock::now();
  GraphProblem problem(graph, weights);
  if (!chordalInitialise(problem)) std::fprintf(stderr, "chordal initialisation failed\n");
  const SparseLMSummary summary = solveSparseLM(problem);
  run.seconds = secondsSince(start);
  run.iterations = summary.iterations;
  run.ceres_half_sum = problem.ceresHalfSum();
  run.se_sync_f = problem.seSyncF();
  if (weights == Weights::kIsotropic) run.certified = certifyOptimum(problem).global;
  return run;
}

double median(std::vector<double> values) {
  std::sort(values.begin(), values.end());
  return values[values.size() / 2];
}

// SE-Sync's certified optima as the README prints them (and the rounding of that print).
const std::map<std::string, std::pair<double, double>> kOptima = {
    {"parking-garage", {1.263, 0.0005}},
    {"sphere2500", {1687, 0.5}},
    {"intel", {52.35, 0.005}},
    {"smallGrid3D", {1025.398, 0.0005}},
    {"cubicle", {717.1, 0.05}}};  // SE-Sync's paper, table 2

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "stereomap-bench-g2o: the standard pose graphs solved by stereomap-posegraph's "
      "optimiser and by Ceres' pose_graph_3d example's configuration, side by side"};
  std::string dir = std::string(STEREOMAP_DATA_DIR) + "/posegraph";
  std::vector<std::string> files;
  int repeat = 3;
  app.add_option("--dir", dir, "Folder of g2o graphs")->capture_default_str();
  app.add_option("graphs", files, "Graphs to run (default: every .g2o file in --dir)");
  app.add_option("--repeat", repeat, "Timed runs of each solver, alternating")
      ->check(CLI::Range(1, 50))
      ->capture_default_str();
  if (auto exit_code = stereomap::common::parseCommandLine(app, argc, argv)) return *exit_code;
  if (files.empty()) {
    std::error_code error;
    for (const auto& entry : std::filesystem::directory_iterator(dir, error)) {
      if (entry.path().extension() == ".g2o") files.push_back(entry.path().string());
    }
    std::sort(files.begin(), files.end());
    if (files.empty()) {
      std::fprintf(stderr, "no .g2o file in %s\n", dir.c_str());
      return 1;
    }
  }
  std::printf(
      "| graph | poses | SE-Sync f (isotropic) | f* (published) | certified | time | file "
      "weights: cost ours | cost Ceres' example (its own report) | time ours | time example | "
      "example / ours |\n|---|---|---|---|---|---|---|---|---|---|---|\n");
  for (const auto& file : files) {
    // SE-Sync's weights use only each edge's blocks: a graph with indefinite edges is read.
    auto graph = readG2o(file, {InformationUse::kBlocks});
    if (!graph) {
      std::fprintf(stderr, "%s\n", graph.error().message.c_str());
      return 1;
    }
    const std::string name = std::filesystem::path(file).stem().string();
    const OursRun isotropic = runOurs(*graph, Weights::kIsotropic);
    const bool indefinite = std::any_of(graph->edges.begin(), graph->edges.end(),
                                        [](const G2oEdge& edge) { return edge.indefinite; });
    std::string reference = "-";
    if (auto it = kOptima.find(name); it != kOptima.end()) {
      char text[64];
      std::snprintf(text, sizeof(text), "%.10g (±%.1g)", it->second.first, it->second.second);
      reference = text;
    }
    std::string file_columns = "(2D: no Ceres 3D example) | | | | |";
    if (indefinite)
      file_columns = "(indefinite information: the file's weights refuse it) | | | | |";
    if (graph->dimension == 3 && graph->has_estimates && !indefinite) {
      std::vector<double> ours_seconds, example_seconds;
      OursRun ours;
      ExampleRun example;
      for (int r = 0; r < repeat; ++r) {
        ours = runOurs(*graph, Weights::kFile);
        example = runExample(*graph);
        ours_seconds.push_back(ours.seconds);
        example_seconds.push_back(example.seconds);
      }
      const double example_cost = GraphProblem(example.solved, Weights::kFile).ceresHalfSum();
      std::vector<double> ratios;
      for (int r = 0; r < repeat; ++r) ratios.push_back(example_seconds[r] / ours_seconds[r]);
      char text[400];
      std::snprintf(text, sizeof(text),
                    "%.9g (%d it) | %.9g (%.9g; %d it) | %.3f s | %.3f s | %.1fx (%.1f-%.1fx) |",
                    ours.ceres_half_sum, ours.iterations, example_cost, example.cost,
                    example.iterations, median(ours_seconds), median(example_seconds),
                    median(ratios), *std::min_element(ratios.begin(), ratios.end()),
                    *std::max_element(ratios.begin(), ratios.end()));
      file_columns = text;
    }
    std::printf("| %s | %d | %.9g | %s | %s | %.3f s | %s\n", name.c_str(),
                static_cast<int>(graph->vertices.size()), isotropic.se_sync_f, reference.c_str(),
                isotropic.certified ? "yes" : "**no**", isotropic.seconds, file_columns.c_str());
    std::fflush(stdout);
  }
  return 0;
}
