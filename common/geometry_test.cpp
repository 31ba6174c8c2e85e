#include "common/geometry.hpp"

#include <gtest/gtest.h>

namespace stereomap::common {
namespace {

TEST(Rigid3, ComposeAndInverseRoundTrip) {
  Rigid3 T_a_b{Quat(Eigen::AngleAxisd(0.3, Vec3(0.2, 0.9, -0.1).normalized())), Vec3(1, -2, 3)};
  const Vec3 p_b(0.5, 1.5, -2.0);
  const Vec3 back = T_a_b.inverse() * (T_a_b * p_b);
  EXPECT_LT((back - p_b).norm(), 1e-12);
  const Rigid3 I = T_a_b * T_a_b.inverse();
  EXPECT_LT(I.translation.norm(), 1e-12);
  EXPECT_NEAR(I.rotation.angularDistance(Quat::Identity()), 0.0, 1e-12);
}

TEST(Geometry, CameraLooksAlongBodyX) {
  const Quat R_body_camera = bodyFromCameraRotation();
  EXPECT_LT((R_body_camera * Vec3(0, 0, 1) - Vec3(1, 0, 0)).norm(), 1e-12);   // forward
  EXPECT_LT((R_body_camera * Vec3(0, 1, 0) - Vec3(0, 0, -1)).norm(), 1e-12);  // down
  EXPECT_LT((R_body_camera * Vec3(1, 0, 0) - Vec3(0, -1, 0)).norm(), 1e-12);  // right
}

TEST(Geometry, UnitQuaternionCheckRejectsNanAndScale) {
  EXPECT_TRUE(isUnitQuaternion(Quat::Identity()));
  EXPECT_FALSE(isUnitQuaternion(Quat(2, 0, 0, 0)));
  EXPECT_FALSE(isUnitQuaternion(Quat(std::nan(""), 0, 0, 0)));
}

TEST(Box3, ExtendAndContain) {
  Box3 box;
  EXPECT_TRUE(box.empty());
  box.extend(Vec3(0, 0, 0));
  box.extend(Vec3(1, 2, 3));
  EXPECT_FALSE(box.empty());
  EXPECT_TRUE(box.contains(Vec3(0.5, 1, 2)));
  EXPECT_FALSE(box.contains(Vec3(0.5, 1, 3.5)));
}

}  // namespace
TEST(Geometry, InterpolateRunsFromOnePoseToTheOther) {
  const Rigid3 a{Quat::Identity(), Vec3(0, 0, 0)};
  const Rigid3 b{Quat(Eigen::AngleAxisd(1.0, Vec3::UnitZ())), Vec3(2, 4, -6)};
  EXPECT_LT((interpolate(a, b, 0).translation - a.translation).norm(), 1e-12);
  EXPECT_LT(interpolate(a, b, 1).rotation.angularDistance(b.rotation), 1e-12);
  const Rigid3 half = interpolate(a, b, 0.5);
  EXPECT_LT((half.translation - Vec3(1, 2, -3)).norm(), 1e-12);
  EXPECT_NEAR(half.rotation.angularDistance(a.rotation), 0.5, 1e-12);
}

}  // namespace stereomap::common
