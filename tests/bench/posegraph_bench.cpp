// stereomap-bench-posegraph: the pose-graph paper's simulated ground test (1000 trials, a
// 400 mm vehicle with 4 markers, 3 mm noise, 4 segments), the linear chained solution and the
// optimised graph side by side with the paper's figures, and its noise sweep (Fig. 8). The
// set-up is in onboard/posegraph/ground_test.hpp; the figures in docs/BENCHMARKS.md.
#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdio>
#include <map>

#include "common/cli.hpp"
#include "onboard/eval/metrics.hpp"
#include "onboard/eval/odometry_run.hpp"
#include "onboard/posegraph/ground_test.hpp"
#include "onboard/sim/sim_source.hpp"
#include "testing/sim_flights.hpp"

using namespace stereomap::posegraph;

namespace {

struct Summary {
  GroundTestErrors::Axes linear, optimised, one_frame;
  double loops_per_trial = 0, rejected_per_trial = 0, solve_ms = 0;
};

Summary run(const GroundTestOptions& options, int trials, unsigned seed) {
  std::mt19937 rng(seed);
  const EdgeInformation information = calibrateEdges(options, rng);
  Summary summary;
  for (int trial = 0; trial < trials; ++trial) {
    const auto errors = runGroundTrial(options, information, rng);
    summary.linear.append(errors.linear);
    summary.optimised.append(errors.optimised);
    summary.one_frame.append(oneFrameErrors(options, rng));
    summary.loops_per_trial += errors.loop_edges / static_cast<double>(trials);
    summary.rejected_per_trial += errors.rejected_edges / static_cast<double>(trials);
    summary.solve_ms += errors.solve_ms / trials;
  }
  return summary;
}

// The product's graph: the sim's looping flight (3 loops, image noise), odometry alone and
// with loop closures.
void flight(uint32_t seed, uint64_t frames) {
  using namespace stereomap;
  auto options = testing::noisyFlight(seed);
  options.max_frames = frames;
  sim::SimSource source(options);
  const auto run = eval::runOdometryWithGraph(source, {});
  const auto before = eval::absoluteError(run.truth, run.estimate, eval::Alignment::kSe3);
  const auto after = eval::absoluteError(run.truth, run.optimised, eval::Alignment::kSe3);
  double path = 0;
  for (size_t i = 1; i < run.truth.size(); ++i) {
    path += (run.truth[i].pose.translation - run.truth[i - 1].pose.translation).norm();
  }
  auto end = [&](const common::Trajectory& t) {
    return (t.back().pose.translation - run.truth.back().pose.translation).norm();
  };
  std::printf(
      "  seed %u: %.1f m, %d keyframes, %d loop closures; ATE %.4f -> %.4f m (%.0f %%); "
      "end %.4f -> %.4f m (%.3f %% of the path); longest solve %.1f ms; odometry %.1f "
      "ms/frame\n",
      seed, path, run.keyframes, run.loops, before.translation.rmse, after.translation.rmse,
      100 * after.translation.rmse / before.translation.rmse, end(run.estimate), end(run.optimised),
      100 * end(run.optimised) / path, run.solve_ms_max, run.medianMilliseconds());
  std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-bench-posegraph: the pose-graph paper's simulated ground test"};
  GroundTestOptions options;
  int trials = 1000, sweep_trials = 200;
  unsigned seed = 1;
  int flight_seeds = 2;
  std::string method = "ls";
  app.add_option("--trials", trials, "Trials at the paper's noise")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  app.add_option("--sweep-trials", sweep_trials,
                 "Trials per noise level of the sweep (0: no sweep)")
      ->check(CLI::Range(0, 100000))
      ->capture_default_str();
  app.add_option("--noise-mm", options.noise_mm, "Marker noise, mm at 3 sigma per axis")
      ->check(CLI::Range(0.0, 50.0))
      ->capture_default_str();
  app.add_option("--frames", options.frames, "Frames per trial (one period out and back)")
      ->check(CLI::Range(40, 5000))
      ->capture_default_str();
  app.add_option("--method", method,
                 "Pose from markers: ls (least squares), vc (the paper's vector-cross) or body "
                 "(eqs. 2-9 frames)")
      ->check(CLI::IsMember({"ls", "vc", "body"}))
      ->capture_default_str();
  app.add_flag("!--first-frame-model", options.track_model,
               "Take the markers' layout from a track's first frame, not from all its frames");
  app.add_flag("!--no-align", options.align,
               "Errors against the truth as solved (the gauge frame's noise in every pose)");
  app.add_option("--seed", seed, "Random seed")->capture_default_str();
  app.add_option("--flight-seeds", flight_seeds,
                 "Sim loop flights (3 loops each, about 40 s apiece) with the product's graph")
      ->check(CLI::Range(0, 20))
      ->capture_default_str();
  if (auto exit_code = stereomap::common::parseCommandLine(app, argc, argv)) return *exit_code;
  options.method = method == "vc"     ? MarkerMethod::kVectorCross
                   : method == "body" ? MarkerMethod::kBodyFrames
                                      : MarkerMethod::kLeastSquares;

  std::printf(
      "%d trials, %d frames each, %d segments (gaps of %d frames), noise %.1f mm (3 sigma), method "
      "%s\n",
      trials, options.frames, options.segments, options.gap, options.noise_mm, method.c_str());
  const auto start = std::chrono::steady_clock::now();
  const Summary main_run = run(options, trials, seed);
  const auto& L = main_run.linear;
  const auto& O = main_run.optimised;
  std::printf("%-22s %14s %14s %14s %14s\n", "3 sigma", "deg, per axis", "mm, per axis",
              "deg, norm", "mm, norm");
  std::printf("%-22s %14.2f %14.2f %14.2f %14.2f\n", "linear (chained)", L.degPerAxis(),
              L.mmPerAxis(), threeSigma(L.deg_norm), threeSigma(L.mm_norm));
  std::printf("%-22s %14.2f %14.2f %14.2f %14.2f\n", "optimised graph", O.degPerAxis(),
              O.mmPerAxis(), threeSigma(O.deg_norm), threeSigma(O.mm_norm));
  const auto& B = main_run.one_frame;
  std::printf("%-22s %14.2f %14.2f %14.2f %14.2f\n", "one frame (the bound)", B.degPerAxis(),
              B.mmPerAxis(), threeSigma(B.deg_norm), threeSigma(B.mm_norm));
  std::printf("%-22s %14.2f %14.2f\n", "paper, linear", 4.0, 6.0);
  std::printf("%-22s %14.2f %14.2f\n", "paper, optimised", 0.5, 3.0);
  std::printf(
      "loop closures %.1f per trial (%.2f set aside), solve %.1f ms per trial, %.1f s in all\n",
      main_run.loops_per_trial, main_run.rejected_per_trial, main_run.solve_ms,
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());

  if (sweep_trials > 0) {
    std::printf(
        "noise sweep (%d trials each, per axis): noise mm -> linear deg / mm, optimised deg / "
        "mm\n",
        sweep_trials);
    for (const double noise : {0.0, 1.0, 2.0, 3.0, 4.0, 5.0}) {
      GroundTestOptions swept = options;
      swept.noise_mm = noise;
      const Summary s = run(swept, sweep_trials, seed + 1);
      std::printf("  %.1f -> %.2f / %.2f, %.2f / %.2f (one frame %.2f / %.2f)\n", noise,
                  s.linear.degPerAxis(), s.linear.mmPerAxis(), s.optimised.degPerAxis(),
                  s.optimised.mmPerAxis(), s.one_frame.degPerAxis(), s.one_frame.mmPerAxis());
    }
  }
  if (flight_seeds > 0) {
    std::printf(
        "sim loop flight, 3 loops with image noise (sigma 2) and blur: odometry -> graph\n");
    for (int s = 1; s <= flight_seeds; ++s) flight(static_cast<uint32_t>(s), 1200);
  }
  // The paper's figures read as per-axis 3 sigma (its attitude is three angles).
  std::printf("pose-graph 3 sigma: linear %.2f deg / %.2f mm, optimised %.2f deg / %.2f mm\n",
              L.degPerAxis(), L.mmPerAxis(), O.degPerAxis(), O.mmPerAxis());
  return 0;
}
