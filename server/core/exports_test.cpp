#include "server/core/exports.hpp"

#include <gtest/gtest.h>

#include <cstring>

#include "testing/synthetic.hpp"

namespace stereomap::core {
namespace {

// Two vehicles' poses and one wall, fused.
class Exports : public ::testing::Test {
 protected:
  void SetUp() override {
    session_.addPose({"v1", 1'000'000'000, common::Rigid3::identity()});
    common::Rigid3 moved;
    moved.translation = {1, 2, 3};
    session_.addPose({"v2", 2'500'000'000, moved});
    ASSERT_TRUE(
        session_.enqueue(FusionJob{"v1", 0, 1'000'000'000, testing::planeCloud(2.05, 0.5, 0.03),
                                   common::Rigid3::identity(), 10}));
    session_.waitUntilIdle();
  }
  Session session_{"s", {.resolution = 0.1}};
};

TEST_F(Exports, EachFormatHasItsTypeAndName) {
  const auto bt = exportSession(session_, "s", {.format = "bt"});
  ASSERT_TRUE(bt) << bt.error().message;
  EXPECT_EQ(bt->name, "s.bt");
  EXPECT_EQ(bt->content.rfind("# Octomap OcTree binary file", 0), 0u);
  const auto ot = exportSession(session_, "s", {.format = "ot"});
  ASSERT_TRUE(ot);
  EXPECT_EQ(ot->content.rfind("# Octomap OcTree file", 0), 0u);
  const auto png = exportSession(session_, "s", {.format = "png"});
  ASSERT_TRUE(png) << png.error().message;
  EXPECT_EQ(png->content_type, "image/png");
  EXPECT_EQ(png->content.substr(1, 3), "PNG");
  const auto tum = exportSession(session_, "s", {.format = "tum"});
  ASSERT_TRUE(tum);
  EXPECT_EQ(tum->name, "s-v1.tum");  // the first vehicle's
  EXPECT_EQ(tum->content_type, "text/plain");
  const auto second = exportSession(session_, "s", {.format = "tum", .vehicle = "v2"});
  ASSERT_TRUE(second);
  EXPECT_EQ(second->name, "s-v2.tum");
  EXPECT_EQ(second->content.rfind("2.500000000 1.000000 2.000000 3.000000", 0), 0u)
      << second->content;
}

TEST_F(Exports, WhatCannotBeExportedIsNamed) {
  const auto vehicle = exportSession(session_, "s", {.format = "tum", .vehicle = "v9"});
  ASSERT_FALSE(vehicle);
  EXPECT_EQ(vehicle.error().code, common::ErrorCode::kNotFound);
  EXPECT_NE(vehicle.error().message.find("no vehicle 'v9'"), std::string::npos);
  const auto format = exportSession(session_, "s", {.format = "las"});
  ASSERT_FALSE(format);
  EXPECT_EQ(format.error().code, common::ErrorCode::kInvalidArgument);
  const auto band = occupancyPng(session_, 5.0, 6.0);
  ASSERT_FALSE(band);
  EXPECT_EQ(band.error().code, common::ErrorCode::kNotFound);
}

TEST_F(Exports, APlyHoldsEveryOccupiedVoxelsCentre) {
  const auto voxels = session_.occupiedVoxels();
  ASSERT_GT(voxels.size(), 50u);
  const std::string ply = occupiedPly(session_);
  const size_t header = ply.find("end_header\n") + 11;
  ASSERT_EQ(ply.size() - header, voxels.size() * 12);  // three floats per voxel
  float first[3];
  std::memcpy(first, ply.data() + header, sizeof(first));
  EXPECT_FLOAT_EQ(first[0], static_cast<float>((voxels[0].x + 0.5) * 0.1));
  EXPECT_FLOAT_EQ(first[2], static_cast<float>((voxels[0].z + 0.5) * 0.1));
}

TEST_F(Exports, TrajectoriesAreOneVehiclesOrAll) {
  EXPECT_EQ(trajectoryTum(session_, "v1"),
            "1.000000000 0.000000 0.000000 0.000000 0.000000000 0.000000000 0.000000000 "
            "1.000000000\n");
  const std::string all = trajectoryTum(session_);
  EXPECT_EQ(std::count(all.begin(), all.end(), '\n'), 2);
  EXPECT_EQ(trajectoryTum(session_, "nobody"), "");
}

}  // namespace
}  // namespace stereomap::core
