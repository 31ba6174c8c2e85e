#include "onboard/eval/landing_run.hpp"

#include <chrono>
#include <cmath>
#include <opencv2/core/utility.hpp>

#include "common/time.hpp"

namespace stereomap::eval {

using common::msSince;
using common::Rigid3;
using common::Vec3;

namespace {

double cornerError(const std::array<cv::Point2d, 8>& corners, const Rigid3& T_camera_pad,
                   const camera::StereoCamera& camera) {
  double squared = 0;
  for (int k = 0; k < 8; ++k) {
    const auto uv = camera.project(T_camera_pad * landing::padModel()[k]);
    squared += uv ? (Eigen::Vector2d(corners[k].x, corners[k].y) - *uv).squaredNorm() : 1e6;
  }
  return std::sqrt(squared / 8);
}

}  // namespace

std::vector<LandingFrameScore> runLanding(sim::DeckSource& source,
                                          const LandingRunOptions& options) {
  std::vector<LandingFrameScore> scores;
  const camera::StereoCamera& camera = source.camera();
  landing::LandingWatch watch(camera, {.tracker = options.tracker});
  const Vec3 centre = landing::padCentre();
  for (uint64_t n = 0;; ++n) {
    auto frame = source.next();
    if (!frame) break;
    const sim::DeckTruth& truth = source.truth();
    // The landing chain on one core (as the figures ask); the renderer on all of them.
    const int threads = cv::getNumThreads();
    cv::setNumThreads(1);
    LandingFrameScore score;
    score.t_s = truth.t_s;
    score.distance_m = truth.distance_m;
    score.corners_in_view = truth.corners_in_view;
    // The body pose from the vehicle's navigation: the sim's truth stands in for GPS/INS, as
    // in the patent.
    const landing::LandingReport& seen =
        watch.update(truth.t_s, frame->left, frame->right, *frame->T_map_body,
                     *frame->T_body_camera, frame->T_world_map.value_or(common::Rigid3{}));
    score.track_ms = seen.track_ms;
    score.state = seen.state;
    score.detected = seen.left.detected;
    score.reason = seen.reason;
    score.right_found = seen.right_tracking;
    const bool scored = n % static_cast<uint64_t>(std::max(options.every, 1)) == 0;
    if (scored) {
      const auto start = std::chrono::steady_clock::now();
      (void)landing::detectPad(frame->left, options.tracker.detector);
      score.detect_ms = msSince(start);
    }
    auto grade = [&](const landing::PadPose& pose, LandingFrameScore::Mode& mode) {
      mode.published = pose.ok;
      mode.rms_px = pose.rms_px;
      if (!pose.ok) return;
      mode.position_pct = 100.0 *
                          (pose.T_camera_pad * centre - truth.T_camera_pad * centre).norm() /
                          truth.distance_m;
      mode.attitude_deg =
          pose.T_camera_pad.rotation.angularDistance(truth.T_camera_pad.rotation) * 180.0 / M_PI;
    };
    if (seen.state == landing::TrackState::kTracking) {
      score.corner_error_px = cornerError(seen.left.corners, truth.T_camera_pad, camera);
      grade(seen.pose, score.modes[0]);
      score.pose_ms[0] = seen.pose_ms;
      const auto start = std::chrono::steady_clock::now();
      const landing::PadPose patent = landing::estimatePadPose(
          seen.left.corners, std::nullopt, camera, {.mode = landing::PoseMode::kPatent});
      score.pose_ms[1] = msSince(start);
      grade(patent, score.modes[1]);
    }
    if (seen.has_pose) {
      score.deck_valid = true;
      score.heave_rate_error = seen.deck.velocity.z() - truth.deck_velocity.z();
      score.deck_attitude_error_deg =
          seen.deck.T_map_deck.rotation.angularDistance(truth.T_world_deck.rotation) * 180.0 / M_PI;
    }
    cv::setNumThreads(threads);
    if (!scored) continue;
    if (options.on_frame) options.on_frame(*frame, score, seen.left);
    scores.push_back(score);
  }
  return scores;
}

}  // namespace stereomap::eval
