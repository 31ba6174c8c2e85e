#include "onboard/odometry/odometry.hpp"

#include <chrono>
#include <cmath>
#include <variant>

#include "onboard/odometry/detail/fast_tracker.hpp"
#include "onboard/odometry/detail/paper_tracker.hpp"

namespace stereomap::odometry {

const char* stateName(TrackingState state) {
  switch (state) {
    case TrackingState::kInit:
      return "init";
    case TrackingState::kOk:
      return "ok";
    case TrackingState::kDegraded:
      return "degraded";
    case TrackingState::kLost:
      return "lost";
  }
  return "?";
}

EulerAngles paperAttitude(const Eigen::Matrix3d& R) {
  // Eq. (12), with 1-based r_ij: pitch = asin(-r32), yaw = atan(r31/r33), roll = atan(r12/r22).
  EulerAngles e;
  e.pitch = std::asin(std::clamp(-R(2, 1), -1.0, 1.0));
  e.yaw = std::atan(R(2, 0) / R(2, 2));
  e.roll = std::atan(R(0, 1) / R(1, 1));
  return e;
}

struct StereoOdometry::Impl {
  Impl(const camera::StereoCamera& camera, const VoOptions& options)
      : options(options),
        tracker(options.mode == VoMode::kPaper
                    ? std::variant<detail::FastTracker, detail::PaperTracker>(
                          std::in_place_type<detail::PaperTracker>, camera, options)
                    : std::variant<detail::FastTracker, detail::PaperTracker>(
                          std::in_place_type<detail::FastTracker>, camera, options)) {}
  VoOptions options;
  std::variant<detail::FastTracker, detail::PaperTracker> tracker;
};

StereoOdometry::StereoOdometry(const camera::StereoCamera& camera, const VoOptions& options)
    : impl_(std::make_unique<Impl>(camera, options)) {}
StereoOdometry::~StereoOdometry() = default;
StereoOdometry::StereoOdometry(StereoOdometry&&) noexcept = default;
StereoOdometry& StereoOdometry::operator=(StereoOdometry&&) noexcept = default;
const VoOptions& StereoOdometry::options() const { return impl_->options; }

VoEstimate StereoOdometry::track(const cv::Mat& left, const cv::Mat& right) {
  const auto start = std::chrono::steady_clock::now();
  VoEstimate estimate = std::visit([&](auto& t) { return t.track(left, right); }, impl_->tracker);
  estimate.milliseconds =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  return estimate;
}

}  // namespace stereomap::odometry
