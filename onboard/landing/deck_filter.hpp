// The deck's motion from the pad's measured poses: each pose taken into the map frame
// (T_map_pad = T_map_body x T_body_camera x T_camera_pad; the body pose from the vehicle's
// navigation), then a constant-velocity Kalman filter per axis of position and per Euler
// angle of the deck: the deck's pose, velocity (heave = its z), angle rates and body angular
// rate, and the pad's distance and bearing from the vehicle.
//
// The deck frame: origin at the pad's centre, x along the T's bar, z up out of the deck.
#pragma once

#include <array>
#include <optional>

#include "common/geometry.hpp"

namespace stereomap::landing {

using Mat6 = Eigen::Matrix<double, 6, 6>;

// The deck frame in the pad frame (the pad's z points into the deck).
common::Rigid3 T_pad_deck();

struct DeckFilterOptions {
  // Random acceleration the filter allows (1 sigma): a deck heaving 0.5 m at 0.1 Hz reaches
  // 0.2 m/s^2; rolling 5 deg every 9 s, 0.04 rad/s^2.
  double acceleration = 0.4;          // m/s^2
  double angular_acceleration = 0.1;  // rad/s^2
  double max_gap_s = 2.0;             // no measurement for longer: start again
};

struct DeckEstimate {
  bool valid = false;
  double t_s = 0;
  common::Rigid3 T_map_deck;
  common::Vec3 velocity = common::Vec3::Zero();      // map frame; heave is z
  common::Vec3 euler = common::Vec3::Zero();         // roll, pitch, yaw (Z-Y-X), radians
  common::Vec3 euler_rate = common::Vec3::Zero();    // their rates
  common::Vec3 angular_rate = common::Vec3::Zero();  // deck axes, rad/s
  Mat6 covariance = Mat6::Zero();                    // (euler, position), diagonal
};

class DeckFilter {
 public:
  explicit DeckFilter(DeckFilterOptions options = {}) : options_(options) {}
  // One measurement of the pad in the map frame, with the covariance of (rotation in the map
  // frame, pad centre's position in the map frame).
  const DeckEstimate& update(double t_s, const common::Rigid3& T_map_pad, const Mat6& covariance);
  const DeckEstimate& estimate() const { return estimate_; }
  void reset() { *this = DeckFilter(options_); }

 private:
  struct Axis {  // [value, rate] with its covariance
    Eigen::Vector2d x = Eigen::Vector2d::Zero();
    Eigen::Matrix2d P = Eigen::Matrix2d::Zero();
    void predict(double dt, double q);
    void correct(double measured, double variance);
  };
  DeckFilterOptions options_;
  std::array<Axis, 6> axes_;  // roll, pitch, yaw, x, y, z
  DeckEstimate estimate_;
};

// The covariance of (rotation, pad centre) in the map frame from the pose solver's
// (rotation, pad origin) covariance in the camera frame.
Mat6 padCovarianceInMap(const common::Rigid3& T_map_camera, const common::Rigid3& T_camera_pad,
                        const Mat6& camera_covariance);

// The pad's centre relative to the vehicle: distance (m) and bearing (degrees clockwise from
// the body's forward axis, in the horizontal plane).
struct PadBearing {
  double distance_m = 0, horizontal_m = 0, height_m = 0, bearing_deg = 0;
};
PadBearing bearingFrom(const common::Rigid3& T_map_body, const common::Vec3& pad_centre_map);

// The pad's centre in its own frame.
common::Vec3 padCentre();

// Z-Y-X Euler angles (roll, pitch, yaw; radians) of a rotation, and the body angular rate of
// their rates.
common::Vec3 eulerZyx(const common::Quat& q);
common::Vec3 bodyRatesFromEuler(const common::Vec3& euler, const common::Vec3& euler_rate);

}  // namespace stereomap::landing
