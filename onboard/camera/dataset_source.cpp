#include "onboard/camera/dataset_source.hpp"

#include <spdlog/spdlog.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>

#include <algorithm>
#include <fstream>
#include <sstream>

#include "common/time.hpp"
#include "common/trajectory.hpp"
#include "onboard/camera/image_noise.hpp"
#include "onboard/camera/rectifier.hpp"

namespace stereomap::camera {

namespace fs = std::filesystem;
using common::ErrorCode;
using common::makeError;
using common::Result;
using common::Rigid3;

namespace {

// The raw left image's noise on every 10th frame (the depth step's estimate is that sparse
// too), for 8-bit grey or colour images; nullopt otherwise.
std::optional<double> rawNoise(const cv::Mat& left, uint64_t index) {
  if (index % 10 != 0) return std::nullopt;
  if (left.type() == CV_8UC1) return imageNoiseSigma(left);
  if (left.type() != CV_8UC3) return std::nullopt;
  cv::Mat grey;
  cv::cvtColor(left, grey, cv::COLOR_BGR2GRAY);
  return imageNoiseSigma(grey);
}

// One recorded frame: file paths, stamp, and ground truth when known.
struct FrameFiles {
  fs::path left, right;
  int64_t stamp_ns = 0;  // the data set's own, or from frame 0 (Clock::kFromFirstFrame)
  std::optional<Rigid3> T_map_body;
};

// Where recorded stamps count from: the data set's own clock (EuRoC), or the moment the first
// frame is taken, as a camera's would (KITTI's times.txt, a folder's frame rate): a vehicle
// that first waits for its server must not send its frames as that much older.
enum class Clock { kDataSet, kFromFirstFrame };

// A source over a list of recorded pairs: reads, rectifies, skips unreadable frames.
class RecordedSource : public FrameSource {
 public:
  RecordedSource(std::string description, std::vector<FrameFiles> frames, Rectifier rectifier,
                 std::optional<Rigid3> T_body_camera, Clock clock)
      : description_(std::move(description)),
        frames_(std::move(frames)),
        rectifier_(std::move(rectifier)),
        T_body_camera_(T_body_camera),
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

// Two live cameras grabbed together (grab both, then retrieve, to keep them close in time).
class VideoSource : public FrameSource {
 public:
  VideoSource(cv::VideoCapture left, cv::VideoCapture right, Rectifier rectifier,
              std::string description, uint64_t max_frames)
      : left_(std::move(left)),
        right_(std::move(right)),
        rectifier_(std::move(rectifier)),
        description_(std::move(description)),
        max_frames_(max_frames) {}
  const StereoCamera& camera() const override { return rectifier_.camera(); }
  std::string describe() const override { return description_; }
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
      frame.raw_noise_sigma = rawNoise(left, frame.index);
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

Result<StereoCalibration> calibrationOr(const DatasetOptions& options,
                                        const std::function<Result<StereoCalibration>()>& own) {
  if (options.calibration_file) return readCalibration(*options.calibration_file);
  return own();
}

cv::Size imageSizeOf(const fs::path& image) {
  const cv::Mat probe = cv::imread(image.string(), cv::IMREAD_UNCHANGED);
  return probe.size();
}

Result<std::unique_ptr<FrameSource>> makeRecorded(std::string description,
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

// KITTI poses are the left camera in frame 0's camera frame (OpenCV axes); our map is
// z-up with the body looking along +x, so the camera's axes are turned into the body's.
Rigid3 kittiBodyPose(const Rigid3& T_cv0_cvk) {
  const Rigid3 R_body_camera{common::bodyFromCameraRotation(), common::Vec3::Zero()};
  return R_body_camera * T_cv0_cvk * R_body_camera.inverse();
}

Result<std::unique_ptr<FrameSource>> openKitti(const fs::path& dir, const DatasetOptions& options) {
  for (const char* needed : {"image_0", "image_1"}) {
    if (!fs::is_directory(dir / needed)) {
      return makeError(ErrorCode::kNotFound, "kitti:" + dir.string() + ": no " + needed +
                                                 "/ folder (expected the KITTI odometry layout)");
    }
  }
  auto calibration =
      calibrationOr(options, [&] { return readKittiCalibration(dir / "calib.txt"); });
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
  return makeRecorded("kitti:" + dir.string(), std::move(frames), *calibration, T_body_camera,
                      Clock::kFromFirstFrame, options);
}

struct Stamped {
  int64_t stamp_ns;
  Rigid3 T;
};

// EuRoC ground truth (timestamp, p xyz, q wxyz, ...) interpolated at `stamp_ns`.
std::optional<Rigid3> interpolate(const std::vector<Stamped>& track, int64_t stamp_ns) {
  if (track.empty() || stamp_ns < track.front().stamp_ns || stamp_ns > track.back().stamp_ns) {
    return std::nullopt;
  }
  auto after = std::lower_bound(track.begin(), track.end(), stamp_ns,
                                [](const Stamped& s, int64_t t) { return s.stamp_ns < t; });
  if (after->stamp_ns == stamp_ns || after == track.begin()) return after->T;
  const auto before = after - 1;
  const double a = static_cast<double>(stamp_ns - before->stamp_ns) /
                   static_cast<double>(after->stamp_ns - before->stamp_ns);
  return common::interpolate(before->T, after->T, a);
}

Result<std::unique_ptr<FrameSource>> openEuroc(const fs::path& dir, const DatasetOptions& options) {
  const fs::path mav0 = fs::is_directory(dir / "mav0") ? dir / "mav0" : dir;
  for (const char* needed : {"cam0/data.csv", "cam1/data.csv"}) {
    if (!fs::exists(mav0 / needed)) {
      return makeError(ErrorCode::kNotFound, "euroc:" + dir.string() + ": no mav0/" + needed +
                                                 " (expected EuRoC's ASL layout)");
    }
  }
  auto calibration = calibrationOr(options, [&] {
    return readEurocCalibration(mav0 / "cam0/sensor.yaml", mav0 / "cam1/sensor.yaml");
  });
  if (!calibration) return calibration.error();

  std::vector<Stamped> truth;
  if (std::ifstream in(mav0 / "state_groundtruth_estimate0/data.csv"); in) {
    for (std::string line; std::getline(in, line);) {
      if (line.empty() || line[0] == '#') continue;
      std::replace(line.begin(), line.end(), ',', ' ');
      std::istringstream numbers(line);
      int64_t t;
      double x, y, z, qw, qx, qy, qz;
      if (numbers >> t >> x >> y >> z >> qw >> qx >> qy >> qz) {
        truth.push_back({t, {common::Quat(qw, qx, qy, qz).normalized(), common::Vec3(x, y, z)}});
      }
    }
  }
  std::vector<FrameFiles> frames;
  std::ifstream csv(mav0 / "cam0/data.csv");
  for (std::string line; std::getline(csv, line);) {
    if (line.empty() || line[0] == '#') continue;
    const size_t comma = line.find(',');
    if (comma == std::string::npos) continue;
    std::string name = line.substr(comma + 1);
    name.erase(name.find_last_not_of(" \r") + 1);
    FrameFiles f{mav0 / "cam0/data" / name, mav0 / "cam1/data" / name};
    f.stamp_ns = std::stoll(line.substr(0, comma));
    f.T_map_body = interpolate(truth, f.stamp_ns);
    frames.push_back(std::move(f));
  }
  return makeRecorded("euroc:" + dir.string(), std::move(frames), *calibration,
                      calibration->T_body_left, Clock::kDataSet, options);
}

Result<std::unique_ptr<FrameSource>> openFolder(const fs::path& dir,
                                                const DatasetOptions& options) {
  if (!fs::is_directory(dir)) {
    return makeError(ErrorCode::kNotFound, "folder:" + dir.string() + ": no such folder");
  }
  // Pairs: left/ and right/ subfolders with the same file names, or left*/right* files.
  std::vector<FrameFiles> frames;
  auto isImage = [](const fs::path& p) {
    std::string ext = p.extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
    return ext == ".png" || ext == ".jpg" || ext == ".jpeg" || ext == ".bmp" || ext == ".pgm";
  };
  std::vector<fs::path> lefts;
  if (fs::is_directory(dir / "left") && fs::is_directory(dir / "right")) {
    for (const auto& e : fs::directory_iterator(dir / "left")) {
      if (isImage(e.path())) lefts.push_back(e.path());
    }
    std::sort(lefts.begin(), lefts.end());
    for (const auto& l : lefts) frames.push_back({l, dir / "right" / l.filename()});
  } else {
    for (const auto& e : fs::directory_iterator(dir)) {
      if (isImage(e.path()) && e.path().filename().string().rfind("left", 0) == 0) {
        lefts.push_back(e.path());
      }
    }
    std::sort(lefts.begin(), lefts.end());
    for (const auto& l : lefts) {
      frames.push_back({l, dir / ("right" + l.filename().string().substr(4))});
    }
  }
  for (size_t i = 0; i < frames.size(); ++i) {
    frames[i].stamp_ns = static_cast<int64_t>(static_cast<double>(i) / options.rate_hz * 1e9);
  }
  auto calibration = calibrationOr(options, [&]() -> Result<StereoCalibration> {
    for (const char* name :
         {"calibration.yaml", "calibration.yml", "calib.txt", "intrinsics.yml"}) {
      if (fs::exists(dir / name)) return readCalibration(dir / name);
    }
    return makeError(ErrorCode::kNotFound,
                     "folder:" + dir.string() +
                         ": no calibration.yaml, calib.txt or intrinsics.yml in it; pass --calib");
  });
  if (!calibration) return calibration.error();
  return makeRecorded("folder:" + dir.string(), std::move(frames), *calibration, std::nullopt,
                      Clock::kFromFirstFrame, options);
}

Result<std::unique_ptr<FrameSource>> openCameras(const std::string& devices,
                                                 const DatasetOptions& options) {
  const size_t comma = devices.find(',');
  if (comma == std::string::npos) {
    return makeError(
        ErrorCode::kInvalidArgument,
        "camera:" + devices + ": expected camera:LEFT,RIGHT (device numbers or paths)");
  }
  if (!options.calibration_file) {
    return makeError(ErrorCode::kInvalidArgument,
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
    return makeError(ErrorCode::kUnavailable, "cannot open video device '" +
                                                  (left.isOpened() ? right_name : left_name) + "'");
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

}  // namespace

Result<std::unique_ptr<FrameSource>> openDatasetSource(const std::string& spec,
                                                       const DatasetOptions& options) {
  const size_t colon = spec.find(':');
  const std::string kind = spec.substr(0, colon);
  const std::string where = colon == std::string::npos ? "" : spec.substr(colon + 1);
  if (colon == std::string::npos || where.empty()) {
    return makeError(ErrorCode::kInvalidArgument,
                     "source '" + spec +
                         "' needs a location: kitti:DIR, euroc:DIR, folder:DIR or "
                         "camera:L,R");
  }
  if (kind == "kitti") return openKitti(where, options);
  if (kind == "euroc") return openEuroc(where, options);
  if (kind == "folder") return openFolder(where, options);
  if (kind == "camera") return openCameras(where, options);
  return makeError(ErrorCode::kInvalidArgument,
                   "unknown source '" + kind +
                       "': use sim, kitti:DIR, euroc:DIR, folder:DIR or "
                       "camera:L,R");
}

}  // namespace stereomap::camera
