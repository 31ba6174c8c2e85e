#include "onboard/camera/dataset_source.hpp"

#include <gtest/gtest.h>

#include "onboard/camera/image_noise.hpp"
#include "testing/data.hpp"

#include <chrono>
#include <fstream>
#include <thread>

#include "common/time.hpp"

namespace stereomap::camera {
namespace {

namespace fs = std::filesystem;
using common::Result;
const fs::path kData = testing::kDataDir;
#define SKIP_WITHOUT(path) STEREOMAP_SKIP_WITHOUT(path)

TEST(DatasetSource, KittiFramesArriveRectifiedWithGroundTruth) {
  const fs::path dir = kData / "kitti_stereo_seq2";
  SKIP_WITHOUT(dir);
  auto source = openKitti(dir, {});
  ASSERT_TRUE(source.ok()) << source.error().message;
  EXPECT_DOUBLE_EQ((*source)->camera().fx, 718.856);
  EXPECT_NEAR((*source)->camera().baseline, 0.5372, 1e-4);
  size_t frames = 0;
  std::optional<SourceFrame> last;
  while (auto frame = (*source)->next()) {
    ASSERT_EQ(frame->left.size(), cv::Size(1241, 376));
    ASSERT_EQ(frame->left.type(), CV_8UC1);
    ASSERT_TRUE(frame->T_map_body.has_value());
    if (frames == 0) {
      EXPECT_LT(frame->T_map_body->translation.norm(), 1e-9);
    }
    ++frames;
    last = std::move(frame);
  }
  EXPECT_EQ(frames, 51u);
  // The car drives forward (map +x at the start) and turns right (towards -y); z is up.
  // poses.txt ends at camera-frame (40.02, -0.86, 19.93): x right, y down, z ahead.
  EXPECT_NEAR(last->T_map_body->translation.x(), 19.93, 0.01);
  EXPECT_NEAR(last->T_map_body->translation.y(), -40.02, 0.01);
  EXPECT_NEAR(last->T_map_body->translation.z(), 0.86, 0.01);
  const common::Vec3 forward = last->T_map_body->rotation * common::Vec3::UnitX();
  EXPECT_LT(std::atan2(forward.y(), forward.x()) * 180 / M_PI, -80.0);  // right turn ~98°
}

TEST(DatasetSource, EurocFramesAreRectifiedAndPosed) {
  const fs::path dir = kData / "euroc_v101_micro";
  SKIP_WITHOUT(dir);
  auto source = openEuroc(dir, {.max_frames = 5});
  ASSERT_TRUE(source.ok()) << source.error().message;
  EXPECT_NEAR((*source)->camera().fx, 436.235, 1e-3);
  size_t frames = 0;
  while (auto frame = (*source)->next()) {
    EXPECT_EQ(frame->left.size(), cv::Size(752, 480));
    // The raw images' noise, every 10th frame: 1.92 measured where the image is flattest
    // (1.7-1.8 over all pixels, texture included, before); undistortion's interpolation
    // leaves about half of it for the rectified images.
    if (frame->index % 10 == 0) {
      ASSERT_TRUE(frame->raw_noise_sigma.has_value());
      EXPECT_NEAR(*frame->raw_noise_sigma, 1.92, 0.15);
      EXPECT_LT(imageNoiseSigma(frame->left), 0.8 * *frame->raw_noise_sigma);
    } else {
      EXPECT_FALSE(frame->raw_noise_sigma.has_value());
    }
    ASSERT_TRUE(frame->T_map_body && frame->T_body_camera);
    // The Vicon room's ground truth: the vehicle stands about 0.95 m above the origin.
    EXPECT_NEAR(frame->T_map_body->translation.z(), 0.947, 0.01);
    ++frames;
  }
  EXPECT_EQ(frames, 5u);
}

TEST(DatasetSource, FolderReportsAndSkipsAMissingFrame) {
  const fs::path kitti = kData / "kitti_stereo_seq2";
  SKIP_WITHOUT(kitti);
  const fs::path dir =
      fs::temp_directory_path() / ("stereomap-folder-" + std::to_string(::getpid()));
  fs::create_directories(dir);
  for (const char* name : {"000000.png", "000001.png", "000002.png"}) {
    fs::copy_file(kitti / "image_0" / name, dir / ("left_" + std::string(name)));
    fs::copy_file(kitti / "image_1" / name, dir / ("right_" + std::string(name)));
  }
  fs::copy_file(kitti / "calib.txt", dir / "calib.txt");
  fs::remove(dir / "right_000001.png");
  auto source = openFolder(dir, {});
  ASSERT_TRUE(source.ok()) << source.error().message;
  std::vector<uint64_t> indices;
  while (auto frame = (*source)->next()) {
    indices.push_back(frame->index);
    EXPECT_FALSE(frame->T_map_body.has_value());  // a folder has no poses
  }
  EXPECT_EQ(indices, (std::vector<uint64_t>{0, 2}));
  fs::remove_all(dir);
}

// Without ground truth (KITTI's test sequences have no poses.txt) a frame still carries the
// camera's mount, and stamps count from the first frame taken, not from opening the source.
TEST(DatasetSource, FramesWithoutGroundTruthKeepTheMountAndStampFromTheFirstFrame) {
  const fs::path kitti = kData / "kitti_stereo_seq2";
  SKIP_WITHOUT(kitti);
  const fs::path dir =
      fs::temp_directory_path() / ("stereomap-kitti-" + std::to_string(::getpid()));
  fs::create_directories(dir / "image_0");
  fs::create_directories(dir / "image_1");
  for (const char* name : {"000000.png", "000001.png"}) {
    fs::copy_file(kitti / "image_0" / name, dir / "image_0" / name);
    fs::copy_file(kitti / "image_1" / name, dir / "image_1" / name);
  }
  fs::copy_file(kitti / "calib.txt", dir / "calib.txt");
  auto source = openKitti(dir, {});
  ASSERT_TRUE(source.ok()) << source.error().message;
  std::this_thread::sleep_for(std::chrono::milliseconds(300));  // a wait for the server
  const int64_t before = common::nowNs();
  auto first = (*source)->next();
  auto second = (*source)->next();
  ASSERT_TRUE(first && second);
  for (const auto* frame : {&*first, &*second}) {
    EXPECT_FALSE(frame->T_map_body.has_value());
    ASSERT_TRUE(frame->T_body_camera.has_value());
    // KITTI's camera looks along the body's x axis.
    EXPECT_NEAR((frame->T_body_camera->rotation * common::Vec3::UnitZ()).x(), 1.0, 1e-9);
  }
  EXPECT_GE(first->stamp_ns, before);
  EXPECT_LT(first->stamp_ns, before + 200'000'000);
  EXPECT_EQ(second->stamp_ns - first->stamp_ns, 100'000'000);  // 10 Hz without times.txt
  fs::remove_all(dir);
}

TEST(DatasetSource, WhatIsMissingIsAClearError) {
  auto expectError = [](const Result<std::unique_ptr<FrameSource>>& source,
                        const std::string& needle) {
    ASSERT_FALSE(source.ok()) << needle;
    EXPECT_NE(source.error().message.find(needle), std::string::npos) << source.error().message;
  };
  expectError(openKitti("/nonexistent", {}), "kitti:/nonexistent: no image_0/ folder");
  expectError(openEuroc("/nonexistent", {}), "euroc:/nonexistent: no mav0/cam0/data.csv");
  expectError(openFolder("/nonexistent", {}), "folder:/nonexistent: no such folder");
  expectError(openCameras("0", {}), "expected camera:LEFT,RIGHT");
  expectError(openCameras("0,1", {}), "needs --calib");
}

}  // namespace
}  // namespace stereomap::camera
