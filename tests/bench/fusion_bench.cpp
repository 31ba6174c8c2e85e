// stereomap-bench-fusion: our fast insertion against OctoMap's insertPointCloud on the same
// clouds, in one run. The headline case is the issue's: 50k points in a 65x50 degree view
// at 2-10 m, 0.05 m voxels, 10 m rays, each insertion into an empty map. Also a simulated
// 640x480 frame (fusion time per frame) and the TUM RGB-D desk frames when available.
//   stereomap-bench-fusion [--runs N] [--stock-runs N]
#include <CLI/CLI.hpp>
#include <opencv2/imgcodecs.hpp>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <functional>
#include <random>
#include <sstream>

#include "common/cli.hpp"
#include "onboard/sim/flight.hpp"
#include "onboard/sim/renderer.hpp"
#include "onboard/stereo/depth.hpp"
#include "server/fusion/occupancy_map.hpp"
#include "testing/tum.hpp"
#include "tests/bench/bench_support.hpp"

namespace {

using namespace stereomap;
using bench::compareInsertion;
using bench::Frame;
using bench::frustumFrame;
using common::Vec3;

Frame simFrame() {
  const sim::Scene scene = sim::Scene::makeRoom({.seed = 1});
  const camera::StereoCamera camera;
  const sim::Renderer renderer(scene, camera);
  const auto pose = sim::Flight().T_map_camera(5.0);
  const auto stereo_frame = renderer.render(pose);
  const stereo::StereoMatcher matcher;
  return {stereo::cloudFromDisparity(matcher.compute(stereo_frame.left, stereo_frame.right),
                                     stereo_frame.left, camera),
          pose};
}

std::vector<Frame> tumFrames(const std::string& dir, size_t count) {
  std::vector<Frame> frames;
  for (auto& f : testing::tumDepthFrames(dir, count)) {
    frames.push_back({std::move(f.cloud), f.T_map_camera});
  }
  return frames;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-bench-fusion: fast insertion vs OctoMap's insertPointCloud"};
  int runs = 10, stock_runs = 3;
  std::string tum = std::string(STEREOMAP_DATA_DIR) + "/tum_rgbd_fr1";
  app.add_option("--runs", runs, "Timed runs of ours per case")->check(CLI::Range(1, 1000));
  app.add_option("--stock-runs", stock_runs, "Timed runs of OctoMap per case")
      ->check(CLI::Range(1, 100));
  app.add_option("--tum", tum, "TUM RGB-D folder (skipped when absent)");
  if (auto exit_code = stereomap::common::parseCommandLine(app, argc, argv)) return *exit_code;

  std::printf(
      "| case | points | OctoMap insertPointCloud | ours, 1 thread | ours, 2 threads | "
      "speedup (2 threads) | agreement |\n|---|---|---|---|---|---|---|\n");
  auto row = [&](const char* name, const std::vector<Frame>& frames, double resolution,
                 double max_range) {
    size_t points = 0;
    for (const auto& f : frames) points += f.cloud.size();
    const auto one = compareInsertion(frames, resolution, max_range, runs, stock_runs, 1);
    const auto two = compareInsertion(frames, resolution, max_range, runs, 1, 2);
    std::printf("| %s | %zu | %.1f ms | %.1f ms | %.1f ms (%.2f M points/s) | %.1fx | %.3f%% |\n",
                name, points, one.stock_ms, one.fast_ms, two.fast_ms, points / two.fast_ms / 1000.0,
                one.stock_ms / two.fast_ms, 100 * two.agreement);
    return std::pair{one.stock_ms / two.fast_ms, two.agreement};
  };
  const auto headline =
      row("50k points, 65x50 deg, 2-10 m, 0.05 m, 10 m rays", {frustumFrame()}, 0.05, 10.0);
  row("sim 640x480 frame (fast stereo), 0.05 m, 6 m rays", {simFrame()}, 0.05, 6.0);
  row("sim 640x480 frame (fast stereo), 0.1 m, 6 m rays", {simFrame()}, 0.1, 6.0);
  const auto desk = tumFrames(tum, 10);
  if (!desk.empty()) row("TUM fr1 desk, 10 frames (every 4th pixel), 0.05 m", desk, 0.05, -1.0);
  std::printf("\nfusion speedup vs octomap insertPointCloud: %.1fx, agreement: %.3f%%\n",
              headline.first, 100 * headline.second);
  return 0;
}
