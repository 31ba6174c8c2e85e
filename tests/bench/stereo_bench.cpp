// stereomap-bench-stereo: dense depth accuracy and speed, ours against stock OpenCV, side by
// side in one run. Accuracy: the Middlebury pairs in ../shared/data/middlebury (bad-pixel
// rate > 1 px and density over GT-known, non-occluded pixels, as the data set's README).
// Speed: rectify + disparity + cloud for a 640x480 pair on one core, median of N runs.
//   stereomap-bench-stereo [--data DIR] [--runs N]
#include <CLI/CLI.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/utility.hpp>

#include <chrono>
#include <cstdio>
#include <functional>

#include "common/cli.hpp"
#include "onboard/camera/rectifier.hpp"
#include "onboard/sim/flight.hpp"
#include "onboard/sim/renderer.hpp"
#include "onboard/sim/sim_source.hpp"
#include "onboard/stereo/depth.hpp"
#include "onboard/stereo/depth_step.hpp"
#include "onboard/stereo/disparity_io.hpp"
#include "tests/support/timing.hpp"

namespace {

using namespace stereomap;
using testing::medianMs;

// Stock OpenCV StereoSGBM as the Middlebury README measures it (mode HH, block 5,
// P1 = 8*25, P2 = 32*25, everything else default).
cv::Mat stockSgbm(const cv::Mat& left, const cv::Mat& right, int num_disparities) {
  auto sgbm = cv::StereoSGBM::create(0, num_disparities, 5, 8 * 25, 32 * 25, 0, 0, 0, 0, 0,
                                     cv::StereoSGBM::MODE_HH);
  cv::Mat fixed_point, disparity;
  sgbm->compute(left, right, fixed_point);
  fixed_point.convertTo(disparity, CV_32F, 1.0 / 16);
  disparity.setTo(-1.0f, fixed_point < 0);
  return disparity;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-bench-stereo: stereo accuracy (Middlebury) and speed (640x480)"};
  std::string data = std::string(STEREOMAP_DATA_DIR) + "/middlebury";
  int runs = 30;
  app.add_option("--data", data, "Middlebury folder")->capture_default_str();
  app.add_option("--runs", runs, "Timed runs per configuration")->check(CLI::Range(1, 1000));
  if (auto exit_code = stereomap::common::parseCommandLine(app, argc, argv)) return *exit_code;
  cv::setNumThreads(1);  // one core, as the figures ask

  const std::vector<std::pair<std::string, stereo::MatcherOptions>> ours = {
      {"ours fast", stereo::MatcherOptions::fast()},
      {"ours accurate", stereo::MatcherOptions::accurate()}};
  // Alternatives measured for the record (accuracy only): the paper's LoG prefilter and
  // ximgproc's WLS filling, each on top of the accurate preset.
  auto variant = [](auto change) {
    auto options = stereo::MatcherOptions::accurate();
    change(options);
    return options;
  };
  auto alternatives = ours;
  // The vehicle's matcher on noisy images (its noise level 0; the Middlebury pairs read 1.0-1.7
  // grey levels, so a vehicle would match them so), with rows in pairs and as it was before.
  const stereo::DepthOptions depth;
  stereo::NoiseLevel full_rows = depth.levels[0];
  full_rows.row_groups = 1;
  full_rows.block_size = 21;
  full_rows.smooth_sigma_px = 1.5;
  full_rows.uniqueness_ratio = 15;
  alternatives.emplace_back("noisy level 0 (rows in pairs)",
                            stereo::levelMatcher(depth.matcher, depth.levels[0]));
  alternatives.emplace_back("noisy level 0, full rows (block 21, before)",
                            stereo::levelMatcher(depth.matcher, full_rows));
  alternatives.emplace_back("accurate + LoG prefilter (sigma 1)",
                            variant([](auto& o) { o.prefilter = stereo::Prefilter::kLoG; }));
  alternatives.emplace_back("accurate + WLS (lambda 8000, sigma 1.5)",
                            variant([](auto& o) { o.wls_lambda = 8000; }));

  std::printf("## Middlebury (bad > 1 px, density; GT known and non-occluded)\n\n");
  std::printf(
      "| pair | configuration | bad | density | bad among valid |\n|---|---|---|---|---|\n");
  for (const char* name : {"tsukuba", "venus", "teddy", "aloe"}) {
    auto pair = stereo::loadMiddleburyPair(std::filesystem::path(data) / name);
    if (!pair) {
      std::printf("| %s | (skipped: %s) | | | |\n", name, pair.error().message.c_str());
      continue;
    }
    const int num_disparities = stereo::disparitiesFor(pair->max_disparity);
    auto report = [&](const std::string& configuration, const cv::Mat& disparity) {
      const auto score = stereo::scoreDisparity(disparity, *pair);
      std::printf("| %s | %s | %.2f%% | %.2f%% | %.2f%% |\n", name, configuration.c_str(),
                  100 * score.bad, 100 * score.density, 100 * score.bad_among_valid);
    };
    report("stock SGBM (HH, block 5)", stockSgbm(pair->left, pair->right, num_disparities));
    for (auto [label, options] : alternatives) {
      options.num_disparities = num_disparities;
      report(label, stereo::StereoMatcher(options).compute(pair->left, pair->right));
    }
  }

  // A raw 640x480 pair: the simulated room, with a mildly distorted, slightly rotated rig
  // so that rectification does real work.
  camera::StereoCalibration calibration;
  const camera::StereoCamera paper_camera;
  calibration.image_size = {paper_camera.width, paper_camera.height};
  calibration.left.K = calibration.right.K = cv::Matx33d(paper_camera.fx, 0, paper_camera.cx, 0,
                                                         paper_camera.fy, paper_camera.cy, 0, 0, 1);
  calibration.left.distortion = (cv::Mat_<double>(1, 5) << -0.05, 0.01, 0, 0, 0);
  calibration.right.distortion = (cv::Mat_<double>(1, 5) << -0.04, 0.01, 0, 0, 0);
  cv::Rodrigues(cv::Vec3d(0.002, -0.003, 0.001), calibration.R);
  calibration.T = cv::Vec3d(-paper_camera.baseline, 0, 0);
  auto rectifier = camera::Rectifier::create(calibration);
  if (!rectifier) {
    std::fprintf(stderr, "%s\n", rectifier.error().message.c_str());
    return 1;
  }
  const sim::Scene scene = sim::Scene::makeRoom({.seed = 1});
  const sim::Renderer renderer(scene, paper_camera);
  const auto frame = renderer.render(sim::Flight().T_map_camera(5.0));

  std::printf("\n## Speed, 640x480, one core: rectify + disparity + cloud (median of %d)\n\n",
              runs);
  std::printf("| configuration | ms per frame | stock SGBM / this |\n|---|---|---|\n");
  cv::Mat left, right;
  auto timePipeline = [&](const std::function<cv::Mat(const cv::Mat&, const cv::Mat&)>& match) {
    return medianMs(runs, [&] {
      (void)rectifier->rectify(frame.left, frame.right, left, right);
      const cv::Mat disparity = match(left, right);
      const auto cloud = stereo::cloudFromDisparity(disparity, left, rectifier->camera());
      (void)cloud;
    });
  };
  const double stock_ms =
      timePipeline([](const cv::Mat& l, const cv::Mat& r) { return stockSgbm(l, r, 80); });
  std::printf("| stock SGBM (HH, block 5, 80 disparities) | %.1f | 1.00 |\n", stock_ms);
  for (const auto& [label, options] : ours) {
    const stereo::StereoMatcher matcher(options);
    const double ms =
        timePipeline([&](const cv::Mat& l, const cv::Mat& r) { return matcher.compute(l, r); });
    std::printf("| %s (%d disparities) | %.1f | %.2f |\n", label.c_str(), options.num_disparities,
                ms, stock_ms / ms);
  }

  // The vehicle's depth step (stereo::DepthStep, the fast preset) over a flight's frames in
  // order, as it runs on board: the clean path, and the noisy one (smoothing, 21 px blocks,
  // block disparities averaged along the poses) on the typical camera's frames. The handling is
  // forced here: rectifying the sim's images again interpolates away most of their noise
  // before the depth step's estimate sees it.
  std::printf(
      "\n## The vehicle's depth step, 640x480, one core: rectify + depth step (median over %d "
      "frames of a flight)\n\n",
      runs);
  std::printf("| images | ms per frame |\n|---|---|\n");
  for (const int kind : {0, 1, 2}) {
    const bool noisy = kind == 2;
    sim::SimSourceOptions flight{
        .seed = 1, .rate_hz = 10.0, .max_frames = static_cast<uint64_t>(runs)};
    flight.render.camera = noisy ? sim::CameraModel::typical() : sim::CameraModel::clean();
    sim::SimSource source(flight);
    std::vector<camera::SourceFrame> frames;
    while (auto f = source.next()) frames.push_back(std::move(*f));
    stereo::DepthOptions options;
    options.noise = noisy ? stereo::NoiseHandling::kOn : stereo::NoiseHandling::kOff;
    options.matcher.fill_nearer = kind != 1;
    stereo::DepthStep depth(rectifier->camera(), options);
    size_t next = 0;
    const double ms = medianMs(runs, [&] {
      const auto& f = frames[next++ % frames.size()];
      (void)rectifier->rectify(f.left, f.right, left, right);
      const auto cloud = depth.compute(left, right, *f.T_map_body * *f.T_body_camera);
      (void)cloud;
    });
    const char* labels[] = {"clean (the fast path)", "clean, without the semi-global fill",
                            "noisy (typical camera, level 0)"};
    std::printf("| %s | %.1f |\n", labels[kind], ms);
  }
  return 0;
}
