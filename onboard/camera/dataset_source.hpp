// Frame sources for real data: KITTI odometry folders, EuRoC (ASL layout), a folder of
// left/right pairs with a calibration file, and two live video devices, one file each. Each
// rectifies its frames (maps computed once) and hands out grey rectified pairs with
// ground-truth poses where the data set has them. A missing or unreadable frame is reported
// and skipped. stereomap-onboard picks one by its --source prefix (onboard/sources).
//
//   auto source = openKitti("/data/kitti/01", {});
#pragma once

#include <filesystem>
#include <memory>
#include <optional>
#include <string>

#include "common/result.hpp"
#include "onboard/camera/calibration.hpp"
#include "onboard/camera/frame_source.hpp"

namespace stereomap::camera {

struct DatasetOptions {
  // Overrides the source's own calibration (required for a folder without a calibration
  // file in it, and for cameras).
  std::optional<std::filesystem::path> calibration_file;
  uint64_t max_frames = 0;  // 0: all
  double rate_hz = 10.0;    // stamps for sources without times (folders, cameras)
};

// Each fails with a message naming what is missing, prefixed by the source as --source names
// it ("kitti:DIR: no image_0/ folder ...").
// KITTI odometry: image_0/, image_1/, calib.txt; times.txt and poses.txt when there.
common::Result<std::unique_ptr<FrameSource>> openKitti(const std::filesystem::path& dir,
                                                       const DatasetOptions& options);
// EuRoC's ASL layout: DIR/mav0 (or DIR itself) with cam0/, cam1/ and their sensor.yaml.
common::Result<std::unique_ptr<FrameSource>> openEuroc(const std::filesystem::path& dir,
                                                       const DatasetOptions& options);
// left/ and right/ with the same file names, or left*/right* files, and calibration.yaml,
// calib.txt or intrinsics.yml (or --calib).
common::Result<std::unique_ptr<FrameSource>> openFolder(const std::filesystem::path& dir,
                                                        const DatasetOptions& options);
// "LEFT,RIGHT": video device numbers or paths; needs options.calibration_file.
common::Result<std::unique_ptr<FrameSource>> openCameras(const std::string& devices,
                                                         const DatasetOptions& options);

}  // namespace stereomap::camera
