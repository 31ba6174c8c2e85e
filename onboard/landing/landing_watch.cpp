#include "onboard/landing/landing_watch.hpp"

#include <chrono>

#include "common/time.hpp"

namespace stereomap::landing {

using common::msSince;
using common::Rigid3;

LandingWatch::LandingWatch(const camera::StereoCamera& camera, LandingWatchOptions options)
    : camera_(camera),
      options_(options),
      left_(options.tracker),
      right_(options.tracker),
      deck_(options.deck) {}

const LandingReport& LandingWatch::update(double t_s, const cv::Mat& left, const cv::Mat& right,
                                          const Rigid3& T_map_body, const Rigid3& T_body_camera,
                                          const Rigid3& T_world_map) {
  LandingReport report;
  report.t_s = t_s;
  auto start = std::chrono::steady_clock::now();
  report.left = left_.update(left);
  report.track_ms = msSince(start);
  const PadTrack& other = right_.update(right);
  report.state = report.left.state;
  report.reason = report.left.reason;
  report.right_tracking = other.state == TrackState::kTracking;
  if (report.state == TrackState::kTracking) {
    start = std::chrono::steady_clock::now();
    report.pose = estimatePadPose(
        PadView{report.left.corners, report.left.edges},
        report.right_tracking ? std::optional(PadView{other.corners, other.edges}) : std::nullopt,
        camera_, options_.pose);
    report.pose_ms = msSince(start);
    if (report.pose) {
      report.has_pose = true;
      const Rigid3 T_map_camera = T_map_body * T_body_camera;
      report.T_map_pad = T_map_camera * report.pose.T_camera_pad;
      // The deck's motion is the world's: where the map is the deck's own frame, the pad sits
      // still in it.
      const Rigid3 T_world_camera = T_world_map * T_map_camera;
      // The patent's linear pose has no covariance: its reprojection error stands in (one
      // pixel at the pad's distance, in every direction).
      Mat6 covariance = report.pose.covariance;
      if (covariance.isZero()) {
        const double z = std::max(report.pose.T_camera_pad.translation.z(), 1.0);
        const double angle = std::max(report.pose.rms_px, 0.3) / camera_.fx;
        covariance.diagonal() << Eigen::Vector3d::Constant(std::pow(angle * 10, 2)),
            Eigen::Vector3d::Constant(std::pow(angle * z, 2));
      }
      report.map_covariance =
          padCovarianceInMap(T_map_camera, report.pose.T_camera_pad, covariance);
      report.deck =
          deck_.update(t_s, T_world_camera * report.pose.T_camera_pad,
                       padCovarianceInMap(T_world_camera, report.pose.T_camera_pad, covariance));
      report.bearing = bearingFrom(T_map_body, report.T_map_pad * padCentre());
    } else {
      report.reason = report.pose.reason;
    }
  }
  if (!report.has_pose && deck_.estimate().valid) report.deck = deck_.estimate();
  report_ = std::move(report);
  return report_;
}

}  // namespace stereomap::landing
