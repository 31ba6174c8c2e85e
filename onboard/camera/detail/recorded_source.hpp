// What the recorded sources (kitti:, euroc:, folder:) share, and the raw images' noise that
// every source of real images measures. Included by onboard/camera's sources only.
#pragma once

#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "common/geometry.hpp"
#include "common/result.hpp"
#include "onboard/camera/calibration.hpp"
#include "onboard/camera/dataset_source.hpp"
#include "onboard/camera/frame_source.hpp"

namespace stereomap::camera::detail {

// The raw left image's noise on every 10th frame (the depth step's estimate is that sparse
// too), for 8-bit grey or colour images; nullopt otherwise.
std::optional<double> rawNoise(const cv::Mat& left, uint64_t index);

// One recorded frame: file paths, stamp, and ground truth when known.
struct FrameFiles {
  std::filesystem::path left, right;
  int64_t stamp_ns = 0;  // the data set's own, or from frame 0 (Clock::kFromFirstFrame)
  std::optional<common::Rigid3> T_map_body;
};

// Where recorded stamps count from: the data set's own clock (EuRoC), or the moment the first
// frame is taken, as a camera's would (KITTI's times.txt, a folder's frame rate): a vehicle
// that first waits for its server must not send its frames as that much older.
enum class Clock { kDataSet, kFromFirstFrame };

// The calibration file the options name, else the source's own.
common::Result<StereoCalibration> calibrationOr(
    const DatasetOptions& options, const std::function<common::Result<StereoCalibration>()>& own);

// A source over recorded pairs: read, rectified with `calibration`, unreadable frames skipped
// (and said so). T_body_raw_left: the raw left camera's mount, when the data set gives it.
common::Result<std::unique_ptr<FrameSource>> makeRecorded(
    const std::string& description, std::vector<FrameFiles> frames,
    const StereoCalibration& calibration, std::optional<common::Rigid3> T_body_raw_left,
    Clock clock, const DatasetOptions& options);

}  // namespace stereomap::camera::detail
