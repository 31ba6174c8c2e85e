// stereomap-bench-map: how right the map is under each simulated camera (issue 16). Flies the
// scripted flight through sim rooms 1-3 with the camera presets clean, typical and poor, makes
// the clouds as the vehicle does, fuses them at 0.05 m on the true poses, and scores the map
// against the rooms' geometry (the same definitions as fusion_accuracy_test).
//   stereomap-bench-map [--cameras clean,typical,poor] [--rooms 1,2,3] [--frames 60]
// Ends with one line per camera preset:
//   map accuracy <preset>: precision <P> recall <R> free <F>
#include <CLI/CLI.hpp>
#include <opencv2/core/utility.hpp>

#include <algorithm>
#include <cstdio>
#include <string>
#include <vector>

#include "common/cli.hpp"
#include "tests/support/sim_map_accuracy.hpp"

int main(int argc, char** argv) {
  using namespace stereomap;
  CLI::App app{"stereomap-bench-map: map accuracy on sim rooms under each camera preset"};
  std::vector<std::string> cameras = {"clean", "typical", "poor"};
  std::vector<uint32_t> rooms = {1, 2, 3};
  int frames = 60;
  double resolution = 0.05;
  std::string stereo_preset = "fast";
  app.add_option("--cameras", cameras, "Camera presets to fly")
      ->delimiter(',')
      ->check(CLI::IsMember({"clean", "typical", "poor"}))
      ->capture_default_str();
  app.add_option("--rooms", rooms, "Sim rooms (seeds)")
      ->delimiter(',')
      ->check(CLI::Range(1u, 1000000u))
      ->capture_default_str();
  app.add_option("--frames", frames, "Frames of each flight (10 Hz)")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  app.add_option("--resolution", resolution, "Map resolution, metres")
      ->check(CLI::Range(0.01, 1.0))
      ->capture_default_str();
  app.add_option("--stereo", stereo_preset, "Matcher preset: fast (the vehicle's) or accurate")
      ->check(CLI::IsMember({"fast", "accurate"}))
      ->capture_default_str();
  std::string handling = "auto";
  app.add_option("--noise-handling", handling,
                 "Depth step: auto (by the image noise, the vehicle's default), off (always the "
                 "clean way) or on (always the noisy way)")
      ->check(CLI::IsMember({"auto", "off", "on"}))
      ->capture_default_str();
  // Knobs for ablations and trials: each replaces the product's default when given.
  double smooth = -1, max_range = -1, span = -1, hit = -1, miss = -1, occupied = -1;
  int block = -1, downscale = -1, row_groups = -1, uniqueness = -1, block_rows = -1,
      disparities = -1;
  app.add_option("--disparities", disparities,
                 "Matcher: width of the disparity search (multiple of 16)")
      ->check(CLI::Range(16, 256) & CLI::Validator(
                                        [](std::string& v) {
                                          return std::stoi(v) % 16 == 0
                                                     ? std::string()
                                                     : std::string("must be a multiple of 16");
                                        },
                                        "MULTIPLE OF 16"));
  app.add_option("--block-rows", block_rows, "Cloud: image rows of a point's block")
      ->check(CLI::Range(1, 16));
  app.add_option("--uniqueness", uniqueness, "Noisy images: the matcher's uniqueness ratio, %")
      ->check(CLI::Range(0, 100));
  app.add_option("--row-groups", row_groups, "Noisy images: match rows averaged in groups of N")
      ->check(CLI::Range(1, 8));
  app.add_option("--downscale", downscale, "Matcher: match at 1/N resolution")
      ->check(CLI::Range(1, 8));
  app.add_option("--smooth", smooth,
                 "Noisy images: the matcher's Gaussian smoothing at every level, px")
      ->check(CLI::Range(0.0, 10.0));
  app.add_option("--block", block, "Noisy images: the matcher's block size at every level (odd)")
      ->check(CLI::Range(5, 255) & CLI::Validator(
                                       [](std::string& v) {
                                         return std::stoi(v) % 2 == 1 ? std::string()
                                                                      : std::string("must be odd");
                                       },
                                       "ODD"));
  app.add_option("--max-range", max_range, "Cloud: depth limit, m")->check(CLI::Range(0.5, 100.0));
  double min_range = -1;
  app.add_option("--min-range", min_range, "Cloud: nearest depth, m")
      ->check(CLI::Range(0.05, 100.0));
  app.add_option("--span", span, "Cloud: largest disparity span of a block, px")
      ->check(CLI::Range(0.0, 100.0));
  app.add_option("--hit", hit, "Map: hit probability")->check(CLI::Range(0.5, 1.0));
  app.add_option("--miss", miss, "Map: miss probability")->check(CLI::Range(0.0, 0.5));
  app.add_option("--occupied", occupied, "Map: occupancy threshold")->check(CLI::Range(0.0, 1.0));
  double noise = -1, shot = -1, defocus = -1, exposure = -1, right_gain = -1, vignetting = -1,
         gamma = -1;
  app.add_option("--noise", noise, "Camera: read noise, grey levels")->check(CLI::Range(0.0, 50.0));
  app.add_option("--shot", shot, "Camera: shot noise, variance per grey level")
      ->check(CLI::Range(0.0, 10.0));
  app.add_option("--defocus", defocus, "Camera: defocus, px")->check(CLI::Range(0.0, 10.0));
  app.add_option("--exposure", exposure, "Camera: exposure, s (motion blur)")
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--right-gain", right_gain, "Camera: the right camera's gain")
      ->check(CLI::Range(0.1, 10.0));
  app.add_option("--vignetting", vignetting, "Camera: vignetting")->check(CLI::Range(0.0, 0.9));
  app.add_option("--gamma", gamma, "Camera: gamma")->check(CLI::Range(0.1, 10.0));
  int temporal_min = -1, temporal_max = -1;
  double gate = -1, interior = -1;
  app.add_option("--temporal", temporal_min,
                 "Noisy images: frames to confirm a block (0: no averaging over frames)")
      ->check(CLI::Range(0, 100));
  app.add_option("--temporal-max", temporal_max, "Noisy images: frames averaged at most")
      ->check(CLI::Range(1, 1000));
  app.add_option("--gate", gate, "Noisy images: agreement over frames, px")
      ->check(CLI::Range(0.01, 100.0));
  app.add_option("--interior", interior,
                 "Noisy images: unconfirmed blocks inside a surface this smooth pass, px (0: none)")
      ->check(CLI::Range(0.0, 100.0));
  if (auto exit_code = stereomap::common::parseCommandLine(app, argc, argv)) return *exit_code;
  if (temporal_max > 0 && temporal_max < std::max(temporal_min, 2)) {
    std::fprintf(stderr, "--temporal-max must be at least --temporal (default 2)\n");
    return 2;
  }
  cv::setNumThreads(1);  // the depth step's time on one core, as the vehicle budgets it

  struct Total {
    double precision = 0, recall = 0, free_space = 0;
  };
  std::vector<std::pair<std::string, Total>> totals;
  std::printf(
      "| camera | room | precision | recall | free | within 1 / 2 voxels | occupied voxels | "
      "depth ms | image noise (handling) |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|\n");
  for (const auto& name : cameras) {
    Total total;
    for (const uint32_t room : rooms) {
      testing::SimMapSetup setup;
      setup.room = room;
      setup.frames = frames;
      setup.camera = *sim::CameraModel::preset(name);
      stereo::DepthOptions& depth = setup.depth;
      depth.matcher = stereo_preset == "accurate" ? stereo::MatcherOptions::accurate()
                                                  : stereo::MatcherOptions::fast();
      depth.noise = handling == "off"  ? stereo::NoiseHandling::kOff
                    : handling == "on" ? stereo::NoiseHandling::kOn
                                       : stereo::NoiseHandling::kAuto;
      setup.map = fusion::OccupancyMap::Options::octomapPreset(resolution);
      auto& temporal = depth.temporal;
      if (temporal_min == 0) temporal.reset();
      if (temporal && temporal_min > 0) temporal->min_frames = temporal_min;
      if (temporal && temporal_max > 0) temporal->max_frames = temporal_max;
      if (temporal && gate > 0) temporal->gate_px = gate;

      if (noise >= 0) setup.camera.noise_sigma = noise;
      if (shot >= 0) setup.camera.shot_noise = shot;
      if (defocus >= 0) setup.camera.blur_sigma = defocus;
      if (exposure >= 0) setup.camera.exposure_s = exposure;
      if (right_gain > 0) setup.camera.right_gain = right_gain;
      if (vignetting >= 0) setup.camera.vignetting = vignetting;
      if (gamma > 0) setup.camera.gamma = gamma;
      for (auto& level : depth.levels) {
        if (smooth >= 0) level.smooth_sigma_px = smooth;
        if (block > 0) level.block_size = block;
        if (interior >= 0) level.interior_px = interior;
        if (row_groups > 0) level.row_groups = row_groups;
        if (uniqueness >= 0) level.uniqueness_ratio = uniqueness;
      }
      if (downscale > 0) depth.matcher.downscale = downscale;
      if (block_rows > 0) depth.cloud.block_rows = block_rows;
      // As the vehicle's flags: a disparity count given searches one window from the range
      // (given, or the rig's rule), a range given moves the rig's far limit.
      if (disparities > 0) {
        depth.matcher.num_disparities = disparities;
        depth.range.reset();
      }
      if (max_range > 0) {
        depth.cloud.max_range_m = max_range;
        if (depth.range) depth.range->far_m = max_range;
      }
      if (min_range > 0) depth.cloud.min_range_m = min_range;
      if (span >= 0) depth.cloud.max_block_span_px = span;
      if (hit > 0) setup.map.prob_hit = hit;
      if (miss > 0) setup.map.prob_miss = miss;
      if (occupied > 0) setup.map.occupancy_threshold = occupied;
      const auto a = testing::measureSimMap(setup);
      std::printf("| %s | %u | %.4f | %.4f | %.4f | %.4f / %.4f | %zu | %.2f | %.2f (%s) |\n",
                  name.c_str(), room, a.precision, a.recall, a.free_space, a.precision_1,
                  a.precision_2, a.occupied, a.depth_ms, a.noise_sigma,
                  a.level < 0 ? "clean" : ("level " + std::to_string(a.level)).c_str());
      std::fflush(stdout);
      total.precision += a.precision / rooms.size();
      total.recall += a.recall / rooms.size();
      total.free_space += a.free_space / rooms.size();
    }
    totals.emplace_back(name, total);
  }
  std::printf("\n");
  for (const auto& [name, t] : totals) {
    std::printf("map accuracy %s: precision %.3f recall %.3f free %.3f\n", name.c_str(),
                t.precision, t.recall, t.free_space);
  }
  return 0;
}
