// kitti:DIR, the KITTI odometry layout (image_0/, image_1/, calib.txt, times.txt, poses.txt).
#include "onboard/camera/dataset_source.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <fstream>

#include "common/trajectory.hpp"
#include "onboard/camera/detail/recorded_source.hpp"

namespace stereomap::camera {

namespace fs = std::filesystem;
using common::Rigid3;
using detail::FrameFiles;

namespace {

// KITTI poses are the left camera in frame 0's camera frame (OpenCV axes); our map is
// z-up with the body looking along +x, so the camera's axes are turned into the body's.
Rigid3 kittiBodyPose(const Rigid3& T_cv0_cvk) {
  const Rigid3 R_body_camera{common::bodyFromCameraRotation(), common::Vec3::Zero()};
  return R_body_camera * T_cv0_cvk * R_body_camera.inverse();
}

}  // namespace

common::Result<std::unique_ptr<FrameSource>> openKitti(const fs::path& dir,
                                                       const DatasetOptions& options) {
  for (const char* needed : {"image_0", "image_1"}) {
    if (!fs::is_directory(dir / needed)) {
      return common::makeError(common::ErrorCode::kNotFound,
                               "kitti:" + dir.string() + ": no " + needed +
                                   "/ folder (expected the KITTI odometry layout)");
    }
  }
  auto calibration =
      detail::calibrationOr(options, [&] { return readKittiCalibration(dir / "calib.txt"); });
  if (!calibration) return calibration.error();

  std::vector<fs::path> lefts;
  for (const auto& entry : fs::directory_iterator(dir / "image_0")) {
    if (entry.path().extension() == ".png") lefts.push_back(entry.path());
  }
  std::sort(lefts.begin(), lefts.end());
  std::vector<double> times;
  if (std::ifstream in(dir / "times.txt"); in) {
    for (double t; in >> t;) times.push_back(t);
  }
  std::vector<Rigid3> poses;  // T_cv0_cvk: the ground truth, when the sequence has it
  if (fs::exists(dir / "poses.txt")) {
    common::TrajectoryFormat format;
    auto read = common::readTrajectory(dir / "poses.txt", {}, &format);
    if (!read || format != common::TrajectoryFormat::kKitti) {
      spdlog::warn("kitti:{}: {}; ground truth ignored", dir.string(),
                   read ? "poses.txt is not 12 numbers per line" : read.error().message);
    } else {
      for (const auto& pose : *read) poses.push_back(pose.pose);
    }
  }
  if (!times.empty() && times.size() != lefts.size()) {
    spdlog::warn("kitti:{}: times.txt has {} lines for {} frames; stamps assume 10 Hz",
                 dir.string(), times.size(), lefts.size());
    times.clear();
  }
  std::vector<FrameFiles> frames;
  for (size_t i = 0; i < lefts.size(); ++i) {
    FrameFiles f{lefts[i], dir / "image_1" / lefts[i].filename()};
    const double t = times.empty() ? static_cast<double>(i) * 0.1 : times[i];
    f.stamp_ns = static_cast<int64_t>(t * 1e9);
    if (i < poses.size()) f.T_map_body = kittiBodyPose(poses[i]);
    frames.push_back(std::move(f));
  }
  const Rigid3 T_body_camera{common::bodyFromCameraRotation(), common::Vec3::Zero()};
  return detail::makeRecorded("kitti:" + dir.string(), std::move(frames), *calibration,
                              T_body_camera, detail::Clock::kFromFirstFrame, options);
}

}  // namespace stereomap::camera
