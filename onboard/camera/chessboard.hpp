// Stereo calibration from chessboard image pairs (the method of OpenCV's stereo_calib
// sample): corners found and refined per view, each camera calibrated on its own, then the
// pair with the intrinsics held fixed. Views where the board is not found in both images
// are reported and left out.
#pragma once

#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include "common/result.hpp"
#include "onboard/camera/calibration.hpp"

namespace stereomap::camera {

struct ChessboardOptions {
  cv::Size inner_corners{9, 6};
  double square_m = 1.0;  // edge of one square; T comes out in the same unit
};

struct ChessboardView {
  std::filesystem::path left, right;
  bool used = false;
  std::string reason;  // why it was left out
  double rms_left_px = 0, rms_right_px = 0;
};

struct ChessboardReport {
  StereoCalibration calibration;
  std::vector<ChessboardView> views;
  double rms_left_px = 0, rms_right_px = 0, rms_stereo_px = 0;
  size_t used_views() const;
};

using ProgressCallback = std::function<void(size_t done, size_t total)>;

common::Result<ChessboardReport> calibrateFromChessboards(
    const std::vector<std::pair<std::filesystem::path, std::filesystem::path>>& pairs,
    const ChessboardOptions& options, const ProgressCallback& progress = {});

}  // namespace stereomap::camera
