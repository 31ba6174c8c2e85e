#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>

#include "common/time.hpp"
#include "proto/cloud_codec.hpp"
#include "proto/wire_size.hpp"
#include "server/core/api.hpp"
#include "server/core/map_server.hpp"
#include "tests/support/synthetic.hpp"

namespace stereomap::core {
namespace {

using nlohmann::json;

common::PointCloud wallCloud(double x) { return testing::planeCloud(x, 0.5, 0.03); }

proto::CloudFrameMsg cloudFrame(const std::string& session, double wall_x, uint64_t seq = 0) {
  return testing::planeFrame("v1", session, seq, wallCloud(wall_x));
}

proto::PoseMsg pose(const std::string& session, double x, int64_t stamp_ns) {
  proto::PoseMsg msg;
  msg.vehicle_id = "v1";
  msg.session_id = session;
  msg.stamp_ns = stamp_ns;
  msg.position = {x, 0, 0};
  return msg;
}

TEST(Validate, RejectsEachKindOfBadSampleWithItsReason) {
  const IngestLimits limits{.max_payload_bytes = 1000};
  ValidCloud cloud;
  auto frame = cloudFrame("s", 3.0);
  frame.payload.resize(frame.payload.size() / 2);  // truncated Draco
  EXPECT_EQ(validateCloudFrame(frame, {}, cloud)->reason, "decode_failed");
  frame = cloudFrame("s", 3.0);
  EXPECT_EQ(validateCloudFrame(frame, limits, cloud)->reason, "oversize");
  frame.sensor_position[1] = std::nan("");
  EXPECT_EQ(validateCloudFrame(frame, {}, cloud)->reason, "non_finite");
  frame = cloudFrame("s", 3.0);
  frame.sensor_orientation = {0, 0, 0, 2};
  EXPECT_EQ(validateCloudFrame(frame, {}, cloud)->reason, "bad_quaternion");
  frame = cloudFrame("s", 3.0);
  frame.point_count += 1;
  EXPECT_EQ(validateCloudFrame(frame, {}, cloud)->reason, "point_count_mismatch");
  frame = cloudFrame("../etc", 3.0);
  EXPECT_EQ(validateCloudFrame(frame, {}, cloud)->reason, "bad_id");
  frame = cloudFrame("s", 3.0);
  EXPECT_FALSE(validateCloudFrame(frame, {}, cloud).has_value());
  EXPECT_EQ(cloud.cloud_camera.size(), frame.point_count);

  ValidPose valid_pose;
  auto bad_pose = pose("s", 1.0, 5);
  bad_pose.position[2] = std::numeric_limits<double>::infinity();
  EXPECT_EQ(validatePose(bad_pose, valid_pose)->reason, "non_finite");
  bad_pose = pose("s", 1.0, 5);
  bad_pose.orientation = {std::nan(""), 0, 0, 1};
  EXPECT_EQ(validatePose(bad_pose, valid_pose)->reason, "non_finite");
  EXPECT_FALSE(validatePose(pose("s", 1.0, 5), valid_pose).has_value());
}

TEST(Validate, PoseCorrectionsAreCheckedKeyframeByKeyframe) {
  proto::PoseCorrectionMsg correction;
  correction.vehicle_id = "v1";
  correction.session_id = "s1";
  for (int k = 0; k < 3; ++k)
    correction.keyframes.push_back({k * 100, {1.0 * k, 0, 0}, {0, 0, 0, 1}});
  std::vector<ValidPose> out;
  ASSERT_FALSE(validatePoseCorrection(correction, out));
  ASSERT_EQ(out.size(), 3u);
  EXPECT_EQ(out[2].stamp_ns, 200);
  EXPECT_DOUBLE_EQ(out[2].T_map_body.translation.x(), 2.0);

  auto reason = [&](proto::PoseCorrectionMsg bad) {
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

TEST(MapServer, FusesGoodFramesAndCountsBadOnes) {
  MapServer server({.resolution = 0.1});
  EXPECT_TRUE(server.ingest(cloudFrame("a", 2.05)));
  auto bad = cloudFrame("a", 2.05);
  bad.payload.resize(10);
  EXPECT_FALSE(server.ingest(bad));
  EXPECT_TRUE(server.ingest(pose("a", 0.5, 1'000'000'000)));
  auto session = server.find("a");
  ASSERT_TRUE(session);
  session->waitUntilIdle();
  const auto status = session->status();
  EXPECT_EQ(status.frames_fused, 1u);
  EXPECT_GT(status.occupied_voxels, 50u);
  EXPECT_EQ(status.poses, 1u);
  EXPECT_EQ(server.metrics().get("stereomap_samples_rejected_total",
                                 {{"topic", "CloudFrame"}, {"reason", "decode_failed"}}),
            1.0);
  EXPECT_NE(server.metricsText().find("stereomap_session_occupied_voxels{session=\"a\"}"),
            std::string::npos);
}

// What each vehicle's accepted samples took on the link, as the vehicle counts it.
TEST(MapServer, CountsEachVehiclesBytes) {
  MapServer server({.resolution = 0.1});
  const auto frame = cloudFrame("a", 2.05);
  ASSERT_TRUE(server.ingest(frame));
  auto second = pose("a", 0.5, 1'000'000'000);
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

TEST(Api, ListsSessionsAndServesTrajectoryAndMap) {
  MapServer server({.resolution = 0.1});
  ASSERT_TRUE(server.ingest(cloudFrame("flight-1", 2.05)));
  ASSERT_TRUE(server.ingest(pose("flight-1", 0.5, 1'700'000'000'250'000'000)));
  server.find("flight-1")->waitUntilIdle();

  auto list = answerApi(server, nullptr, "GET", "/api/sessions");
  ASSERT_TRUE(list && list->status == 200);
  const auto sessions = json::parse(list->body);
  ASSERT_EQ(sessions.size(), 1u);
  EXPECT_EQ(sessions[0]["id"], "flight-1");
  EXPECT_EQ(sessions[0]["vehicle"], "v1");
  EXPECT_EQ(sessions[0]["frames"], 1);
  EXPECT_GT(sessions[0]["occupied_voxels"].get<int>(), 50);
  EXPECT_NEAR(sessions[0]["bounds"]["min"][0].get<double>(), 2.0, 1e-9);

  auto tum = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/trajectory.tum");
  ASSERT_TRUE(tum && tum->status == 200);
  EXPECT_EQ(tum->body,
            "1700000000.250000000 0.500000 0.000000 0.000000 0.000000000 "
            "0.000000000 0.000000000 1.000000000\n");
  auto bt = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.bt");
  ASSERT_TRUE(bt && bt->status == 200);
  EXPECT_EQ(bt->body.rfind("# Octomap OcTree binary file", 0), 0u);

  auto ot = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.ot");
  ASSERT_TRUE(ot && ot->status == 200);
  EXPECT_EQ(ot->body.rfind("# Octomap OcTree file", 0), 0u);
  auto ply = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.ply");
  ASSERT_TRUE(ply && ply->status == 200);
  const auto voxels = sessions[0]["occupied_voxels"].get<size_t>();
  const size_t header = ply->body.find("end_header\n") + 11;
  EXPECT_EQ(ply->body.size() - header, voxels * 12);  // three floats per voxel
  auto png = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.png?zmin=-0.2&zmax=0.2");
  ASSERT_TRUE(png && png->status == 200);
  EXPECT_EQ(png->content_type, "image/png");
  EXPECT_EQ(png->body.substr(1, 3), "PNG");
  // The wall seen from above: white voxels, each a square of `scale` pixels.
  auto decoded = [](const std::string& body) {
    return cv::imdecode(std::vector<uint8_t>(body.begin(), body.end()), cv::IMREAD_UNCHANGED);
  };
  const cv::Mat one = decoded(png->body);
  ASSERT_EQ(one.type(), CV_8UC1);
  EXPECT_GT(cv::countNonZero(one), 5);
  auto png3 = answerApi(server, nullptr, "GET",
                        "/api/sessions/flight-1/map.png?zmin=-0.2&zmax=0.2&scale=3");
  ASSERT_TRUE(png3 && png3->status == 200);
  cv::Mat expected;
  cv::resize(one, expected, cv::Size(), 3, 3, cv::INTER_NEAREST);
  const cv::Mat three = decoded(png3->body);
  ASSERT_EQ(three.size(), expected.size());
  EXPECT_EQ(cv::countNonZero(three != expected), 0);
  EXPECT_EQ(
      answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.png?zmin=5&zmax=6")->status,
      404);
  EXPECT_EQ(answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.png?zmin=x")->status,
            400);
  EXPECT_EQ(answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.png?scale=40")->status,
            400);
  EXPECT_EQ(answerApi(server, nullptr, "GET", "/api/sessions/nope/map.bt")->status, 404);
  EXPECT_EQ(answerApi(server, nullptr, "POST", "/api/sessions")->status, 405);
  EXPECT_EQ(answerApi(server, nullptr, "GET", "/api/other")->status, 404);
  EXPECT_EQ(answerApi(server, nullptr, "GET", "/healthz")->body, "ok\n");
  EXPECT_FALSE(answerApi(server, nullptr, "GET", "/index.html").has_value());
}

// A top view whose image would be gigabytes is refused before anything is allocated: two
// walls 800 m apart at 0.1 m and 16 pixels per voxel would be 128,000 pixels on a side.
TEST(Api, ATopViewTooLargeToDrawIsRefused) {
  MapServer server({.resolution = 0.1});
  ASSERT_TRUE(server.ingest(cloudFrame("far", 2.05, 0)));
  auto far = cloudFrame("far", 2.05, 1);
  far.sensor_position = {800.0, 800.0, 0.0};
  ASSERT_TRUE(server.ingest(far));
  server.find("far")->waitUntilIdle();
  const auto refused =
      answerApi(server, nullptr, "GET", "/api/sessions/far/map.png?zmin=-0.2&zmax=0.2&scale=16");
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->status, 413) << refused->body;
  EXPECT_NE(refused->body.find("smaller scale"), std::string::npos) << refused->body;
}

TEST(Session, AFullQueueDropsAndCountsInsteadOfBlocking) {
  Session session("q", {.resolution = 0.1, .queue_capacity = 1});
  size_t accepted = 0;
  for (int i = 0; i < 20; ++i) {
    FusionJob job{"v", static_cast<uint64_t>(i), 0, wallCloud(3.0), common::Rigid3::identity(), 10};
    accepted += session.enqueue(std::move(job));
  }
  session.waitUntilIdle();
  const auto status = session.status();
  EXPECT_EQ(status.frames_received, 20u);
  EXPECT_EQ(status.frames_dropped + status.frames_fused, 20u);
  EXPECT_EQ(status.frames_fused, accepted);
  EXPECT_GT(status.frames_dropped, 0u);
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
  ASSERT_TRUE(server.ingest(pose("s", 1.0, 10)));
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
  ASSERT_TRUE(server.ingest(cloudFrame("s", 3.0, 1)));
  session->waitUntilIdle();
  for (int i = 0; i < 500 && snapshots.taken == 0; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));  // the writer's own thread
  }
  EXPECT_GT(snapshots.taken, 0);
}

// Frames keep coming, faster than a correction's re-fusion reads the journal, so that it
// never catches up by reading and hands over with frames only the worker's tail holds: the
// swapped-in map has every frame, each where the correction puts it. The journal is a list
// of the jobs (the store's reading is tested with the store).
TEST(Session, FramesArrivingDuringARefusionAreNotLost) {
  std::vector<FusionJob> journal;  // what the session was sent, numbered 1..
  std::mutex journal_mutex;
  auto job = [](int i, double dy) {
    common::Rigid3 pose;
    pose.translation = {0, dy, 0.1 * i};  // each frame a wall patch of its own
    return FusionJob{
        "v", static_cast<uint64_t>(i),    1000 + i, testing::planeCloud(2.0, 0.4, 0.05), pose,
        10,  static_cast<uint64_t>(i + 1)};
  };
  Session::Options options{.resolution = 0.1};
  options.reread_frames = [&](uint64_t after, uint64_t up_to,
                              const std::function<void(FusionJob &&)>& fuse) {
    for (size_t i = 0;; ++i) {
      FusionJob copy;
      {
        std::lock_guard lock(journal_mutex);
        if (i >= journal.size()) break;
        copy = journal[i];
      }
      if (copy.journal_number <= after || copy.journal_number > up_to) continue;
      std::this_thread::sleep_for(std::chrono::milliseconds(5));  // slower than frames come
      fuse(std::move(copy));
    }
    return common::Status(common::Ok{});
  };
  Session session("r", options);
  int sent = 0;
  auto send = [&] {
    auto frame = job(sent++, 0.5);  // 0.5 m off in y
    session.addPose({"v", frame.stamp_ns, frame.T_map_camera});
    {
      std::lock_guard lock(journal_mutex);
      journal.push_back(frame);
    }
    // Waits for room: a full queue drops frames by design (another test), and a slow build
    // (AddressSanitizer) filled it here before the re-fusion ended.
    ASSERT_TRUE(session.enqueue(std::move(frame), /*wait_for_room=*/true));
  };
  for (int i = 0; i < 20; ++i) send();
  session.waitUntilIdle();
  std::vector<StampedBodyPose> keyframes;
  for (int i = 0; i < 20; i += 5) keyframes.push_back({job(i, 0).stamp_ns, job(i, 0).T_map_camera});
  auto correction = session.correctionFor("v", keyframes);
  ASSERT_TRUE(correction);
  session.correct("v", *correction, /*refuse=*/true);
  while (session.status().refusions == 0 && sent < 2000) {
    send();
    std::this_thread::sleep_for(std::chrono::milliseconds(3));
  }
  for (int i = 0; i < 5; ++i) send();
  session.waitUntilIdle();
  EXPECT_EQ(session.status().refusions, 1u);
  EXPECT_EQ(session.status().frames_fused, static_cast<uint64_t>(sent));

  Session right("t", {.resolution = 0.1});
  for (int i = 0; i < sent; ++i) ASSERT_TRUE(right.enqueue(job(i, 0), /*wait_for_room=*/true));
  right.waitUntilIdle();
  EXPECT_EQ(session.occupiedVoxels(), right.occupiedVoxels());
}

}  // namespace
}  // namespace stereomap::core
