// stereomap-bench-vo: the visual odometry's figures for docs/BENCHMARKS.md, fast and paper
// modes side by side on the same data: KITTI 01 frames 0-50 (rotation drift, Sim3 ATE),
// sim flights with image noise and blur (ATE, attitude), the static EuRoC clip (motion), and
// time per frame on one core (median). Also: ablations of the fast mode (no window
// adjustment, no right-offset estimate), and on KITTI the rotation drift of a rotation-only
// reference (5-point essential matrix on 1000+ KLT tracks per frame, chained with the true
// translations) that shows how low this excerpt's images and ground truth let rotation drift go.
#include <CLI/CLI.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include <cmath>
#include <cstdio>
#include <filesystem>

#include "common/cli.hpp"
#include "onboard/camera/dataset_source.hpp"
#include "onboard/eval/metrics.hpp"
#include "onboard/eval/odometry_run.hpp"
#include "onboard/sim/sim_source.hpp"
#include "testing/sim_flights.hpp"

using namespace stereomap;

namespace {

void row(const char* data, const char* mode, const eval::OdometryRun& run,
         const std::vector<double>& lengths) {
  const auto drift = eval::kittiDrift(run.truth, run.estimate, lengths);
  const auto sim3 = eval::absoluteError(run.truth, run.estimate, eval::Alignment::kSim3);
  const auto se3 = eval::absoluteError(run.truth, run.estimate, eval::Alignment::kSe3);
  const double path = eval::pathLength(run.truth);
  const double moved = eval::largestDisplacement(run.estimate);
  std::printf(
      "| %s | %s | %zu | %d | %.2f %% / %.2f | %.3f m (scale %.3f) | %.3f m (%.2f %% of %.1f m) | "
      "%.3f | %.4f | %+.2f | %.1f |\n",
      data, mode, run.estimate.size(), run.lost,
      drift.empty() ? 0.0 : drift.back().translation_percent,
      drift.empty() ? 0.0 : drift.back().rotation_deg_per_100m, sim3.translation.rmse,
      sim3.alignment.scale, se3.translation.rmse,
      path > 0 ? 100 * se3.translation.rmse / path : 0.0, path, se3.rotation.rmse, moved,
      run.right_offset_px, run.medianMilliseconds());
}

// Rotation drift of the 5-point essential matrix between consecutive left images (GFTT 2000,
// KLT, RANSAC 0.5 px), chained with the true translations: no stereo, no depth, no scale.
// Also the mean per-frame rotation error (camera axes, degrees). `focal_scale` scales fx, fy.
struct RotationReference {
  double drift = 0;
  Eigen::Vector3d mean_error_deg = Eigen::Vector3d::Zero();
};
RotationReference essentialRotation(camera::FrameSource& source, double length,
                                    double focal_scale) {
  const auto& c = source.camera();
  const cv::Matx33d K(c.fx * focal_scale, 0, c.cx, 0, c.fy * focal_scale, c.cy, 0, 0, 1);
  RotationReference reference;
  common::Trajectory truth, estimate;
  cv::Mat previous;
  while (auto frame = source.next()) {
    const common::Rigid3 T = frame->T_map_body.value_or(common::Rigid3{}) *
                             frame->T_body_camera.value_or(common::Rigid3{});
    const double t = static_cast<double>(frame->stamp_ns) * 1e-9;
    if (previous.empty()) {
      truth.push_back({t, T});
      estimate.push_back({t, T});
      previous = frame->left;
      continue;
    }
    std::vector<cv::Point2f> a, b, pa, pb;
    cv::goodFeaturesToTrack(previous, a, 2000, 0.01, 8);
    std::vector<uchar> status;
    std::vector<float> error;
    cv::calcOpticalFlowPyrLK(previous, frame->left, a, b, status, error, cv::Size(21, 21), 4);
    for (size_t k = 0; k < a.size(); ++k) {
      if (status[k]) {
        pa.push_back(a[k]);
        pb.push_back(b[k]);
      }
    }
    cv::Mat mask, R, tv;
    const cv::Mat E = cv::findEssentialMat(pa, pb, K, cv::RANSAC, 0.999, 0.5, mask);
    cv::recoverPose(E, pa, pb, K, R, tv, mask);
    Eigen::Matrix3d M;
    for (int r = 0; r < 3; ++r) {
      for (int k = 0; k < 3; ++k) M(r, k) = R.at<double>(r, k);
    }
    common::Rigid3 step = truth.back().pose.inverse() * T;      // true previous-to-current
    const common::Quat measured = common::Quat(M).conjugate();  // R maps previous to current
    const Eigen::AngleAxisd wrong(step.rotation.conjugate() * measured);
    reference.mean_error_deg += wrong.axis() * wrong.angle() * 180.0 / M_PI;
    step.rotation = measured;
    estimate.push_back({t, estimate.back().pose * step});
    truth.push_back({t, T});
    previous = frame->left;
  }
  const auto drift = eval::kittiDrift(truth, estimate, {length});
  if (!drift.empty()) reference.drift = drift.front().rotation_deg_per_100m;
  if (truth.size() > 1) reference.mean_error_deg /= static_cast<double>(truth.size() - 1);
  return reference;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-bench-vo: visual odometry figures, fast and paper modes"};
  std::string data = STEREOMAP_DATA_DIR;
  app.add_option("--data", data, "The shared data folder")->capture_default_str();
  if (auto exit_code = stereomap::common::parseCommandLine(app, argc, argv)) return *exit_code;
  cv::setNumThreads(0);  // one core, as on the vehicle's budget
  std::printf(
      "| data | mode | frames | lost | drift: translation / rotation (deg/100 m) | ATE Sim3 | ATE "
      "SE3 | attitude RMS (deg) | largest motion (m) | right offset (px) | ms/frame (median) |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|\n");
  odometry::VoOptions no_window, no_offset, paper;
  no_window.window_frames = 0;
  no_offset.right_offset_step_px = 0;
  paper.mode = odometry::VoMode::kPaper;
  struct Mode {
    const char* name;
    odometry::VoOptions options;
    bool ablation;  // fewer rows: KITTI and one sim room
  };
  const std::vector<Mode> modes = {{"fast", {}, false},
                                   {"fast, no window", no_window, true},
                                   {"fast, no offset estimate", no_offset, true},
                                   {"paper", paper, false}};
  const auto kitti = std::filesystem::path(data) / "kitti_stereo_seq2";
  const auto euroc = std::filesystem::path(data) / "euroc_v101_micro";
  for (const auto& [mode, options, ablation] : modes) {
    if (std::filesystem::exists(kitti)) {
      auto source = camera::openKitti(kitti, {});
      if (source)
        row("KITTI 01 0-50 (20 m segments)", mode, eval::runOdometry(**source, options), {20});
    }
    for (uint32_t seed : {1u, 2u, 3u}) {
      if (ablation && seed > 1) break;
      sim::SimSource source(testing::noisyFlight(seed));
      const std::string label =
          "sim room " + std::to_string(seed) + ", noise 2, blur 1 (5 m segments)";
      row(label.c_str(), mode, eval::runOdometry(source, options), {5});
    }
    if (!ablation) {  // the paper's setting: near walls, clean images
      sim::SimSource source({.seed = 1, .rate_hz = 10.0, .max_frames = 300});
      row("sim room 1, no noise or blur (5 m segments)", mode, eval::runOdometry(source, options),
          {5});
    }
    if (std::filesystem::exists(euroc) && !ablation) {
      auto source = camera::openEuroc(euroc, {});
      if (source) row("EuRoC V1_01 static clip", mode, eval::runOdometry(**source, options), {});
    }
  }
  for (const double focal_scale : {1.0, 0.99}) {
    if (!std::filesystem::exists(kitti)) break;
    auto source = camera::openKitti(kitti, {});
    if (!source) break;
    const auto r = essentialRotation(**source, 20, focal_scale);
    std::printf(
        "\nRotation-only reference on KITTI 01 0-50 (essential matrix, true translations, "
        "focal length x %.2f): %.2f deg/100 m over 20 m segments; mean error per frame "
        "(camera x, y, z) %+.4f %+.4f %+.4f deg\n",
        focal_scale, r.drift, r.mean_error_deg.x(), r.mean_error_deg.y(), r.mean_error_deg.z());
  }
  return 0;
}
