#include "server/core/pose_correction.hpp"

#include <gtest/gtest.h>

#include <cmath>

namespace stereomap::core {
namespace {

using common::Quat;
using common::Rigid3;
using common::Vec3;

constexpr int64_t kStep = 100'000'000;  // 10 Hz

// A vehicle flying along x from `start`, one pose per frame.
std::vector<StampedBodyPose> flight(const Vec3& start, int frames) {
  std::vector<StampedBodyPose> sent;
  for (int i = 0; i < frames; ++i) {
    sent.push_back(
        {i * kStep,
         {Quat(Eigen::AngleAxisd(0.01 * i, Vec3::UnitZ())), start + Vec3(0.3 * i, 0, 0)}});
  }
  return sent;
}

TEST(PoseCorrection, KeyframesLandExactlyWhereCorrected) {
  const auto sent = flight(Vec3::Zero(), 30);
  std::vector<StampedBodyPose> keyframes;
  for (const int k : {0, 10, 20}) {
    keyframes.push_back({sent[k].stamp_ns, Rigid3{Quat(Eigen::AngleAxisd(0.02 * k, Vec3::UnitY())),
                                                  Vec3(0.1 * k, -0.2, 0.05)} *
                                               sent[k].T_map_body});
  }
  const auto correction = PoseCorrection::create(sent, keyframes);
  ASSERT_TRUE(correction) << correction.error().message;
  for (const auto& k : keyframes) {
    const Rigid3 sent_pose = sent[static_cast<size_t>(k.stamp_ns / kStep)].T_map_body;
    const Rigid3 corrected = correction->delta(k.stamp_ns) * sent_pose;
    EXPECT_LT((corrected.translation - k.T_map_body.translation).norm(), 1e-9);
    EXPECT_LT(corrected.rotation.angularDistance(k.T_map_body.rotation), 1e-9);
  }
  // After the last keyframe, its correction alone: the motion since it is kept as sent.
  const Rigid3 late = correction->delta(sent[25].stamp_ns) * sent[25].T_map_body;
  const Rigid3 expected =
      keyframes[2].T_map_body * sent[20].T_map_body.inverse() * sent[25].T_map_body;
  EXPECT_LT((late.translation - expected.translation).norm(), 1e-9);
}

TEST(PoseCorrection, AShiftMovesEverySampleByIt) {
  const auto sent = flight(Vec3::Zero(), 20);
  const Vec3 shift(1.0, -2.0, 0.5);
  std::vector<StampedBodyPose> keyframes;
  for (const int k : {3, 9, 15}) {
    keyframes.push_back(
        {sent[k].stamp_ns, {sent[k].T_map_body.rotation, sent[k].T_map_body.translation + shift}});
  }
  const auto correction = PoseCorrection::create(sent, keyframes);
  ASSERT_TRUE(correction);
  for (const int64_t stamp : {int64_t{0}, 5 * kStep + kStep / 3, 12 * kStep, 19 * kStep}) {
    const Rigid3 delta = correction->delta(stamp);
    EXPECT_LT((delta.translation - shift).norm(), 1e-9) << stamp;
    EXPECT_LT(delta.rotation.angularDistance(Quat::Identity()), 1e-9) << stamp;
  }
}

// 100 m from the map's origin, one keyframe turned by 1 degree about the vehicle and the next
// left as it was: half-way, the vehicle moves by centimetres. Blending the two map-frame
// deltas instead would swing it by about 0.9 m (100 m x 0.5 degree).
TEST(PoseCorrection, FarFromTheOriginATurnDoesNotSwingTheVehicle) {
  const auto sent = flight(Vec3(100, 0, 0), 21);
  const Rigid3& a = sent[0].T_map_body;
  const Rigid3 turned{a.rotation * Quat(Eigen::AngleAxisd(M_PI / 180, Vec3::UnitZ())),
                      a.translation};
  const auto correction = PoseCorrection::create(sent, {{sent[0].stamp_ns, turned}, sent[20]});
  ASSERT_TRUE(correction);
  const Rigid3 middle = correction->delta(sent[10].stamp_ns) * sent[10].T_map_body;
  // Through keyframe a the turn moves frame 10 (3 m ahead of a) by 3 m x 1 degree; blended
  // half with b's (none): about 2.6 cm, not 0.9 m.
  EXPECT_LT((middle.translation - sent[10].T_map_body.translation).norm(), 0.03);
}

TEST(PoseCorrection, RefusesWhatItCannotApply) {
  const auto sent = flight(Vec3::Zero(), 5);
  EXPECT_FALSE(PoseCorrection::create(sent, {}));
  EXPECT_FALSE(PoseCorrection::create(sent, {{kStep / 2, sent[0].T_map_body}}));  // not sent
  EXPECT_FALSE(PoseCorrection::create(sent, {sent[1], sent[1]}));                 // twice
  EXPECT_FALSE(
      PoseCorrection::create(sent, {{sent[1].stamp_ns, {Quat(0, 0, 0, 0), Vec3::Zero()}}}));
  auto nan = sent;
  nan[2].T_map_body.translation.x() = std::nan("");
  EXPECT_FALSE(PoseCorrection::create(nan, {sent[1]}));
  EXPECT_TRUE(PoseCorrection::create(sent, {sent[1]}));
}

// A keyframe whose pose never reached the server is left out; the others still correct.
TEST(PoseCorrection, AKeyframeWhosePoseNeverArrivedIsLeftOut) {
  const auto sent = flight(Vec3::Zero(), 5);
  Rigid3 moved = sent[3].T_map_body;
  moved.translation.z() += 0.5;
  const auto correction =
      PoseCorrection::create(sent, {{kStep / 2, sent[0].T_map_body}, {sent[3].stamp_ns, moved}});
  ASSERT_TRUE(correction);
  EXPECT_NEAR((correction->delta(sent[3].stamp_ns) * sent[3].T_map_body).translation.z(),
              moved.translation.z(), 1e-9);
}

}  // namespace
}  // namespace stereomap::core
