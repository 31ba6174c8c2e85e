#include "onboard/landing/deck_filter.hpp"

#include <cmath>

namespace stereomap::landing {

using common::Quat;
using common::Rigid3;
using common::Vec3;

namespace {

Quat fromEulerZyx(const Vec3& e) {
  return Quat(Eigen::AngleAxisd(e.z(), Vec3::UnitZ())) *
         Quat(Eigen::AngleAxisd(e.y(), Vec3::UnitY())) *
         Quat(Eigen::AngleAxisd(e.x(), Vec3::UnitX()));
}

Eigen::Matrix3d skew(const Vec3& v) {
  Eigen::Matrix3d S;
  S << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return S;
}

}  // namespace

Vec3 padCentre() { return {1.5, 2.0, 0.0}; }

Vec3 eulerZyx(const Quat& q) {
  const Eigen::Matrix3d R = q.toRotationMatrix();
  return {std::atan2(R(2, 1), R(2, 2)), std::asin(std::clamp(-R(2, 0), -1.0, 1.0)),
          std::atan2(R(1, 0), R(0, 0))};
}

Vec3 bodyRatesFromEuler(const Vec3& euler, const Vec3& rate) {
  const double roll = euler.x(), pitch = euler.y();
  return {rate.x() - rate.z() * std::sin(pitch),
          rate.y() * std::cos(roll) + rate.z() * std::cos(pitch) * std::sin(roll),
          -rate.y() * std::sin(roll) + rate.z() * std::cos(pitch) * std::cos(roll)};
}

Rigid3 T_pad_deck() {
  // x along the bar, y and z turned over (the pad's z points into the deck).
  return {Quat(Eigen::AngleAxisd(M_PI, Vec3::UnitX())), padCentre()};
}

void DeckFilter::Axis::predict(double dt, double q) {
  Eigen::Matrix2d F;
  F << 1, dt, 0, 1;
  Eigen::Matrix2d Q;
  Q << dt * dt * dt * dt / 4, dt * dt * dt / 2, dt * dt * dt / 2, dt * dt;
  x = F * x;
  P = F * P * F.transpose() + Q * q * q;
}

void DeckFilter::Axis::correct(double measured, double variance) {
  const double innovation = measured - x(0);
  const double S = P(0, 0) + variance;
  const Eigen::Vector2d K = P.col(0) / S;
  x += K * innovation;
  P -= K * P.row(0);
}

const DeckEstimate& DeckFilter::update(double t_s, const Rigid3& T_map_pad,
                                       const Mat6& covariance) {
  const Rigid3 T_map_deck = T_map_pad * T_pad_deck();
  Vec3 euler = eulerZyx(T_map_deck.rotation);
  const Vec3 position = T_map_deck.translation;
  const bool restart =
      !estimate_.valid || t_s - estimate_.t_s > options_.max_gap_s || t_s <= estimate_.t_s;
  if (restart) {
    for (int i = 0; i < 6; ++i) {
      axes_[i].x << (i < 3 ? euler[i] : position[i - 3]), 0.0;
      // Unknown rate: a wide start (1 m/s, 0.2 rad/s).
      axes_[i].P << std::max(covariance(i, i), 1e-8), 0, 0, i < 3 ? 0.04 : 1.0;
    }
  } else {
    const double dt = t_s - estimate_.t_s;
    // The yaw measured next to the one predicted, not 2 pi away.
    euler.z() = axes_[2].x(0) + std::remainder(euler.z() - axes_[2].x(0), 2 * M_PI);
    for (int i = 0; i < 6; ++i) {
      axes_[i].predict(dt, i < 3 ? options_.angular_acceleration : options_.acceleration);
      axes_[i].correct(i < 3 ? euler[i] : position[i - 3], std::max(covariance(i, i), 1e-10));
    }
  }
  estimate_.valid = true;
  estimate_.t_s = t_s;
  for (int i = 0; i < 3; ++i) {
    estimate_.euler[i] = axes_[i].x(0);
    estimate_.euler_rate[i] = axes_[i].x(1);
    estimate_.velocity[i] = axes_[i + 3].x(1);
    estimate_.T_map_deck.translation[i] = axes_[i + 3].x(0);
  }
  estimate_.T_map_deck.rotation = fromEulerZyx(estimate_.euler);
  estimate_.angular_rate = bodyRatesFromEuler(estimate_.euler, estimate_.euler_rate);
  estimate_.covariance.setZero();
  for (int i = 0; i < 6; ++i) estimate_.covariance(i, i) = axes_[i].P(0, 0);
  return estimate_;
}

Mat6 padCovarianceInMap(const Rigid3& T_map_camera, const Rigid3& T_camera_pad,
                        const Mat6& camera_covariance) {
  // The centre p = exp(d) R c + t: dp/dd = -[R c]x, dp/dt = I.
  Eigen::Matrix<double, 6, 6> J = Eigen::Matrix<double, 6, 6>::Zero();
  J.block<3, 3>(0, 0).setIdentity();
  J.block<3, 3>(3, 0) = -skew(T_camera_pad.rotation * padCentre());
  J.block<3, 3>(3, 3).setIdentity();
  Eigen::Matrix<double, 6, 6> Rm = Eigen::Matrix<double, 6, 6>::Zero();
  Rm.block<3, 3>(0, 0) = T_map_camera.rotation.toRotationMatrix();
  Rm.block<3, 3>(3, 3) = Rm.block<3, 3>(0, 0);
  return Rm * J * camera_covariance * J.transpose() * Rm.transpose();
}

PadBearing bearingFrom(const Rigid3& T_map_body, const Vec3& pad_centre_map) {
  const Vec3 in_body = T_map_body.inverse() * pad_centre_map;
  PadBearing out;
  out.distance_m = in_body.norm();
  out.horizontal_m = std::hypot(in_body.x(), in_body.y());
  out.height_m = -in_body.z();
  // FLU body: forward x, left y; clockwise from forward is towards -y.
  out.bearing_deg = std::atan2(-in_body.y(), in_body.x()) * 180.0 / M_PI;
  return out;
}

}  // namespace stereomap::landing
