#include "onboard/camera/detail/recorded_source.hpp"

#include <spdlog/spdlog.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <sstream>

#include "common/time.hpp"
#include "onboard/camera/image_noise.hpp"
#include "onboard/camera/rectifier.hpp"

namespace stereomap::camera::detail {

namespace fs = std::filesystem;
using common::ErrorCode;
using common::makeError;
using common::Result;
using common::Rigid3;

std::optional<double> rawNoise(const cv::Mat& left, uint64_t index) {
  if (index % 10 != 0) return std::nullopt;
  if (left.type() == CV_8UC1) return imageNoiseSigma(left);
  if (left.type() != CV_8UC3) return std::nullopt;
  cv::Mat grey;
  cv::cvtColor(left, grey, cv::COLOR_BGR2GRAY);
  return imageNoiseSigma(grey);
}

namespace {

// A source over a list of recorded pairs: reads, rectifies, skips unreadable frames.
class RecordedSource : public FrameSource {
 public:
  RecordedSource(std::string description, std::vector<FrameFiles> frames, Rectifier rectifier,
                 std::optional<Rigid3> T_body_camera, Clock clock)
      : description_(std::move(description)),
        frames_(std::move(frames)),
        rectifier_(std::move(rectifier)),
        T_body_camera_(std::move(T_body_camera)),
        clock_(clock) {}

  const StereoCamera& camera() const override { return rectifier_.camera(); }
  std::string describe() const override { return description_; }

  std::optional<SourceFrame> next() override {
    while (next_ < frames_.size()) {
      const FrameFiles& files = frames_[next_++];
      const cv::Mat left = cv::imread(files.left.string(), cv::IMREAD_UNCHANGED);
      const cv::Mat right = cv::imread(files.right.string(), cv::IMREAD_UNCHANGED);
      if (left.empty() || right.empty()) {
        spdlog::warn("frame {}: cannot read {}; skipped", next_ - 1,
                     (left.empty() ? files.left : files.right).string());
        continue;
      }
      SourceFrame frame;
      frame.index = next_ - 1;
      if (clock_ == Clock::kFromFirstFrame && !first_frame_ns_) first_frame_ns_ = common::nowNs();
      frame.stamp_ns = files.stamp_ns + first_frame_ns_.value_or(0);
      frame.raw_noise_sigma = rawNoise(left, frame.index);
      if (auto status = rectifier_.rectify(left, right, frame.left, frame.right); !status) {
        spdlog::warn("frame {}: {}; skipped", frame.index, status.error().message);
        continue;
      }
      frame.T_map_body = files.T_map_body;
      frame.T_body_camera = T_body_camera_;  // the mount, with or without ground truth
      return frame;
    }
    return std::nullopt;
  }

 private:
  std::string description_;
  std::vector<FrameFiles> frames_;
  Rectifier rectifier_;
  std::optional<Rigid3> T_body_camera_;
  Clock clock_;
  std::optional<int64_t> first_frame_ns_;
  size_t next_ = 0;
};

cv::Size imageSizeOf(const fs::path& image) {
  const cv::Mat probe = cv::imread(image.string(), cv::IMREAD_UNCHANGED);
  return probe.size();
}

}  // namespace

Result<StereoCalibration> calibrationOr(const DatasetOptions& options,
                                        const std::function<Result<StereoCalibration>()>& own) {
  if (options.calibration_file) return readCalibration(*options.calibration_file);
  return own();
}

Result<std::unique_ptr<FrameSource>> makeRecorded(const std::string& description,
                                                  std::vector<FrameFiles> frames,
                                                  const StereoCalibration& calibration,
                                                  std::optional<Rigid3> T_body_raw_left,
                                                  Clock clock, const DatasetOptions& options) {
  if (frames.empty()) return makeError(ErrorCode::kNotFound, description + ": no frames found");
  if (options.max_frames != 0 && frames.size() > options.max_frames) {
    frames.resize(options.max_frames);
  }
  const cv::Size size = calibration.image_size.area() != 0 ? calibration.image_size
                                                           : imageSizeOf(frames.front().left);
  if (size.area() == 0) {
    return makeError(ErrorCode::kCorrupt, "cannot read " + frames.front().left.string());
  }
  auto rectifier = Rectifier::create(calibration, size);
  if (!rectifier) return rectifier.error();
  // The rectified left camera is the raw one turned by leftRotation(): p_rect = R p_raw.
  std::optional<Rigid3> T_body_camera;
  if (T_body_raw_left) {
    const cv::Matx33d R = rectifier->leftRotation().t();
    Eigen::Matrix3d R_raw_rect;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) R_raw_rect(r, c) = R(r, c);
    }
    T_body_camera = *T_body_raw_left * Rigid3{common::Quat(R_raw_rect), common::Vec3::Zero()};
  }
  std::ostringstream text;
  text << description << ", " << frames.size() << " frames, " << size.width << "x" << size.height
       << (rectifier->passThrough() ? " (already rectified)" : " (rectified)") << ", baseline "
       << rectifier->camera().baseline;
  return std::unique_ptr<FrameSource>(std::make_unique<RecordedSource>(
      text.str(), std::move(frames), std::move(rectifier).value(), T_body_camera, clock));
}

}  // namespace stereomap::camera::detail
