// The pad's pose in the left camera from its 8 corners (a..h, as padModel()).
//   Default: IPPE's two planar PnP solutions from the left image, each refined with Ceres on
//     the reprojection error in both rectified cameras (the baseline gives metric depth and
//     settles the planar ambiguity), Huber loss; the better one kept, with the covariance of
//     its 6 parameters (rotation vector, translation) scaled by the residuals. Where a view
//     has the sub-pixel points along the T's edges, the error is their distance from the
//     pad's projected edges instead of the corners': every edge point counts, and the pose
//     ties the short edges' directions to the long ones' (a corner from two short edges is
//     the least certain).
//   Patent: the patent's linear solution exactly as it writes it, in the coplanar form the
//     flat pad allows (Tsai's radial alignment: 5 unknowns p1, p2, tx, p4, p5 over ty, |ty|
//     from the unit rows, the third row from orthonormality, tz from a second linear solve
//     with the known intrinsics), then its Euler angles. Left image only.
// Either pose is refused (never published) when its reprojection error is too large.
#pragma once

#include <array>
#include <optional>
#include <string>

#include <opencv2/core.hpp>

#include "common/geometry.hpp"
#include "onboard/camera/stereo_camera.hpp"
#include "onboard/landing/pad_detector.hpp"

namespace stereomap::landing {

enum class PoseMode { kDefault, kPatent };

struct PadPoseOptions {
  PoseMode mode = PoseMode::kDefault;
  double max_rms_px = 1.5;  // reprojection error above this: refused
  double huber_px = 1.0;
};

struct PadPose {
  bool ok = false;
  std::string reason;           // why refused
  common::Rigid3 T_camera_pad;  // the left camera's view of the pad
  Eigen::Matrix<double, 6, 6> covariance =
      Eigen::Matrix<double, 6, 6>::Zero();        // (rotation, translation), default mode
  double rms_px = 0;                              // reprojection error over the corners used
  bool stereo = false;                            // the right image's corners were used
  common::Vec3 euler_deg = common::Vec3::Zero();  // roll, pitch, yaw (Z-Y-X) of R_camera_pad
  explicit operator bool() const { return ok; }
};

// The pad in one image: its corners a..h and, if known, the edge points behind them.
struct PadView {
  std::array<cv::Point2d, 8> corners{};
  PadEdgePoints edges;
};

// `right`: the pad in the right image, when found there.
PadPose estimatePadPose(const PadView& left, const std::optional<PadView>& right,
                        const camera::StereoCamera& camera, const PadPoseOptions& options = {});
// Corners alone.
PadPose estimatePadPose(const std::array<cv::Point2d, 8>& left,
                        const std::optional<std::array<cv::Point2d, 8>>& right,
                        const camera::StereoCamera& camera, const PadPoseOptions& options = {});

// The patent's linear solution alone (no checks), for tests: nullopt when degenerate.
std::optional<common::Rigid3> patentLinearPose(const std::array<cv::Point2d, 8>& image,
                                               const camera::StereoCamera& camera);

}  // namespace stereomap::landing
