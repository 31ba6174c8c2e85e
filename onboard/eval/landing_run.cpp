#include "onboard/eval/landing_run.hpp"

#include <chrono>
#include <cmath>

namespace stereomap::eval {

using common::Rigid3;
using common::Vec3;

namespace {

double msSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
      .count();
}

}  // namespace

std::vector<LandingFrameScore> runLanding(sim::DeckSource& source,
                                          const LandingRunOptions& options) {
  std::vector<LandingFrameScore> scores;
  const camera::StereoCamera& camera = source.camera();
  const Vec3 centre(1.5, 2.0, 0.0);  // the pad's centre in its frame
  for (uint64_t n = 0;; ++n) {
    auto frame = source.next();
    if (!frame) break;
    if (n % static_cast<uint64_t>(std::max(options.every, 1)) != 0) continue;
    const sim::DeckTruth& truth = source.truth();
    LandingFrameScore score;
    score.t_s = truth.t_s;
    score.distance_m = truth.distance_m;
    score.corners_in_view = truth.corners_in_view;
    auto start = std::chrono::steady_clock::now();
    const landing::PadDetection left = landing::detectPad(frame->left, options.detector);
    score.detect_ms = msSince(start);
    score.detected = left.found;
    score.reason = left.reason;
    if (left) {
      double squared = 0;
      for (int k = 0; k < 8; ++k) {
        const auto uv = camera.project(truth.T_camera_pad * landing::padModel()[k]);
        squared +=
            uv ? (Eigen::Vector2d(left.corners[k].x, left.corners[k].y) - *uv).squaredNorm() : 1e6;
      }
      score.corner_error_px = std::sqrt(squared / 8);
      const landing::PadDetection right = landing::detectPad(frame->right, options.detector);
      score.right_detected = right.found;
      const std::optional<std::array<cv::Point2d, 8>> right_corners =
          right ? std::optional(right.corners) : std::nullopt;
      for (int m = 0; m < 2; ++m) {
        start = std::chrono::steady_clock::now();
        const landing::PadPose pose = landing::estimatePadPose(
            left.corners, right_corners, camera,
            {.mode = m == 0 ? landing::PoseMode::kDefault : landing::PoseMode::kPatent});
        score.pose_ms[m] = msSince(start);
        auto& mode = score.modes[m];
        mode.published = pose.ok;
        mode.rms_px = pose.rms_px;
        if (!pose.ok && m == 0) score.reason = pose.reason;
        if (!pose.ok) continue;
        mode.position_pct = 100.0 *
                            (pose.T_camera_pad * centre - truth.T_camera_pad * centre).norm() /
                            truth.distance_m;
        mode.attitude_deg =
            pose.T_camera_pad.rotation.angularDistance(truth.T_camera_pad.rotation) * 180.0 / M_PI;
      }
    }
    if (options.on_frame) options.on_frame(*frame, score);
    scores.push_back(score);
  }
  return scores;
}

}  // namespace stereomap::eval
