// stereomap-bench-vo: the visual odometry's figures for docs/BENCHMARKS.md, fast and paper
// modes side by side on the same data: KITTI 01 frames 0-50 (rotation drift, Sim3 ATE),
// sim flights with image noise and blur (ATE, attitude), the static EuRoC clip (motion), and
// time per frame on one core (median).
#include <CLI/CLI.hpp>
#include <opencv2/core/utility.hpp>

#include <cstdio>
#include <filesystem>

#include "onboard/camera/dataset_source.hpp"
#include "onboard/eval/metrics.hpp"
#include "onboard/eval/odometry_run.hpp"
#include "onboard/sim/sim_source.hpp"

using namespace stereomap;

namespace {

const char* name(odometry::VoMode mode) { return mode == odometry::VoMode::kFast ? "fast" : "paper"; }

void row(const char* data, odometry::VoMode mode, const eval::OdometryRun& run,
         const std::vector<double>& lengths) {
  const auto drift = eval::kittiDrift(run.truth, run.estimate, lengths);
  const auto sim3 = eval::absoluteError(run.truth, run.estimate, eval::Alignment::kSim3);
  const auto se3 = eval::absoluteError(run.truth, run.estimate, eval::Alignment::kSe3);
  const double path = eval::pathLength(run.truth);
  double moved = 0;
  for (const auto& p : run.estimate) {
    moved = std::max(moved, (p.pose.translation - run.estimate.front().pose.translation).norm());
  }
  std::printf("| %s | %s | %zu | %d | %.2f %% / %.2f | %.3f m (scale %.3f) | %.3f m (%.2f %% of %.1f m) | %.3f | %.4f | %.1f |\n",
              data, name(mode), run.estimate.size(), run.lost,
              drift.empty() ? 0.0 : drift.back().translation_percent,
              drift.empty() ? 0.0 : drift.back().rotation_deg_per_100m, sim3.translation.rmse,
              sim3.alignment.scale, se3.translation.rmse, path > 0 ? 100 * se3.translation.rmse / path : 0.0,
              path, se3.rotation.rmse, moved, run.medianMilliseconds());
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-bench-vo: visual odometry figures, fast and paper modes"};
  std::string data = STEREOMAP_DATA_DIR;
  app.add_option("--data", data, "The shared data folder")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  cv::setNumThreads(0);  // one core, as on the vehicle's budget
  std::printf("| data | mode | frames | lost | drift: translation / rotation (deg/100 m) | ATE Sim3 | ATE SE3 | attitude RMS (deg) | largest motion (m) | ms/frame (median) |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|\n");
  for (const auto mode : {odometry::VoMode::kFast, odometry::VoMode::kPaper}) {
    const auto kitti = std::filesystem::path(data) / "kitti_stereo_seq2";
    if (std::filesystem::exists(kitti)) {
      auto source = camera::openDatasetSource("kitti:" + kitti.string(), {});
      if (source) row("KITTI 01 0-50 (20 m segments)", mode, eval::runOdometry(**source, {.mode = mode}), {20});
    }
    for (uint32_t seed : {1u, 2u, 3u}) {
      sim::SimSourceOptions options{.seed = seed, .rate_hz = 10.0, .max_frames = 300};
      options.render.noise_sigma = 2.0;
      options.render.blur_sigma = 1.0;
      sim::SimSource source(options);
      const std::string label = "sim room " + std::to_string(seed) + ", noise 2, blur 1 (5 m segments)";
      row(label.c_str(), mode, eval::runOdometry(source, {.mode = mode}), {5});
    }
    const auto euroc = std::filesystem::path(data) / "euroc_v101_micro";
    if (std::filesystem::exists(euroc)) {
      auto source = camera::openDatasetSource("euroc:" + euroc.string(), {});
      if (source) row("EuRoC V1_01 static clip", mode, eval::runOdometry(**source, {.mode = mode}), {});
    }
  }
  return 0;
}
