// Cross-process: a real stereomap-server receives bad samples over real DDS (a truncated
// Draco payload, a NaN pose, an oversize cloud, a non-unit quaternion) between good ones.
// It must stay up, count each rejection with its reason, and keep fusing the good samples.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "proto/cloud_codec.hpp"
#include "proto/dds.hpp"
#include "tests/support/server_fixture.hpp"
#include "tests/support/synthetic.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;

constexpr int kDomain = 72;
const std::string kSession = "bad-input";

proto::CloudFrameMsg wallFrame(uint64_t seq, double x) {
  return planeFrame("tester", kSession, seq, planeCloud(x, 1.0, 0.02));
}

proto::PoseMsg goodPose(uint64_t seq) {
  proto::PoseMsg pose;
  pose.vehicle_id = "tester";
  pose.session_id = kSession;
  pose.seq = seq;
  pose.stamp_ns = 1'000'000'000 + static_cast<int64_t>(seq);
  pose.position = {0.1 * static_cast<double>(seq), 0, 1};
  return pose;
}

double metric(const std::string& metrics, const std::string& series) {
  const size_t at = metrics.find(series + " ");
  return at == std::string::npos ? 0.0 : std::atof(metrics.c_str() + at + series.size() + 1);
}

TEST(BadInput, ServerRejectsBadSamplesAndKeepsFusingGoodOnes) {
  ServerProcess server(kDomain);
  auto participant =
      proto::Participant::create({.domain_id = kDomain, .config_file = STEREOMAP_DDS_CONFIG});
  ASSERT_TRUE(participant.ok()) << participant.error().message;
  auto clouds = proto::Writer<proto::CloudFrameMsg>::create(*participant);
  auto poses = proto::Writer<proto::PoseMsg>::create(*participant);
  ASSERT_TRUE(clouds.ok() && poses.ok());
  ASSERT_TRUE((*clouds)->waitForReaders(1, 20s)) << "the server never subscribed";
  ASSERT_TRUE((*poses)->waitForReaders(1, 20s));

  ASSERT_TRUE((*clouds)->write(wallFrame(0, 2.05)).ok());
  ASSERT_TRUE((*poses)->write(goodPose(0)).ok());

  auto truncated = wallFrame(1, 2.55);
  truncated.payload.resize(truncated.payload.size() / 3);
  ASSERT_TRUE((*clouds)->write(truncated).ok());

  auto nan_pose = goodPose(1);
  nan_pose.position[1] = std::nan("");
  ASSERT_TRUE((*poses)->write(nan_pose).ok());

  auto oversize = wallFrame(2, 2.55);  // 5 MiB: over the server's 4 MiB default limit
  oversize.payload.resize(5u << 20, 0xAB);
  ASSERT_TRUE((*clouds)->write(oversize).ok());

  auto tilted = wallFrame(3, 2.55);
  tilted.sensor_orientation = {0.5, 0.5, 0.5, 0.9};
  ASSERT_TRUE((*clouds)->write(tilted).ok());

  ASSERT_TRUE((*clouds)->write(wallFrame(4, 3.05)).ok());
  ASSERT_TRUE((*poses)->write(goodPose(2)).ok());

  std::string metrics;
  const bool counted = waitUntil(30s, [&] {
    metrics = server.get("/metrics").body;
    return metric(metrics, "stereomap_session_frames_fused{session=\"bad-input\"}") == 2 &&
           metric(metrics,
                  "stereomap_samples_rejected_total{topic=\"Pose\",reason=\"non_finite\"}") == 1 &&
           metric(metrics, "stereomap_samples_accepted_total{topic=\"Pose\"}") == 2;
  });
  ASSERT_TRUE(counted) << metrics << "\n" << server.log();
  EXPECT_EQ(
      metric(metrics,
             "stereomap_samples_rejected_total{topic=\"CloudFrame\",reason=\"decode_failed\"}"),
      1);
  EXPECT_EQ(
      metric(metrics, "stereomap_samples_rejected_total{topic=\"CloudFrame\",reason=\"oversize\"}"),
      1);
  EXPECT_EQ(
      metric(metrics,
             "stereomap_samples_rejected_total{topic=\"CloudFrame\",reason=\"bad_quaternion\"}"),
      1);
  EXPECT_EQ(metric(metrics, "stereomap_samples_accepted_total{topic=\"CloudFrame\"}"), 2);

  // The good frames are in the map: both walls, nothing of the rejected ones at x = 2.55.
  const auto session = nlohmann::json::parse(server.get("/api/sessions/" + kSession).body);
  EXPECT_EQ(session["frames"], 2);
  EXPECT_EQ(session["poses"], 2);
  EXPECT_NEAR(session["bounds"]["min"][0].get<double>(), 2.0, 1e-6);
  EXPECT_NEAR(session["bounds"]["max"][0].get<double>(), 3.1, 1e-6);
  const std::string log = server.log();
  EXPECT_NE(log.find("Draco payload does not decode"), std::string::npos) << log;
  EXPECT_NE(log.find("pose position is not finite"), std::string::npos) << log;
  EXPECT_NE(log.find("exceeds the limit"), std::string::npos) << log;

  EXPECT_EQ(server.get("/healthz").status, 200);
  EXPECT_TRUE(server.process().running());
  EXPECT_EQ(server.process().stop(), 0) << "the server should stop cleanly on SIGTERM";
}

}  // namespace
}  // namespace stereomap::testing
