// camera:LEFT,RIGHT, two live video devices (numbers or paths) and a calibration file.
#include "onboard/camera/dataset_source.hpp"

#include <spdlog/spdlog.h>
#include <opencv2/videoio.hpp>

#include <algorithm>

#include "common/time.hpp"
#include "onboard/camera/detail/recorded_source.hpp"
#include "onboard/camera/rectifier.hpp"

namespace stereomap::camera {

namespace {

// Two live cameras grabbed together (grab both, then retrieve, to keep them close in time).
class VideoSource : public FrameSource {
 public:
  // (cv::VideoCapture cannot be moved: copies share the device.)
  VideoSource(const cv::VideoCapture& left, const cv::VideoCapture& right, Rectifier rectifier,
              std::string description, uint64_t max_frames)
      : left_(left),
        right_(right),
        rectifier_(std::move(rectifier)),
        description_(std::move(description)),
        max_frames_(max_frames) {}
  const StereoCamera& camera() const override { return rectifier_.camera(); }
  std::string describe() const override { return description_; }
  bool live() const override { return true; }
  // Grabbed and dropped: the driver's buffered frames are the old ones.
  void skip(uint64_t frames) override {
    for (uint64_t i = 0; i < frames; ++i) left_.grab(), right_.grab();
  }
  std::optional<SourceFrame> next() override {
    if (max_frames_ != 0 && index_ >= max_frames_) return std::nullopt;
    for (int attempt = 0; attempt < 10; ++attempt) {
      cv::Mat left, right;
      if (!left_.grab() || !right_.grab() || !left_.retrieve(left) || !right_.retrieve(right)) {
        spdlog::warn("camera frame {}: grab failed (attempt {} of 10)", index_, attempt + 1);
        continue;
      }
      SourceFrame frame;
      frame.index = index_++;
      frame.stamp_ns = common::nowNs();
      frame.raw_noise_sigma = detail::rawNoise(left, frame.index);
      if (auto status = rectifier_.rectify(left, right, frame.left, frame.right); !status) {
        spdlog::warn("camera frame {}: {}", frame.index, status.error().message);
        continue;
      }
      return frame;
    }
    spdlog::error("the cameras stopped delivering frames");
    return std::nullopt;
  }

 private:
  cv::VideoCapture left_, right_;
  Rectifier rectifier_;
  std::string description_;
  uint64_t max_frames_;
  uint64_t index_ = 0;
};

}  // namespace

common::Result<std::unique_ptr<FrameSource>> openCameras(const std::string& devices,
                                                         const DatasetOptions& options) {
  const size_t comma = devices.find(',');
  if (comma == std::string::npos) {
    return common::makeError(
        common::ErrorCode::kInvalidArgument,
        "camera:" + devices + ": expected camera:LEFT,RIGHT (device numbers or paths)");
  }
  if (!options.calibration_file) {
    return common::makeError(common::ErrorCode::kInvalidArgument,
                             "camera: needs --calib FILE (make one with stereomap-calibrate)");
  }
  auto calibration = readCalibration(*options.calibration_file);
  if (!calibration) return calibration.error();
  auto open = [](const std::string& name) {
    cv::VideoCapture capture;
    const bool numeric = !name.empty() && std::all_of(name.begin(), name.end(), ::isdigit);
    numeric ? capture.open(std::stoi(name)) : capture.open(name);
    return capture;
  };
  const std::string left_name = devices.substr(0, comma), right_name = devices.substr(comma + 1);
  cv::VideoCapture left = open(left_name), right = open(right_name);
  if (!left.isOpened() || !right.isOpened()) {
    return common::makeError(
        common::ErrorCode::kUnavailable,
        "cannot open video device '" + (left.isOpened() ? right_name : left_name) + "'");
  }
  const cv::Size size = calibration->image_size;
  if (size.area() > 0) {
    for (auto* capture : {&left, &right}) {
      capture->set(cv::CAP_PROP_FRAME_WIDTH, size.width);
      capture->set(cv::CAP_PROP_FRAME_HEIGHT, size.height);
    }
  }
  auto rectifier = Rectifier::create(*calibration);
  if (!rectifier) return rectifier.error();
  return std::unique_ptr<FrameSource>(
      std::make_unique<VideoSource>(std::move(left), std::move(right), std::move(rectifier).value(),
                                    "camera:" + devices, options.max_frames));
}

}  // namespace stereomap::camera
