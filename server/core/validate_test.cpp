#include "server/core/validate.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "testing/synthetic.hpp"

namespace stereomap::core {
namespace {

TEST(Validate, RejectsEachKindOfBadSampleWithItsReason) {
  const IngestLimits limits{.max_payload_bytes = 1000};
  ValidCloud cloud;
  auto frame = testing::wallFrame("s", 3.0);
  frame.payload.resize(frame.payload.size() / 2);  // truncated Draco
  EXPECT_EQ(validateCloudFrame(frame, {}, cloud)->reason, "decode_failed");
  frame = testing::wallFrame("s", 3.0);
  EXPECT_EQ(validateCloudFrame(frame, limits, cloud)->reason, "oversize");
  frame.sensor_position[1] = std::nan("");
  EXPECT_EQ(validateCloudFrame(frame, {}, cloud)->reason, "non_finite");
  frame = testing::wallFrame("s", 3.0);
  frame.sensor_orientation = {0, 0, 0, 2};
  EXPECT_EQ(validateCloudFrame(frame, {}, cloud)->reason, "bad_quaternion");
  frame = testing::wallFrame("s", 3.0);
  frame.point_count += 1;
  EXPECT_EQ(validateCloudFrame(frame, {}, cloud)->reason, "point_count_mismatch");
  frame = testing::wallFrame("../etc", 3.0);
  EXPECT_EQ(validateCloudFrame(frame, {}, cloud)->reason, "bad_id");
  frame = testing::wallFrame("s", 3.0);
  EXPECT_FALSE(validateCloudFrame(frame, {}, cloud).has_value());
  EXPECT_EQ(cloud.cloud_camera.size(), frame.point_count);

  ValidPose valid_pose;
  auto bad_pose = testing::poseAt("s", 1.0, 5);
  bad_pose.position[2] = std::numeric_limits<double>::infinity();
  EXPECT_EQ(validatePose(bad_pose, valid_pose)->reason, "non_finite");
  bad_pose = testing::poseAt("s", 1.0, 5);
  bad_pose.orientation = {std::nan(""), 0, 0, 1};
  EXPECT_EQ(validatePose(bad_pose, valid_pose)->reason, "non_finite");
  EXPECT_FALSE(validatePose(testing::poseAt("s", 1.0, 5), valid_pose).has_value());
}

TEST(Validate, PoseCorrectionsAreCheckedKeyframeByKeyframe) {
  proto::PoseCorrectionMsg correction{.vehicle_id = "v1", .session_id = "s1"};
  for (int k = 0; k < 3; ++k)
    correction.keyframes.push_back({k * 100, {1.0 * k, 0, 0}, {0, 0, 0, 1}});
  std::vector<ValidPose> out;
  ASSERT_FALSE(validatePoseCorrection(correction, out));
  ASSERT_EQ(out.size(), 3u);
  EXPECT_EQ(out[2].stamp_ns, 200);
  EXPECT_DOUBLE_EQ(out[2].T_map_body.translation.x(), 2.0);

  auto reason = [&](const proto::PoseCorrectionMsg& bad) {
    const auto rejection = validatePoseCorrection(bad, out);
    EXPECT_TRUE(out.empty());
    return rejection ? rejection->reason : std::string("accepted");
  };
  auto bad = correction;
  bad.session_id = "../x";
  EXPECT_EQ(reason(bad), "bad_id");
  bad = correction;
  bad.keyframes.clear();
  EXPECT_EQ(reason(bad), "empty");
  bad = correction;
  bad.keyframes[2].stamp_ns = 100;  // repeats the one before
  EXPECT_EQ(reason(bad), "bad_stamp");
  bad = correction;
  bad.keyframes[1].orientation = {0, 0, 0, 2};
  EXPECT_EQ(reason(bad), "bad_quaternion");
  bad = correction;
  bad.keyframes[1].position[0] = std::nan("");
  EXPECT_EQ(reason(bad), "non_finite");
  bad = correction;
  bad.keyframes.resize(proto::kMaxCorrectedKeyframes + 1);
  EXPECT_EQ(reason(bad), "oversize");
}

}  // namespace
}  // namespace stereomap::core
