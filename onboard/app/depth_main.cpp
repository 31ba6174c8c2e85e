// stereomap-depth: dense disparity (and optionally a point cloud) from one stereo pair.
// Works without a calibration for disparity alone (e.g. Middlebury pairs).
#include <CLI/CLI.hpp>
#include <opencv2/imgcodecs.hpp>

#include <chrono>
#include <cstdio>

#include "common/cli.hpp"
#include "onboard/camera/calibration.hpp"
#include "onboard/camera/rectifier.hpp"
#include "onboard/stereo/depth.hpp"
#include "onboard/stereo/disparity_io.hpp"

int main(int argc, char** argv) {
  using namespace stereomap;
  CLI::App app{"stereomap-depth: disparity and point cloud from one stereo pair"};
  std::string left_path, right_path, calib_path, disparity_out, cloud_out, colorized_out;
  std::string preset = "accurate";
  int max_disparity = 0;
  std::string max_range = "auto";
  double map_resolution = 0.1;
  app.add_option("--left", left_path, "Left image")->required()->check(CLI::ExistingFile);
  app.add_option("--right", right_path, "Right image")->required()->check(CLI::ExistingFile);
  app.add_option("--calib", calib_path,
                 "Stereo calibration (rectifies first; needed for --cloud-out)")
      ->check(CLI::ExistingFile);
  app.add_option("--max-disparity", max_disparity,
                 "Largest disparity to search, pixels (default: the preset's)")
      ->check(CLI::Range(1, 1024));
  app.add_option("--stereo", preset, "Matcher configuration: fast or accurate")
      ->check(CLI::IsMember({"fast", "accurate"}))
      ->capture_default_str();
  app.add_option("--disparity-out", disparity_out,
                 "16-bit PNG, value = disparity x 256, 0 = invalid (KITTI convention)")
      ->required();
  app.add_option("--cloud-out", cloud_out, "PLY point cloud in the left camera frame");
  app.add_option("--colorized", colorized_out, "Colour picture of the disparity");
  app.add_option("--max-range", max_range,
                 "Cloud range limit, metres, or auto (with --calib: where a disparity error "
                 "moves a point by less than a voxel of --map-resolution, as the vehicle's; "
                 "without: 20)")
      ->check(common::autoOr(0.5, 100.0))
      ->capture_default_str();
  app.add_option("--map-resolution", map_resolution,
                 "With --calib: the map's voxel, for the automatic range and disparity search "
                 "(the vehicle's: stereomap-onboard --map-resolution)")
      ->check(CLI::Range(0.001, 10.0))
      ->capture_default_str();
  if (auto exit_code = common::parseCommandLine(app, argc, argv)) return *exit_code;
  if (!cloud_out.empty() && calib_path.empty()) {
    std::fprintf(stderr, "--cloud-out needs --calib: depth needs the focal length and baseline\n");
    return 2;
  }

  cv::Mat left = cv::imread(left_path, cv::IMREAD_GRAYSCALE);
  cv::Mat right = cv::imread(right_path, cv::IMREAD_GRAYSCALE);
  if (left.empty() || right.empty()) {
    std::fprintf(stderr, "cannot read %s\n", (left.empty() ? left_path : right_path).c_str());
    return 1;
  }
  if (left.size() != right.size()) {
    std::fprintf(stderr, "the images differ in size: %dx%d and %dx%d\n", left.cols, left.rows,
                 right.cols, right.rows);
    return 1;
  }
  std::optional<camera::Rectifier> rectifier;
  if (!calib_path.empty()) {
    auto calibration = camera::readCalibration(calib_path);
    if (!calibration) {
      std::fprintf(stderr, "%s\n", calibration.error().message.c_str());
      return 1;
    }
    auto created = camera::Rectifier::create(*calibration, left.size());
    if (!created) {
      std::fprintf(stderr, "%s\n", created.error().message.c_str());
      return 1;
    }
    rectifier = std::move(created).value();
    cv::Mat left_rect, right_rect;
    if (auto status = rectifier->rectify(left, right, left_rect, right_rect); !status) {
      std::fprintf(stderr, "%s\n", status.error().message.c_str());
      return 1;
    }
    left = left_rect;
    right = right_rect;
  }

  stereo::MatcherOptions options =
      preset == "fast" ? stereo::MatcherOptions::fast() : stereo::MatcherOptions::accurate();
  double range_m = common::autoOrNumber(max_range).value_or(20.0);  // checked by autoOr
  if (max_disparity > 0) {
    options.num_disparities = stereo::disparitiesFor(max_disparity);
  } else if (rectifier) {
    // The vehicle's search: the rig's range and its pyramid of windows (rig_range.hpp).
    const auto range =
        stereo::rigRange(rectifier->camera(),
                         stereo::rigRangeOptions(options, map_resolution,
                                                 common::autoOrNumber(max_range).value_or(0.0)));
    options = stereo::fitToWindows(options, range.windows);
    range_m = range.far_m;
    std::printf("range: %s\n", range.explain().c_str());
  }
  if (const auto problem = stereo::searchProblem(options, left.cols); !problem.empty()) {
    std::fprintf(stderr, "%s\n", problem.c_str());
    return 1;
  }
  const stereo::StereoMatcher matcher(options);
  const auto start = std::chrono::steady_clock::now();
  const cv::Mat disparity = matcher.compute(left, right);
  const double ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  const double valid = cv::countNonZero(disparity >= 0) / static_cast<double>(disparity.total());
  std::printf("disparity: %dx%d, %d disparities, %.1f%% valid, %.1f ms (%s)\n", disparity.cols,
              disparity.rows, options.num_disparities, 100 * valid, ms, preset.c_str());

  if (auto status = stereo::writeDisparityPng(disparity_out, disparity); !status) {
    std::fprintf(stderr, "%s\n", status.error().message.c_str());
    return 1;
  }
  std::printf("written: %s\n", disparity_out.c_str());
  if (!colorized_out.empty()) {
    if (!cv::imwrite(colorized_out, stereo::colorizeDisparity(disparity))) {
      std::fprintf(stderr, "%s: cannot write\n", colorized_out.c_str());
      return 1;
    }
    std::printf("written: %s\n", colorized_out.c_str());
  }
  if (!cloud_out.empty()) {
    const auto cloud =
        stereo::cloudFromDisparity(disparity, left, rectifier->camera(), {.max_range_m = range_m});
    if (auto status = stereo::writePly(cloud_out, cloud); !status) {
      std::fprintf(stderr, "%s\n", status.error().message.c_str());
      return 1;
    }
    std::printf("written: %s (%zu points)\n", cloud_out.c_str(), cloud.size());
  }
  return 0;
}
