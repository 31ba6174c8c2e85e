#include "onboard/pipeline/pipeline.hpp"

#include <gtest/gtest.h>

#include <cmath>

#include "onboard/eval/metrics.hpp"
#include "onboard/sim/sim_source.hpp"
#include "proto/dds.hpp"
#include "proto/pose_fields.hpp"

namespace stereomap::pipeline {
namespace {

using namespace std::chrono_literals;

TEST(Pipeline, MessagesCarryTheCloudAndTheSensorPose) {
  sim::SimSource source({.seed = 3, .max_frames = 1});
  auto frame = source.next();
  ASSERT_TRUE(frame.has_value());
  const PipelineOptions options{.vehicle_id = "uav", .session_id = "s1"};
  const stereo::StereoMatcher matcher;
  const auto cloud = stereo::cloudFromDisparity(matcher.compute(frame->left, frame->right),
                                                frame->left, source.camera(), options.stereo.cloud);
  ASSERT_GT(cloud.size(), 5000u);
  const auto T_map_camera = *frame->T_map_body * *frame->T_body_camera;
  auto msg = makeCloudFrameMsg(options, options.codec, 4, frame->stamp_ns, T_map_camera, cloud,
                               options.stereo.cloud.max_range_m);
  ASSERT_TRUE(msg.ok());
  EXPECT_EQ(msg->point_count, cloud.size());
  EXPECT_EQ(msg->seq, 4u);
  EXPECT_TRUE(msg->has_intensity);
  // At least the range limit, and long enough for every point (corner rays exceed it).
  float longest = 0;
  for (const auto& p : cloud.points) longest = std::max(longest, p.norm());
  EXPECT_GE(msg->max_range, 6.0f);
  EXPECT_GE(msg->max_range, longest);
  EXPECT_LE(msg->max_range, std::max(6.0f, longest) * 1.01f);
  const common::Quat q = proto::quatFromFields(msg->sensor_orientation);
  EXPECT_NEAR(q.angularDistance(T_map_camera.rotation), 0.0, 1e-9);
  auto decoded = proto::decodeCloud(msg->payload, proto::payloadInfo(*msg));
  ASSERT_TRUE(decoded.ok());
  EXPECT_EQ(decoded->size(), cloud.size());
  // About 4 bytes per point at 14 bits (Draco kd-tree): the link budget of a vehicle.
  EXPECT_LT(static_cast<double>(msg->payload.size()) / cloud.size(), 6.0);
}

TEST(Pipeline, RunsASourceToTheEndWithoutPublishing) {
  sim::SimSource source({.seed = 1, .max_frames = 3});
  common::Shutdown shutdown;
  const auto summary = runPipeline(source, nullptr, {.rate_hz = 0, .progress_every = 0}, shutdown);
  EXPECT_EQ(summary.frames, 3u);
  EXPECT_GT(summary.points, 15000u);
  EXPECT_FALSE(summary.stopped);
  EXPECT_EQ(summary.publish_errors, 0u);
}

TEST(Pipeline, StopRequestEndsAPacedRun) {
  sim::SimSource source({.seed = 1});
  common::Shutdown shutdown;
  std::thread stopper([&] {
    std::this_thread::sleep_for(300ms);
    shutdown.requestStop();
  });
  const auto summary = runPipeline(source, nullptr, {.rate_hz = 5, .progress_every = 0}, shutdown);
  stopper.join();
  EXPECT_TRUE(summary.stopped);
  EXPECT_GE(summary.frames, 1u);
  EXPECT_LE(summary.frames, 3u);
}

// The pose graph on a worker thread: past one loop of the flight it closes loops and makes
// corrections (what a vehicle sends the server), and the final trajectory beats the odometry.
TEST(Pipeline, APoseGraphCorrectsThePoses) {
  sim::SimSourceOptions sim_options{.seed = 1, .max_frames = 520};
  sim_options.render.camera.noise_sigma = 2.0;
  sim::SimSource source(sim_options);
  common::Shutdown shutdown;
  PipelineOptions options{.rate_hz = 0, .progress_every = 0, .depth = false, .pose_graph = true};
  std::vector<FrameReport> reports;
  options.on_frame = [&](const FrameReport& r) { reports.push_back(r); };
  const auto summary = runPipeline(source, nullptr, options, shutdown);
  ASSERT_EQ(summary.frames, 520u);
  ASSERT_EQ(summary.corrected_T_map_body.size(), 520u);
  EXPECT_GT(summary.graph.loops, 0);
  common::Trajectory truth, odometry_only, corrected_poses;
  for (size_t i = 0; i < reports.size(); ++i) {
    const double t = static_cast<double>(reports[i].stamp_ns) * 1e-9;
    truth.push_back({t, *reports[i].T_map_body_truth});
    odometry_only.push_back({t, reports[i].T_map_body_odometry});
    corrected_poses.push_back({t, summary.corrected_T_map_body[i]});
  }
  const double odometry =
      eval::absoluteError(truth, odometry_only, eval::Alignment::kSe3).translation.rmse;
  const double corrected =
      eval::absoluteError(truth, corrected_poses, eval::Alignment::kSe3).translation.rmse;
  EXPECT_GT(summary.corrections, 0u);
  // Published poses stay the odometry's (the corrections go apart).
  EXPECT_EQ(reports.back().T_map_body.translation, reports.back().T_map_body_odometry.translation);
  std::printf("520 frames: %d closures; ATE %.4f m (odometry) -> %.4f m\n", summary.graph.loops,
              odometry, corrected);
  EXPECT_LT(corrected, odometry);
}

// The poses a run reports (as published), with ground truth, from the sim's first frames.
std::vector<FrameReport> reportsOf(PipelineOptions options, uint64_t frames) {
  sim::SimSource source({.seed = 1, .max_frames = frames});
  common::Shutdown shutdown;
  options.rate_hz = 0;
  options.progress_every = 0;
  options.depth = false;
  std::vector<FrameReport> reports;
  options.on_frame = [&](const FrameReport& r) { reports.push_back(r); };
  runPipeline(source, nullptr, options, shutdown);
  return reports;
}

void expectNear(const common::Rigid3& a, const common::Rigid3& b, double tolerance = 1e-9) {
  EXPECT_NEAR((a.translation - b.translation).norm(), 0.0, tolerance);
  EXPECT_NEAR(a.rotation.angularDistance(b.rotation), 0.0, tolerance);
}

// In its own frame (issue 56) the vehicle's first pose is the start pose, and every later one
// keeps its motion from there; the ground truth stays the source's.
TEST(Pipeline, InItsOwnFrameTheFirstPoseIsTheStartPose) {
  const common::Rigid3 start{common::Quat(Eigen::AngleAxisd(M_PI / 6, common::Vec3::UnitZ())),
                             common::Vec3(1, 2, 3)};
  for (const auto pose_source : {PoseSource::kGroundTruth, PoseSource::kOdometry}) {
    SCOPED_TRACE(pose_source == PoseSource::kOdometry ? "odometry" : "ground truth");
    const auto session = reportsOf({.pose_source = pose_source}, 4);
    const auto own = reportsOf(
        {.pose_source = pose_source, .frame = proto::VehicleFrame::kOwn, .start_pose = start}, 4);
    ASSERT_EQ(own.size(), 4u);
    ASSERT_EQ(session.size(), 4u);
    expectNear(own[0].T_map_body, start);
    for (size_t i = 0; i < own.size(); ++i) {
      expectNear(own[0].T_map_body.inverse() * own[i].T_map_body,
                 session[0].T_map_body.inverse() * session[i].T_map_body, 1e-6);
      // The camera's, and so the clouds', poses move with the body's.
      expectNear(own[i].T_map_camera,
                 own[0].T_map_body * session[0].T_map_body.inverse() * session[i].T_map_camera,
                 1e-6);
      ASSERT_TRUE(own[i].T_map_body_truth && session[i].T_map_body_truth);
      EXPECT_EQ(own[i].T_map_body_truth->translation, session[i].T_map_body_truth->translation);
    }
  }
  // In the session's frame the source's poses go as they are.
  const auto session = reportsOf({.pose_source = PoseSource::kGroundTruth}, 2);
  for (const auto& r : session) {
    EXPECT_EQ(r.T_map_body.translation, r.T_map_body_truth->translation);
    EXPECT_EQ(r.T_map_body.rotation.coeffs(), r.T_map_body_truth->rotation.coeffs());
  }
}

TEST(Pipeline, TheSessionEventSaysTheFrame) {
  const camera::StereoCamera camera;
  EXPECT_EQ(makeSessionEvent({}, camera, proto::SessionEventKind::kStarted).frame,
            proto::VehicleFrame::kSession);
  EXPECT_EQ(makeSessionEvent({.frame = proto::VehicleFrame::kOwn}, camera,
                             proto::SessionEventKind::kEnded)
                .frame,
            proto::VehicleFrame::kOwn);
}

// A vehicle in its own frame learns from the acknowledgements whether the server has aligned it,
// and where its frame sits in the session's.
TEST(Pipeline, TheAcknowledgementsSayWhereTheVehiclesFrameIs) {
  auto participant =
      proto::Participant::create({.domain_id = 135, .config_file = STEREOMAP_DDS_CONFIG});
  ASSERT_TRUE(participant) << participant.error().message;
  auto acks =
      proto::Writer<proto::AckMsg>::create(*participant, {proto::vehiclePartition("s1", "uav")});
  ASSERT_TRUE(acks);
  auto spool = link::Spool::open({});
  ASSERT_TRUE(spool);
  auto publisher =
      VehiclePublisher::create(*participant, "s1", std::move(*spool), {.vehicle_id = "uav"});
  ASSERT_TRUE(publisher) << publisher.error().message;
  EXPECT_EQ((*publisher)->frameState(), proto::FrameState::kNone);
  proto::AckMsg ack;
  ack.session_id = "s1";
  ack.vehicle_id = "uav";
  ack.stream = 1;
  auto expectState = [&](proto::FrameState state) {
    ack.frame_state = state;
    const auto deadline = std::chrono::steady_clock::now() + 3s;
    while ((*publisher)->frameState() != state && std::chrono::steady_clock::now() < deadline) {
      ASSERT_TRUE((*acks)->write(ack));  // again until the reader has matched
      (*publisher)->service(50ms);
    }
    EXPECT_EQ((*publisher)->frameState(), state);
  };
  expectState(proto::FrameState::kAligning);
  ack.frame_position = {1, 2, 3};
  ack.frame_orientation = {0, 0, std::sin(0.25), std::cos(0.25)};
  expectState(proto::FrameState::kAligned);
  expectNear((*publisher)->T_session_own(),
             {common::Quat(Eigen::AngleAxisd(0.5, common::Vec3::UnitZ())), common::Vec3(1, 2, 3)});
}

// A vehicle holding samples that no server reads (in a cluster: its session left memory while
// the vehicle went on) says its session started again every 2 s, as its start event was first
// sent, so that a server takes the session up; once nothing waits, it stops.
TEST(Pipeline, AVehicleHoldingSamplesAnnouncesItsSessionWhileNoServerReadsIt) {
  auto participant =
      proto::Participant::create({.domain_id = 93, .config_file = STEREOMAP_DDS_CONFIG});
  ASSERT_TRUE(participant) << participant.error().message;
  auto events =
      proto::Reader<proto::SessionEventMsg>::create(*participant, {proto::kEverySessionPartition});
  ASSERT_TRUE(events);
  auto spool = link::Spool::open({});
  ASSERT_TRUE(spool);
  auto publisher =
      VehiclePublisher::create(*participant, "s1", std::move(*spool), {.vehicle_id = "uav"});
  ASSERT_TRUE(publisher) << publisher.error().message;
  proto::SessionEventMsg started;
  started.session_id = "s1";
  started.vehicle_id = "uav";
  started.kind = proto::SessionEventKind::kStarted;
  ASSERT_TRUE((*publisher)->publish(started));
  proto::PoseMsg pose;
  pose.session_id = "s1";
  pose.vehicle_id = "uav";
  pose.orientation = {0, 0, 0, 1};
  ASSERT_TRUE((*publisher)->publish(pose));  // held: nobody acknowledges it
  std::vector<proto::SessionEventMsg> seen;
  const auto deadline = std::chrono::steady_clock::now() + 4500ms;
  while (std::chrono::steady_clock::now() < deadline) {
    (*publisher)->service(50ms);
    events->get()->take(seen, 0ms);
  }
  ASSERT_GE(seen.size(), 3u) << "the start, then again every 2 s";
  for (const auto& event : seen) {
    EXPECT_EQ(event.kind, proto::SessionEventKind::kStarted);
    EXPECT_EQ(event.seq, seen.front().seq) << "the same sample: a server that has it skips it";
    EXPECT_EQ(event.stream, seen.front().stream);
  }
}

}  // namespace
}  // namespace stereomap::pipeline
