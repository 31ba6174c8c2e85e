#include "onboard/sim/flight.hpp"

#include <cmath>

namespace stereomap::sim {

using common::Quat;
using common::Rigid3;
using common::Vec3;

Flight::Flight(FlightOptions options) : options_(options) {}

Rigid3 Flight::T_map_body(double t_s) const {
  const double phase = 2 * M_PI * t_s / options_.period_s;
  const Vec3 position(options_.radius_x * std::cos(phase), options_.radius_y * std::sin(phase),
                      options_.height + options_.height_swing * std::sin(2 * phase));
  // Heading along the path's tangent, turned outward so the camera sees walls and obstacles.
  const double heading =
      std::atan2(options_.radius_y * std::cos(phase), -options_.radius_x * std::sin(phase)) -
      options_.look_outward;
  return {Quat(Eigen::AngleAxisd(heading, Vec3::UnitZ())), position};
}

Rigid3 Flight::T_body_camera() const {
  // Pitch down is a positive rotation about the body's y (left) axis.
  const Quat pitch(Eigen::AngleAxisd(options_.camera_pitch_down, Vec3::UnitY()));
  return {pitch * common::bodyFromCameraRotation(), Vec3::Zero()};
}

}  // namespace stereomap::sim
