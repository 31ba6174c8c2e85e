#include "onboard/camera/calibration.hpp"

#include <gtest/gtest.h>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/video/tracking.hpp>
#include "testing/data.hpp"

#include <chrono>
#include <fstream>

#include "common/statistics.hpp"
#include "onboard/camera/chessboard.hpp"
#include "onboard/camera/rectifier.hpp"

namespace stereomap::camera {
namespace {

namespace fs = std::filesystem;
const fs::path kData = testing::kDataDir;

#define SKIP_WITHOUT(path) STEREOMAP_SKIP_WITHOUT(path)

class TempDir {
 public:
  TempDir() : path_(fs::temp_directory_path() / ("stereomap-calib-" + std::to_string(::getpid()))) {
    fs::create_directories(path_);
  }
  ~TempDir() { fs::remove_all(path_); }
  fs::path operator/(const std::string& name) const { return path_ / name; }

 private:
  fs::path path_;
};

void writeText(const fs::path& path, const std::string& text) { std::ofstream(path) << text; }

StereoCalibration sample() {
  StereoCalibration c;
  c.image_size = {640, 480};
  c.left.K = cv::Matx33d(500, 0, 320, 0, 501, 240, 0, 0, 1);
  c.right.K = cv::Matx33d(502, 0, 322, 0, 503, 241, 0, 0, 1);
  c.left.distortion = (cv::Mat_<double>(1, 5) << -0.2, 0.05, 0.001, -0.001, 0.0);
  c.right.distortion = (cv::Mat_<double>(1, 5) << -0.21, 0.04, 0.0, 0.001, 0.0);
  cv::Rodrigues(cv::Vec3d(0.01, -0.02, 0.005), c.R);
  c.T = cv::Vec3d(-0.12, 0.001, 0.002);
  return c;
}

TEST(Calibration, OurFormatRoundTrips) {
  TempDir dir;
  ASSERT_TRUE(writeCalibration(dir / "rig.yaml", sample()).ok());
  auto back = readCalibration(dir / "rig.yaml");
  ASSERT_TRUE(back.ok()) << back.error().message;
  EXPECT_EQ(back->image_size, cv::Size(640, 480));
  EXPECT_LT(cv::norm(back->left.K, sample().left.K), 1e-12);
  EXPECT_LT(cv::norm(back->right.distortion, sample().right.distortion), 1e-12);
  EXPECT_LT(cv::norm(back->R, sample().R), 1e-12);
  EXPECT_LT(cv::norm(back->T, sample().T), 1e-12);
}

TEST(Calibration, ReadsOpenCvStereoCalibFilesSplitOrJoined) {
  TempDir dir;
  const auto c = sample();
  {
    cv::FileStorage intrinsics((dir / "intrinsics.yml").string(), cv::FileStorage::WRITE);
    intrinsics << "M1" << cv::Mat(c.left.K) << "D1" << c.left.distortion << "M2"
               << cv::Mat(c.right.K) << "D2" << c.right.distortion;
    cv::FileStorage extrinsics((dir / "extrinsics.yml").string(), cv::FileStorage::WRITE);
    extrinsics << "R" << cv::Mat(c.R) << "T" << cv::Mat(c.T);
  }
  auto split = readCalibration(dir / "intrinsics.yml");
  ASSERT_TRUE(split.ok()) << split.error().message;
  EXPECT_LT(cv::norm(split->T, c.T), 1e-12);
  EXPECT_EQ(split->image_size, cv::Size());  // stereo_calib does not store it
  {
    cv::FileStorage joined((dir / "joined.xml").string(), cv::FileStorage::WRITE);
    joined << "M1" << cv::Mat(c.left.K) << "D1" << c.left.distortion << "M2" << cv::Mat(c.right.K)
           << "D2" << c.right.distortion << "R" << cv::Mat(c.R) << "T" << cv::Mat(c.T);
  }
  auto joined = readCalibration(dir / "joined.xml");
  ASSERT_TRUE(joined.ok()) << joined.error().message;
  EXPECT_LT(cv::norm(joined->R, c.R), 1e-12);
}

TEST(Calibration, BadFilesNameTheFileAndTheField) {
  TempDir dir;
  auto expectError = [](const fs::path& path, const std::string& needle) {
    auto result = readCalibration(path);
    ASSERT_FALSE(result.ok()) << path;
    EXPECT_NE(result.error().message.find(path.string()), std::string::npos)
        << result.error().message;
    EXPECT_NE(result.error().message.find(needle), std::string::npos) << result.error().message;
  };
  expectError(dir / "missing.yaml", "no such calibration file");
  writeText(dir / "garbage.yaml", "%YAML:1.0\nfoo: [1, 2\n");
  expectError(dir / "garbage.yaml", "cannot be parsed");
  writeText(dir / "list.yaml", "%YAML:1.0\n- 1\n- 2\n");
  expectError(dir / "list.yaml", "its top level is not a map");
  writeText(dir / "unknown.yaml", "%YAML:1.0\nfoo: 1\n");
  expectError(dir / "unknown.yaml", "not a known calibration format");

  auto broken = sample();
  ASSERT_TRUE(writeCalibration(dir / "ok.yaml", broken).ok());
  std::ifstream in(dir / "ok.yaml");
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  writeText(dir / "no_t.yaml", text.substr(0, text.find("T: ")));
  expectError(dir / "no_t.yaml", "T is missing");
  // A size OpenCV would allocate before reading the data (50 GB): refused first.
  std::string huge = text;
  huge.replace(huge.find("cols", huge.find("R: ")), 7, "cols: 2000000000");
  writeText(dir / "huge.yaml", huge);
  expectError(dir / "huge.yaml", "R has rows or cols that are not whole numbers in 0..64");

  // OpenCV 4.6's parser loops forever on these 20 bytes (found by fuzzing): an error after the
  // parse deadline (5 s), not a hang.
  writeText(dir / "loops.yaml", "%YAML:1.\n t:d\n  \n-\n-");
  const auto started = std::chrono::steady_clock::now();
  expectError(dir / "loops.yaml", "parser did not finish within 5 s");
  EXPECT_LT(std::chrono::steady_clock::now() - started, std::chrono::seconds(30));
  // Far larger than any calibration: refused before anything parses it.
  writeText(dir / "large.yaml", "%YAML:1.0\nfoo: \"" + std::string(2 << 20, 'x') + "\"\n");
  expectError(dir / "large.yaml", "too large for a calibration file");

  broken.T = cv::Vec3d(0, 0, 0);
  EXPECT_NE(validateCalibration(broken).error().message.find("T is zero"), std::string::npos);
  broken = sample();
  broken.left.K(0, 0) = std::nan("");
  EXPECT_NE(validateCalibration(broken).error().message.find("K_left"), std::string::npos);
  broken = sample();
  broken.R = cv::Matx33d(1, 0, 0, 0, 1, 0, 0, 0.5, 1);
  EXPECT_NE(validateCalibration(broken).error().message.find("R is not a rotation"),
            std::string::npos);

  writeText(dir / "calib.txt", "P0: 1 0 2 0 0 1 2 0 0 0 1 0\nP1: 1 0 2 -0.5 0 1 2 0 0 0 1\n");
  expectError(dir / "calib.txt", "P1 has fewer than 12 numbers");
  writeText(dir / "calib2.txt", "P0: 1 0 2 0 0 1 2 0 0 0 1 0\nP1: 1 0 2 0.5 0 1 2 0 0 0 1 0\n");
  expectError(dir / "calib2.txt", "P1[0,3]");
}

TEST(Calibration, ReadsKittiCalib) {
  const fs::path path = kData / "kitti_stereo_seq2/calib.txt";
  SKIP_WITHOUT(path);
  auto c = readCalibration(path);
  ASSERT_TRUE(c.ok()) << c.error().message;
  EXPECT_TRUE(c->isRectified());
  EXPECT_DOUBLE_EQ(c->left.K(0, 0), 718.856);
  EXPECT_NEAR(c->baseline(), 386.1448 / 718.856, 1e-12);
}

TEST(Calibration, ReadsEurocSensorYamls) {
  const fs::path cam0 = kData / "euroc_v101_micro/mav0/cam0/sensor.yaml";
  SKIP_WITHOUT(cam0);
  auto c = readEurocCalibration(cam0, kData / "euroc_v101_micro/mav0/cam1/sensor.yaml");
  ASSERT_TRUE(c.ok()) << c.error().message;
  EXPECT_FALSE(c->isRectified());
  EXPECT_EQ(c->image_size, cv::Size(752, 480));
  EXPECT_NEAR(c->baseline(), 0.11008, 5e-5);  // the data set's README
  cv::Vec3d rotation;
  cv::Rodrigues(c->R, rotation);
  EXPECT_NEAR(cv::norm(rotation) * 180 / CV_PI, 0.818, 0.001);
  ASSERT_TRUE(c->T_body_left.has_value());

  auto rectifier = Rectifier::create(*c);
  ASSERT_TRUE(rectifier.ok()) << rectifier.error().message;
  EXPECT_NEAR(rectifier->camera().fx, 436.235, 0.001);
  EXPECT_NEAR(rectifier->camera().cx, 364.441, 0.001);
  EXPECT_NEAR(rectifier->camera().cy, 256.952, 0.001);
  EXPECT_NEAR(rectifier->camera().baseline, 0.11008, 5e-5);
}

// Rectified EuRoC pairs must put matched features on the same row: KLT-tracked corners
// (sub-pixel) from left to right, median |dy| over the clip. Before rectification the
// median is about 12 px, so the check can fail.
TEST(Rectifier, EurocMatchesLieOnTheSameRow) {
  const fs::path mav0 = kData / "euroc_v101_micro/mav0";
  SKIP_WITHOUT(mav0);
  auto c = readEurocCalibration(mav0 / "cam0/sensor.yaml", mav0 / "cam1/sensor.yaml");
  ASSERT_TRUE(c.ok());
  auto rectifier = Rectifier::create(*c);
  ASSERT_TRUE(rectifier.ok());
  std::vector<double> raw_dy, rectified_dy;
  auto track = [](const cv::Mat& left, const cv::Mat& right, std::vector<double>& dy) {
    std::vector<cv::Point2f> corners, tracked, back;
    cv::goodFeaturesToTrack(left, corners, 400, 0.01, 10);
    std::vector<uchar> ok, ok_back;
    std::vector<float> error;
    cv::calcOpticalFlowPyrLK(left, right, corners, tracked, ok, error, cv::Size(21, 21), 4);
    cv::calcOpticalFlowPyrLK(right, left, tracked, back, ok_back, error, cv::Size(21, 21), 4);
    for (size_t i = 0; i < corners.size(); ++i) {
      // Keep tracks that come back to where they started (a consistency check, not a row one).
      if (ok[i] && ok_back[i] && cv::norm(back[i] - corners[i]) < 0.3) {
        dy.push_back(std::abs(tracked[i].y - corners[i].y));
      }
    }
  };
  int pairs = 0;
  for (const auto& entry : fs::directory_iterator(mav0 / "cam0/data")) {
    if (pairs++ % 4 != 0) continue;  // every 4th pair: 10 of 40
    const cv::Mat left = cv::imread(entry.path().string(), cv::IMREAD_GRAYSCALE);
    const cv::Mat right =
        cv::imread((mav0 / "cam1/data" / entry.path().filename()).string(), cv::IMREAD_GRAYSCALE);
    ASSERT_FALSE(left.empty() || right.empty()) << entry.path();
    track(left, right, raw_dy);
    cv::Mat left_rect, right_rect;
    ASSERT_TRUE(rectifier->rectify(left, right, left_rect, right_rect).ok());
    track(left_rect, right_rect, rectified_dy);
  }
  auto median = [](std::vector<double> v) { return common::median(std::move(v)).value_or(0.0); };
  ASSERT_GT(rectified_dy.size(), 1000u);
  std::printf("EuRoC vertical disparity: median %.3f px raw, %.3f px rectified (%zu tracks)\n",
              median(raw_dy), median(rectified_dy), rectified_dy.size());
  EXPECT_GT(median(raw_dy), 5.0);
  EXPECT_LE(median(rectified_dy), 0.5);
}

}  // namespace
}  // namespace stereomap::camera

namespace stereomap::camera {
namespace {

// OpenCV's stereo_calib images: the data set's README measures a stereo RMS of 0.4469 px
// with the same method (per-camera calibration, then stereo with fixed intrinsics).
TEST(Chessboard, CalibratesOpenCvsStereoSampleToItsReferenceRms) {
  const fs::path dir = kData / "stereo_calib/opencv_9x6";
  SKIP_WITHOUT(dir);
  std::vector<std::pair<fs::path, fs::path>> pairs;
  for (int i = 1; i <= 14; ++i) {
    char name[16];
    std::snprintf(name, sizeof(name), "%02d.jpg", i);
    if (fs::exists(dir / ("left" + std::string(name)))) {
      pairs.emplace_back(dir / ("left" + std::string(name)), dir / ("right" + std::string(name)));
    }
  }
  ASSERT_EQ(pairs.size(), 13u);
  auto report = calibrateFromChessboards(pairs, {.inner_corners = {9, 6}, .square_m = 1.0});
  ASSERT_TRUE(report.ok()) << report.error().message;
  EXPECT_EQ(report->used_views(), 13u);
  EXPECT_NEAR(report->rms_stereo_px, 0.4469, 0.005);
  EXPECT_NEAR(report->rms_left_px, 0.4079, 0.005);
  EXPECT_NEAR(report->calibration.baseline(), 3.3449, 0.01);  // in squares
  EXPECT_NEAR(report->calibration.left.K(0, 0), 536.06, 0.5);
}

TEST(Chessboard, TooFewBoardsIsAClearError) {
  const fs::path dir = kData / "stereo_calib/opencv_9x6";
  SKIP_WITHOUT(dir);
  auto report = calibrateFromChessboards({{dir / "left01.jpg", dir / "right01.jpg"}},
                                         {.inner_corners = {7, 7}});
  ASSERT_FALSE(report.ok());
  EXPECT_NE(report.error().message.find("found in only 0 of 1"), std::string::npos);
}

}  // namespace
}  // namespace stereomap::camera
