// Stereo calibration: both cameras' intrinsics and distortion, and the rigid transform
// between them, read from the formats users have (OpenCV stereo_calib YAML/XML, KITTI
// calib.txt, EuRoC sensor.yaml pairs, our own YAML) and written in ours. Every reader
// rejects missing, non-finite or inconsistent fields with a message naming file and field.
//
//   auto calibration = readCalibration("rig.yaml");         // format detected from content
//   auto euroc = readEurocCalibration("mav0/cam0/sensor.yaml", "mav0/cam1/sensor.yaml");
#pragma once

#include <filesystem>
#include <optional>
#include <string>

#include <opencv2/core.hpp>

#include "common/geometry.hpp"
#include "common/result.hpp"

namespace stereomap::camera {

struct CameraIntrinsics {
  cv::Matx33d K = cv::Matx33d::eye();
  cv::Mat distortion;  // 1xN CV_64F, OpenCV order (k1 k2 p1 p2 [k3 ...]); empty = none
};

struct StereoCalibration {
  cv::Size image_size;  // may be 0x0 when the file does not say (taken from the images)
  CameraIntrinsics left, right;
  // OpenCV's stereoCalibrate convention: p_right = R * p_left + T (metres or board units).
  cv::Matx33d R = cv::Matx33d::eye();
  cv::Vec3d T{0, 0, 0};
  // The left camera's pose on the vehicle body (FLU), when the source gives one (EuRoC).
  std::optional<common::Rigid3> T_body_left;
  std::string source;  // file(s) it was read from, for messages

  // True when the pair is already rectified: no distortion, equal intrinsics, R = I and T
  // along -x (KITTI, the simulator).
  bool isRectified() const;
  double baseline() const { return cv::norm(T); }
};

// Reads a calibration file, recognising the format from its content: our YAML
// (`format: stereomap-stereo-calibration`), OpenCV stereo_calib (M1 D1 M2 D2 [R T]; R and
// T from extrinsics.yml beside an intrinsics.yml when missing), or KITTI (P0/P1 lines).
common::Result<StereoCalibration> readCalibration(const std::filesystem::path& path);
common::Result<StereoCalibration> readKittiCalibration(const std::filesystem::path& path);
common::Result<StereoCalibration> readEurocCalibration(const std::filesystem::path& cam0_yaml,
                                                       const std::filesystem::path& cam1_yaml);

// Writes our YAML format (read back by readCalibration).
common::Status writeCalibration(const std::filesystem::path& path,
                                const StereoCalibration& calibration);

// Checks the fields for consistency (positive focal lengths, finite values, distortion of a
// known length, R a rotation, a non-zero baseline); the error names the field.
common::Status validateCalibration(const StereoCalibration& calibration);

}  // namespace stereomap::camera
