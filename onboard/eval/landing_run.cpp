#include "onboard/eval/landing_run.hpp"

#include <chrono>
#include <cmath>
#include <opencv2/core/utility.hpp>

namespace stereomap::eval {

using common::Rigid3;
using common::Vec3;

namespace {

double msSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
      .count();
}

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
  landing::PadTracker left_tracker(options.tracker), right_tracker(options.tracker);
  landing::DeckFilter deck;
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
    auto start = std::chrono::steady_clock::now();
    const landing::PadTrack left = left_tracker.update(frame->left);
    score.track_ms = msSince(start);
    const landing::PadTrack& right = right_tracker.update(frame->right);
    score.state = left.state;
    score.detected = left.detected;
    score.reason = left.reason;
    const bool scored = n % static_cast<uint64_t>(std::max(options.every, 1)) == 0;
    if (scored) {
      start = std::chrono::steady_clock::now();
      (void)landing::detectPad(frame->left, options.tracker.detector);
      score.detect_ms = msSince(start);
    }
    if (left.state == landing::TrackState::kTracking) {
      score.corner_error_px = cornerError(left.corners, truth.T_camera_pad, camera);
      score.right_found = right.state == landing::TrackState::kTracking;
      const std::optional<landing::PadView> right_view =
          score.right_found ? std::optional(landing::PadView{right.corners, right.edges})
                            : std::nullopt;
      for (int m = 0; m < 2; ++m) {
        start = std::chrono::steady_clock::now();
        const landing::PadPose pose = landing::estimatePadPose(
            landing::PadView{left.corners, left.edges}, right_view, camera,
            {.mode = m == 0 ? landing::PoseMode::kDefault : landing::PoseMode::kPatent});
        score.pose_ms[m] = msSince(start);
        auto& mode = score.modes[m];
        mode.published = pose.ok;
        mode.rms_px = pose.rms_px;
        if (!pose.ok) {
          if (m == 0) score.reason = pose.reason;
          continue;
        }
        const Vec3 centre = landing::padCentre();
        mode.position_pct = 100.0 *
                            (pose.T_camera_pad * centre - truth.T_camera_pad * centre).norm() /
                            truth.distance_m;
        mode.attitude_deg =
            pose.T_camera_pad.rotation.angularDistance(truth.T_camera_pad.rotation) * 180.0 / M_PI;
        if (m != 0) continue;
        // The deck's motion: the body pose from the vehicle's navigation (the sim's truth
        // stands in for GPS/INS, as in the patent).
        const Rigid3 T_map_camera = *frame->T_map_body * *frame->T_body_camera;
        const auto& estimate = deck.update(
            truth.t_s, T_map_camera * pose.T_camera_pad,
            landing::padCovarianceInMap(T_map_camera, pose.T_camera_pad, pose.covariance));
        score.deck_valid = true;
        score.heave_rate_error = estimate.velocity.z() - truth.deck_velocity.z();
        score.deck_attitude_error_deg =
            estimate.T_map_deck.rotation.angularDistance(truth.T_world_deck.rotation) * 180.0 /
            M_PI;
      }
    }
    cv::setNumThreads(threads);
    if (!scored) continue;
    if (options.on_frame) options.on_frame(*frame, score, left);
    scores.push_back(score);
  }
  return scores;
}

}  // namespace stereomap::eval
