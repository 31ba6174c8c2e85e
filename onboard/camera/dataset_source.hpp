// Frame sources for real data: KITTI odometry folders, EuRoC (ASL layout), a folder of
// left/right pairs with a calibration file, and two live video devices. Each rectifies its
// frames (maps computed once) and hands out grey rectified pairs with ground-truth poses
// where the data set has them. A missing or unreadable frame is reported and skipped.
//
//   auto source = openDatasetSource("kitti:/data/kitti/01", {});
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
  // Overrides the source's own calibration (required for folder: without a calibration
  // file in the folder, and for camera:).
  std::optional<std::filesystem::path> calibration_file;
  uint64_t max_frames = 0;  // 0: all
  double rate_hz = 10.0;    // stamps for sources without times (folder:, camera:)
};

// spec: "kitti:DIR", "euroc:DIR", "folder:DIR" or "camera:L,R" (video device numbers or
// paths). Fails with a message naming what is missing.
common::Result<std::unique_ptr<FrameSource>> openDatasetSource(const std::string& spec,
                                                               const DatasetOptions& options);

}  // namespace stereomap::camera
