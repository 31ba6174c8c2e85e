#include "server/core/map_server.hpp"

#include <gtest/gtest.h>

#include <cstdio>
#include <thread>

#include "common/time.hpp"
#include "proto/wire_size.hpp"
#include "testing/synthetic.hpp"

namespace stereomap::core {
namespace {

TEST(MapServer, FusesGoodFramesAndCountsBadOnes) {
  MapServer server({.resolution = 0.1});
  EXPECT_TRUE(server.ingest(testing::wallFrame("a", 2.05)));
  auto bad = testing::wallFrame("a", 2.05);
  bad.payload.resize(10);
  EXPECT_FALSE(server.ingest(bad));
  EXPECT_TRUE(server.ingest(testing::poseAt("a", 0.5, 1'000'000'000)));
  auto session = server.find("a");
  ASSERT_TRUE(session);
  session->waitUntilIdle();
  const auto status = session->status();
  EXPECT_EQ(status.frames_fused, 1u);
  EXPECT_GT(status.occupied_voxels, 50u);
  EXPECT_EQ(status.poses, 1u);
  // The live frame's lag from arrival to its tiles: one sample, shorter than the test.
  EXPECT_EQ(status.publish_lag.count(), 1u);
  EXPECT_GT(status.publish_lag.quantile(0.5), 0.0);
  EXPECT_LT(status.publish_lag.quantile(0.5), 10.0);
  EXPECT_EQ(server.metrics().get("stereomap_samples_rejected_total",
                                 {{"topic", "CloudFrame"}, {"reason", "decode_failed"}}),
            1.0);
  EXPECT_NE(server.metricsText().find("stereomap_session_occupied_voxels{session=\"a\"}"),
            std::string::npos);
  EXPECT_NE(server.metricsText().find(
                "stereomap_session_publish_lag_seconds{session=\"a\",quantile=\"0.95\"}"),
            std::string::npos);
}

// A sample proto's reader refused (an unknown enumeration) is counted under its type and
// makes no session.
TEST(MapServer, CountsSamplesTheReaderRefused) {
  MapServer server({.resolution = 0.1});
  server.refuse({"Pose", "uav-1", "a", "tracking_state has unknown value 9"});
  EXPECT_EQ(server.metrics().get("stereomap_samples_rejected_total",
                                 {{"topic", "Pose"}, {"reason", "bad_enum"}}),
            1.0);
  EXPECT_EQ(server.metrics().get("stereomap_samples_received_total", {{"topic", "Pose"}}), 1.0);
  EXPECT_EQ(server.find("a"), nullptr);
}

// A journaled frame a restored snapshot already holds is counted and claimed, not fused: its
// payload is not even decoded (most of a restart's time went there). A live frame with the
// same payload is refused.
TEST(MapServer, ACoveredFrameIsCountedWithoutDecodingItsPayload) {
  MapServer server({.resolution = 0.1});
  auto frame = testing::wallFrame("a", 2.05);
  frame.payload.resize(10);  // would not decode
  EXPECT_TRUE(server.ingest(frame, Origin::kCovered, 1));
  const auto status = server.find("a")->status();
  EXPECT_EQ(status.frames_received, 1u);
  EXPECT_EQ(status.frames_fused, 1u);                       // in the snapshot, so in the map
  EXPECT_EQ(status.occupied_voxels, 0u);                    // but not inserted again
  EXPECT_FALSE(server.ingest(frame, Origin::kCovered, 1));  // claimed: a duplicate now
  frame.seq = 1;
  frame.stamp_ns += 1;
  EXPECT_FALSE(server.ingest(frame));  // live: decoded, refused
  auto bad_pose = testing::wallFrame("a", 2.05, 2);
  bad_pose.sensor_orientation = {0, 0, 0, 2};
  EXPECT_FALSE(server.ingest(bad_pose, Origin::kCovered, 2));  // the fields are still checked
}

// What each vehicle's accepted samples took on the link, as the vehicle counts it.
TEST(MapServer, CountsEachVehiclesBytes) {
  MapServer server({.resolution = 0.1});
  const auto frame = testing::wallFrame("a", 2.05);
  ASSERT_TRUE(server.ingest(frame));
  auto second = testing::poseAt("a", 0.5, 1'000'000'000);
  ASSERT_TRUE(server.ingest(second));
  second.vehicle_id = "v2";
  ASSERT_TRUE(server.ingest(second));
  auto bad = frame;
  bad.payload.resize(10);
  EXPECT_FALSE(server.ingest(bad));  // rejected: not counted
  auto bytes = [&](const std::string& vehicle, const std::string& topic) {
    return server.metrics().get("stereomap_vehicle_received_bytes_total",
                                {{"session", "a"}, {"vehicle", vehicle}, {"topic", topic}});
  };
  EXPECT_EQ(bytes("v1", "CloudFrame"), static_cast<double>(proto::wireBytes(frame)));
  EXPECT_GT(bytes("v1", "CloudFrame"), static_cast<double>(frame.payload.size()));
  EXPECT_EQ(bytes("v1", "Pose"), static_cast<double>(proto::wireBytes(second)));
  EXPECT_EQ(bytes("v2", "Pose"), static_cast<double>(proto::wireBytes(second)));
  // Any id is a valid vehicle: past 64 in a session (two taken above) they share one series.
  for (int i = 100; i < 200; ++i) {
    char id[16];
    std::snprintf(id, sizeof id, "w%d", i);  // ("w" + to_string: a false gcc 12 -Wrestrict)
    second.vehicle_id = id;
    second.seq = 1;
    second.stamp_ns = common::nowNs();  // stamped now: its age counts
    ASSERT_TRUE(server.ingest(second));
  }
  EXPECT_GT(bytes("w161", "Pose"), 0.0);
  EXPECT_EQ(bytes("w162", "Pose"), 0.0);
  EXPECT_EQ(bytes("(other)", "Pose"), static_cast<double>(38 * proto::wireBytes(second)));
  EXPECT_NE(server.metricsText().find("stereomap_vehicle_pose_latency_seconds{session=\"a\","
                                      "vehicle=\"w161\",quantile=\"0.95\"}"),
            std::string::npos);
  // A session that goes takes its series along.
  ASSERT_TRUE(server.unload("a"));
  EXPECT_EQ(bytes("v1", "CloudFrame"), 0.0);
  EXPECT_EQ(server.metricsText().find("session=\"a\""), std::string::npos);
}

// A vehicle still sending to a session the operator closed (or opened read-only) is answered:
// an AckStatus::kSessionClosed acknowledgement with the reason, once per stream however many
// samples came, again only after kClosedAnswerEvery; a session that is loaded again answers
// as before. A vehicle's counters are kept with its loaded session, newest first.
TEST(MapServer, AClosedSessionsVehicleIsAnsweredAndAVehiclesCountersAreKept) {
  MapServer server({.resolution = 0.1});
  auto frame = testing::wallFrame("a", 2.05);
  frame.stream = 5;
  ASSERT_TRUE(server.ingest(frame));
  proto::VehicleStatusMsg counters;
  counters.vehicle_id = "v1";
  counters.session_id = "a";
  counters.stamp_ns = 10;
  counters.spool_samples = 12;
  counters.skipped_frames = 3;
  ASSERT_TRUE(server.ingest(counters));
  auto older = counters;
  older.stamp_ns = 9;
  older.spool_samples = 99;
  EXPECT_TRUE(server.ingest(older));  // taken, not kept: an older one arrived late
  auto status = server.find("a")->status();
  ASSERT_EQ(status.vehicle_status.size(), 1u);
  EXPECT_EQ(status.vehicle_status[0].status.spool_samples, 12u);
  EXPECT_EQ(status.vehicle_status[0].status.skipped_frames, 3u);
  auto huge = counters;
  huge.stamp_ns = 11;
  huge.spool_bytes = UINT64_MAX;  // not exact in JSON or the viewer: refused
  EXPECT_FALSE(server.ingest(huge));
  EXPECT_EQ(server.find("a")->status().vehicle_status[0].status.spool_bytes, 0u);
  auto stranger = counters;
  stranger.session_id = "nowhere";
  EXPECT_FALSE(server.ingest(stranger));  // makes no session
  EXPECT_EQ(server.find("nowhere"), nullptr);

  server.takeAcks();  // the journaled frame's
  ASSERT_TRUE(server.unload("a"));
  for (uint64_t seq = 1; seq < 4; ++seq) {
    auto late = testing::wallFrame("a", 2.05, seq);
    late.stream = 5;
    EXPECT_FALSE(server.ingest(late));
  }
  auto pose = testing::poseAt("a", 0.5, 2'000'000'000);
  pose.vehicle_id = "v2";
  pose.stream = 6;
  EXPECT_FALSE(server.ingest(pose));
  auto answers = server.takeAcks();
  ASSERT_EQ(answers.size(), 2u);  // one per stream
  for (const auto& answer : answers) {
    EXPECT_EQ(answer.status, proto::AckStatus::kSessionClosed);
    EXPECT_EQ(answer.session_id, "a");
    EXPECT_EQ(answer.poses + answer.clouds + answer.events + answer.corrections, 0u);
    EXPECT_NE(answer.reason.find("closed"), std::string::npos) << answer.reason;
  }
  EXPECT_EQ(answers[0].vehicle_id, "v1");
  EXPECT_EQ(answers[0].stream, 5u);
  EXPECT_EQ(answers[1].vehicle_id, "v2");
  const auto told = std::chrono::steady_clock::now();
  auto again = testing::wallFrame("a", 2.05, 4);
  again.stream = 5;
  EXPECT_FALSE(server.ingest(again));
  const auto soon = server.takeAcks();
  if (std::chrono::steady_clock::now() - told < MapServer::kClosedAnswerEvery / 2) {
    EXPECT_TRUE(soon.empty()) << "told less than a second ago";
  }
  std::this_thread::sleep_for(MapServer::kClosedAnswerEvery);
  EXPECT_EQ(server.takeAcks().size(), 1u) << "it still sends: told again";
  EXPECT_TRUE(server.takeAcks().empty()) << "nothing came since";

  // Opened read-only: its vehicles are told the same.
  ASSERT_TRUE(server.createSession("a", 0.1, /*read_only=*/true));
  auto read_only = testing::wallFrame("a", 2.05, 5);
  read_only.stream = 5;
  EXPECT_FALSE(server.ingest(read_only));
  answers = server.takeAcks();
  ASSERT_EQ(answers.size(), 1u);
  EXPECT_NE(answers[0].reason.find("read-only"), std::string::npos) << answers[0].reason;
}

// A session's own counts of what its vehicles sent, which the viewer turns into poses/s,
// clouds/s and the link's kB/s: the clouds and poses taken, and the bytes of every live sample
// taken for it (each topic, duplicates too: they crossed the link), the sum of its vehicles'
// series in /metrics. Replayed samples crossed no link now; rejected ones were not taken.
TEST(MapServer, ASessionCountsTheCloudsPosesAndLinkBytesItsVehiclesSent) {
  MapServer server({.resolution = 0.1});
  proto::SessionEventMsg started;
  started.vehicle_id = "v1";
  started.session_id = "a";
  started.stamp_ns = 1'000'000'000;
  ASSERT_TRUE(server.ingest(started));
  const auto frame = testing::wallFrame("a", 2.05);
  ASSERT_TRUE(server.ingest(frame));
  auto pose = testing::poseAt("a", 0.5, 1'000'000'000);
  ASSERT_TRUE(server.ingest(pose));
  EXPECT_FALSE(server.ingest(pose));  // a duplicate: on the link, but no new pose
  pose.vehicle_id = "v2";
  ASSERT_TRUE(server.ingest(pose));
  proto::LandingTargetMsg target;
  target.vehicle_id = "v1";
  target.session_id = "a";
  ASSERT_TRUE(server.ingest(target));
  auto bad = frame;
  bad.payload.resize(10);
  EXPECT_FALSE(server.ingest(bad));  // rejected
  auto replayed = testing::poseAt("a", 0.6, 2'000'000'000);
  ASSERT_TRUE(server.ingest(replayed, Origin::kReplay));
  ASSERT_TRUE(server.ingest(testing::wallFrame("b", 2.05)));  // another session's

  const auto status = server.find("a")->status();
  EXPECT_EQ(status.frames_received, 1u);
  EXPECT_EQ(status.poses, 3u);  // v1's, v2's and the replayed one
  const size_t link_bytes = proto::wireBytes(started) + proto::wireBytes(frame) +
                            3 * proto::wireBytes(pose) + proto::wireBytes(target);
  EXPECT_EQ(status.bytes_received, link_bytes);
  double in_metrics = 0;
  for (const char* vehicle : {"v1", "v2"}) {
    for (const char* topic : {"SessionEvent", "CloudFrame", "Pose", "LandingTarget"}) {
      in_metrics +=
          server.metrics().get("stereomap_vehicle_received_bytes_total",
                               {{"session", "a"}, {"vehicle", vehicle}, {"topic", topic}});
    }
  }
  EXPECT_EQ(in_metrics, static_cast<double>(link_bytes));
}

// A journal that keeps everything but pose corrections (a disk that fills up just then).
class NoRoomForCorrections : public IngestLog {
 public:
  common::Result<uint64_t> append(const proto::CloudFrameMsg&) override { return ++number_; }
  common::Result<uint64_t> append(const proto::PoseMsg&) override { return ++number_; }
  common::Result<uint64_t> append(const proto::SessionEventMsg&) override { return ++number_; }
  common::Result<uint64_t> append(const proto::PoseCorrectionMsg&) override {
    return common::makeError(common::ErrorCode::kIo, "No space left on device");
  }
  common::Result<uint64_t> append(const proto::FrameAlignmentMsg&) override { return ++number_; }

 private:
  uint64_t number_ = 0;
};

// A correction the journal cannot keep is refused (the vehicle's DDS history brings it again)
// and changes nothing: not the trajectory, not the snapshots, which it would otherwise hold up.
TEST(MapServer, ACorrectionThatCannotBeJournaledChangesNothing) {
  NoRoomForCorrections journal;
  struct Snapshots : SnapshotSink {
    common::Status saveSnapshot(const std::string&, uint64_t, const std::string&) override {
      ++taken;
      return common::Ok{};
    }
    std::atomic<int> taken{0};
  } snapshots;
  MapServerOptions options{.resolution = 0.1, .log = &journal};
  options.snapshots = &snapshots;
  options.snapshot_every = 1;
  MapServer server(options);
  ASSERT_TRUE(server.ingest(testing::poseAt("s", 1.0, 10)));
  proto::PoseCorrectionMsg correction;
  correction.vehicle_id = "v1";
  correction.session_id = "s";
  correction.seq = 1;
  correction.keyframes.push_back({10, {1.0, 2.0, 0}, {0, 0, 0, 1}});
  EXPECT_FALSE(server.ingest(correction));
  const auto session = server.find("s");
  EXPECT_EQ(session->status().corrections, 0u);
  EXPECT_EQ(session->trajectory(0).at(0).T_map_body.translation.y(), 0.0);
  EXPECT_NE(session->status().store_error.find("No space left"), std::string::npos);
  EXPECT_FALSE(server.storeHealth().ok);
  EXPECT_NE(server.metricsText().find("reason=\"journal_failed\""), std::string::npos);
  session->waitUntilIdle();  // returns: nothing is pending
  // Snapshots go on (the correction's announcement was withdrawn).
  ASSERT_TRUE(server.ingest(testing::wallFrame("s", 3.0, 1)));
  session->waitUntilIdle();
  for (int i = 0; i < 500 && snapshots.taken == 0; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));  // the writer's own thread
  }
  EXPECT_GT(snapshots.taken, 0);
}

}  // namespace
}  // namespace stereomap::core
