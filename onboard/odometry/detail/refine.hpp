// Ceres refinement shared by the odometry modes: the pose of the current left camera
// relative to a reference frame, from reference 3D points and their current observations.
#pragma once

#include <Eigen/Core>
#include <optional>
#include <vector>

#include "common/geometry.hpp"
#include "onboard/camera/stereo_camera.hpp"

namespace stereomap::odometry::detail {

struct Observation {
  common::Vec3 point;                    // in the reference frame
  Eigen::Vector2d left;                  // pixel in the current left image
  std::optional<Eigen::Vector2d> right;  // the same point in the current right image
};

struct RefineOptions {
  double huber_px = 1.0;
  // Constant-velocity prior: standard deviations of the pose around `prior` (0: none).
  double prior_rotation_rad = 0.0;
  double prior_translation_m = 0.0;
  int max_iterations = 10;
  bool covariance = true;
};

struct RefineResult {
  common::Rigid3 T_current_reference;
  Eigen::Matrix<double, 6, 6> covariance = Eigen::Matrix<double, 6, 6>::Identity();  // rot, trans
  double rms_px = 0;
};

// Minimises the reprojection error in both cameras (robust) from `initial`.
RefineResult refinePose(const camera::StereoCamera& camera,
                        const std::vector<Observation>& observations, const common::Rigid3& initial,
                        const common::Rigid3& prior, const RefineOptions& options);

// Pixel of a point in the left (baseline 0) or right camera; nullopt behind the camera.
std::optional<Eigen::Vector2d> project(const camera::StereoCamera& camera,
                                       const common::Vec3& p_camera, bool right = false);

}  // namespace stereomap::odometry::detail
