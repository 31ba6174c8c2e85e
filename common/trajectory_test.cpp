// Trajectory files: what is written reads back, whatever the numbers' size.
#include "common/trajectory.hpp"

#include <gtest/gtest.h>

#include <unistd.h>

#include <filesystem>

namespace stereomap::common {
namespace {

TEST(Trajectory, TumTextReadsBackEvenForHugePositions) {
  Trajectory poses = {{1732690000.25, {Quat::Identity(), Vec3(1, 2, 3)}},
                      {1732690000.35, {Quat(0, 0, 0, 1), Vec3(1e300, -1e300, 0)}}};
  const std::string text = tumText(poses);
  const auto path = std::filesystem::temp_directory_path() /
                    ("stereomap-trajectory-test-" + std::to_string(::getpid()) + ".txt");
  ASSERT_TRUE(writeText(path, text).ok());
  TrajectoryFormat format;
  auto read = readTrajectory(path, {}, &format);
  std::filesystem::remove(path);
  ASSERT_TRUE(read.ok()) << read.error().message;
  EXPECT_EQ(format, TrajectoryFormat::kTum);
  ASSERT_EQ(read->size(), 2u);
  EXPECT_DOUBLE_EQ((*read)[1].pose.translation.x(), 1e300);
  EXPECT_NEAR((*read)[0].t, 1732690000.25, 1e-6);
}

}  // namespace
}  // namespace stereomap::common
