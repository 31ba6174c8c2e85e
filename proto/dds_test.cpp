#include "proto/dds.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <thread>
#include <typeinfo>

namespace stereomap::proto {
namespace {

using namespace std::chrono_literals;

// Each test binary uses its own DDS domain id so parallel tests never cross-talk.
constexpr uint32_t kDomain = 61;

std::shared_ptr<Participant> makeParticipant() {
  auto participant =
      Participant::create({.domain_id = kDomain, .config_file = STEREOMAP_DDS_CONFIG});
  EXPECT_TRUE(participant.ok()) << participant.error().message;
  return *participant;
}

template <typename T>
std::vector<T> takeAtLeast(Reader<T>& reader, size_t count) {
  std::vector<T> out;
  const auto deadline = std::chrono::steady_clock::now() + 10s;
  while (out.size() < count && std::chrono::steady_clock::now() < deadline) {
    reader.take(out, 500ms);
  }
  return out;
}

// A reader and a writer of T on `participant` that have met; null ones (with a failure
// reported) when they could not be made or did not meet.
template <typename T>
struct Link {
  std::unique_ptr<Reader<T>> reader;
  std::unique_ptr<Writer<T>> writer;
  bool ok() const { return reader && writer; }
};

template <typename T>
Link<T> connect(const std::shared_ptr<Participant>& participant) {
  auto reader = Reader<T>::create(participant);
  auto writer = Writer<T>::create(participant);
  if (!reader.ok() || !writer.ok() || !(*writer)->waitForReaders(1, 5s)) {
    ADD_FAILURE() << "no " << typeid(T).name() << " reader and writer that met";
    return {};
  }
  return {std::move(reader).value(), std::move(writer).value()};
}

TEST(Dds, PoseRoundTripsEveryField) {
  auto participant = makeParticipant();
  auto link = connect<PoseMsg>(participant);
  ASSERT_TRUE(link.ok());

  PoseMsg pose;
  pose.vehicle_id = "uav-7";
  pose.session_id = "flight-42";
  pose.seq = 9;
  pose.stamp_ns = 1'700'000'000'123'456'789;
  pose.position = {1.5, -2.25, 3.0};
  pose.orientation = {0.0, 0.0, 0.70710678, 0.70710678};
  pose.velocity = {0.1, 0.2, 0.3};
  for (size_t i = 0; i < 36; ++i) pose.covariance[i] = static_cast<double>(i) * 0.01;
  pose.tracking_state = TrackingState::kDegraded;
  pose.source = PoseSource::kVisualOdometry;
  ASSERT_TRUE(link.writer->write(pose).ok());

  auto got = takeAtLeast(*link.reader, 1);
  ASSERT_EQ(got.size(), 1u);
  EXPECT_EQ(got[0].vehicle_id, pose.vehicle_id);
  EXPECT_EQ(got[0].session_id, pose.session_id);
  EXPECT_EQ(got[0].seq, pose.seq);
  EXPECT_EQ(got[0].stamp_ns, pose.stamp_ns);
  EXPECT_EQ(got[0].position, pose.position);
  EXPECT_EQ(got[0].orientation, pose.orientation);
  EXPECT_EQ(got[0].velocity, pose.velocity);
  EXPECT_EQ(got[0].covariance, pose.covariance);
  EXPECT_EQ(got[0].tracking_state, pose.tracking_state);
  EXPECT_EQ(got[0].source, pose.source);
}

TEST(Dds, CloudFramePayloadOfFourMegabytesArrivesIntact) {
  auto participant = makeParticipant();
  auto link = connect<CloudFrameMsg>(participant);
  ASSERT_TRUE(link.ok());

  CloudFrameMsg frame;
  frame.vehicle_id = "v";
  frame.session_id = "s";
  frame.point_count = 123;
  frame.max_range = 7.5f;
  frame.quantization_bits = 14;
  frame.has_intensity = true;
  frame.payload.resize(4u << 20);
  for (size_t i = 0; i < frame.payload.size(); ++i) frame.payload[i] = static_cast<uint8_t>(i * 31);
  for (uint64_t seq = 0; seq < 3; ++seq) {
    frame.seq = seq;
    ASSERT_TRUE(link.writer->write(frame).ok());
  }
  auto got = takeAtLeast(*link.reader, 3);
  ASSERT_EQ(got.size(), 3u);
  for (uint64_t seq = 0; seq < 3; ++seq) {
    EXPECT_EQ(got[seq].seq, seq);
    EXPECT_EQ(got[seq].payload, frame.payload);
    EXPECT_EQ(got[seq].point_count, 123u);
    EXPECT_TRUE(got[seq].has_intensity);
  }
}

TEST(Dds, OverBoundValuesAreRefusedByTheWriter) {
  auto participant = makeParticipant();
  auto writer = Writer<CloudFrameMsg>::create(participant);
  ASSERT_TRUE(writer.ok());
  CloudFrameMsg frame;
  frame.vehicle_id = std::string(65, 'x');
  auto status = (*writer)->write(frame);
  ASSERT_FALSE(status.ok());
  EXPECT_NE(status.error().message.find("vehicle_id"), std::string::npos);
  frame.vehicle_id = "v";
  frame.payload.resize(kMaxPayloadBytes + 1);
  EXPECT_FALSE((*writer)->write(frame).ok());
}

TEST(Dds, SessionEventReachesALateJoiningReader) {
  auto participant = makeParticipant();
  auto writer = Writer<SessionEventMsg>::create(participant);
  ASSERT_TRUE(writer.ok());
  SessionEventMsg event;
  event.vehicle_id = "v1";
  event.session_id = "late";
  event.width = 640;
  event.fx = 492.45;
  event.baseline = 0.120081;
  ASSERT_TRUE((*writer)->write(event).ok());

  auto reader = Reader<SessionEventMsg>::create(participant);  // joins after the write
  ASSERT_TRUE(reader.ok());
  auto got = takeAtLeast(**reader, 1);
  ASSERT_EQ(got.size(), 1u);
  EXPECT_EQ(got[0].session_id, "late");
  EXPECT_EQ(got[0].kind, SessionEventKind::kStarted);
  EXPECT_DOUBLE_EQ(got[0].baseline, 0.120081);
}

// A pose graph's correction: every keyframe arrives as sent, and a server that joins late
// still gets the newest one (keep-last 1, transient-local).
TEST(Dds, PoseCorrectionReachesALateJoiningReaderWithEveryKeyframe) {
  auto participant = makeParticipant();
  auto writer = Writer<PoseCorrectionMsg>::create(participant);
  ASSERT_TRUE(writer.ok());
  PoseCorrectionMsg correction;
  correction.vehicle_id = "uav-7";
  correction.session_id = "flight-42";
  for (uint64_t seq = 1; seq <= 2; ++seq) {
    correction.seq = seq;
    correction.stamp_ns = static_cast<int64_t>(seq) * 1000;
    correction.keyframes.clear();
    for (int k = 0; k < 500 * static_cast<int>(seq); ++k) {
      correction.keyframes.push_back({k * 100'000'000LL,
                                      {0.1 * k, -0.2 * k, 1.5},
                                      {0, 0, std::sin(0.01 * k), std::cos(0.01 * k)}});
    }
    ASSERT_TRUE((*writer)->write(correction).ok());
  }
  auto reader = Reader<PoseCorrectionMsg>::create(participant);  // joins after both writes
  ASSERT_TRUE(reader.ok());
  auto got = takeAtLeast(**reader, 1);
  ASSERT_EQ(got.size(), 1u) << "only the newest correction is kept";
  EXPECT_EQ(got[0].seq, 2u);
  EXPECT_EQ(got[0].session_id, "flight-42");
  ASSERT_EQ(got[0].keyframes.size(), correction.keyframes.size());
  for (size_t k = 0; k < correction.keyframes.size(); ++k) {
    EXPECT_EQ(got[0].keyframes[k].stamp_ns, correction.keyframes[k].stamp_ns);
    EXPECT_EQ(got[0].keyframes[k].position, correction.keyframes[k].position);
    EXPECT_EQ(got[0].keyframes[k].orientation, correction.keyframes[k].orientation);
  }
  correction.keyframes.resize(kMaxCorrectedKeyframes + 1);
  EXPECT_FALSE((*writer)->write(correction).ok());
}

TEST(Dds, LandingTargetRoundTripsEveryField) {
  auto participant = makeParticipant();
  auto reader = Reader<LandingTargetMsg>::create(participant);  // volatile: joins first
  auto writer = Writer<LandingTargetMsg>::create(participant);
  ASSERT_TRUE(reader.ok() && writer.ok());
  LandingTargetMsg target;
  target.vehicle_id = "uav-7";
  target.session_id = "deck-1";
  target.seq = 3;
  target.stamp_ns = 123;
  target.state = LandingState::kTracking;
  target.mode = LandingMode::kPatent;
  target.reason = "followed";
  target.has_pose = true;
  target.camera_position = {0.5, -1, 20};
  target.map_orientation = {0, 0, 0.6, 0.8};
  target.map_covariance[35] = 1e-4;
  target.deck_velocity = {5, 0, -0.3};
  target.distance = 20.1;
  target.bearing_deg = -12;
  target.reprojection_px = 0.2;
  // A volatile writer sends only to readers it has met: write until one arrives.
  std::vector<LandingTargetMsg> got;
  for (int attempt = 0; attempt < 50 && got.empty(); ++attempt) {
    ASSERT_TRUE((*writer)->write(target).ok());
    (*reader)->take(got, std::chrono::milliseconds(100));
  }
  ASSERT_FALSE(got.empty());
  EXPECT_EQ(got[0].reason, "followed");
  EXPECT_EQ(got[0].state, LandingState::kTracking);
  EXPECT_EQ(got[0].mode, LandingMode::kPatent);
  EXPECT_TRUE(got[0].has_pose);
  EXPECT_EQ(got[0].camera_position, target.camera_position);
  EXPECT_EQ(got[0].map_orientation, target.map_orientation);
  EXPECT_EQ(got[0].map_covariance, target.map_covariance);
  EXPECT_EQ(got[0].deck_velocity, target.deck_velocity);
  EXPECT_EQ(got[0].distance, 20.1);
  EXPECT_EQ(got[0].bearing_deg, -12);
  target.reason.assign(kMaxLandingReason + 1, 'x');
  EXPECT_FALSE((*writer)->write(target).ok());
}

// Enumerations travel as integers (stereomap.idl): a sample with an unknown value reaches the
// reader, which refuses it and says who sent it and what was wrong (the server counts it).
// An acknowledgement's answer that the session is closed, with its reason, and a vehicle's
// counters, every field across.
TEST(Dds, AClosedAnswerAndAVehiclesStatusRoundTrip) {
  auto participant = makeParticipant();
  auto acks_link = connect<AckMsg>(participant);
  auto status_link = connect<VehicleStatusMsg>(participant);
  ASSERT_TRUE(acks_link.ok() && status_link.ok());
  auto& ack_writer = acks_link.writer;
  auto& ack_reader = acks_link.reader;
  auto& status_writer = status_link.writer;
  auto& status_reader = status_link.reader;
  AckMsg ack;
  ack.vehicle_id = "uav-1";
  ack.session_id = "s";
  ack.stream = 77;
  ack.status = AckStatus::kSessionClosed;
  ack.reason = "session 's' was closed into the store";
  ASSERT_TRUE(ack_writer->write(ack).ok());
  VehicleStatusMsg status;
  status.vehicle_id = "uav-1";
  status.session_id = "s";
  status.stamp_ns = 5;
  status.frames = 1;
  status.skipped_frames = 2;
  status.late_frames = 3;
  status.spool_samples = 4;
  status.spool_bytes = 5;
  status.given_up = 6;
  status.held_back = 7;
  status.session_closed = true;
  ASSERT_TRUE(status_writer->write(status).ok());
  std::vector<AckMsg> acks;
  std::vector<VehicleStatusMsg> statuses;
  for (int i = 0; i < 50 && (acks.empty() || statuses.empty()); ++i) {
    ack_reader->take(acks, 100ms);
    status_reader->take(statuses, 100ms);
  }
  ASSERT_EQ(acks.size(), 1u);
  EXPECT_EQ(acks[0].status, AckStatus::kSessionClosed);
  EXPECT_EQ(acks[0].reason, ack.reason);
  EXPECT_EQ(acks[0].stream, 77u);
  ASSERT_EQ(statuses.size(), 1u);
  const auto& got = statuses[0];
  EXPECT_EQ(
      std::vector<uint64_t>({got.frames, got.skipped_frames, got.late_frames, got.spool_samples,
                             got.spool_bytes, got.given_up, got.held_back}),
      std::vector<uint64_t>({1, 2, 3, 4, 5, 6, 7}));
  EXPECT_TRUE(got.session_closed);
  EXPECT_EQ(got.stamp_ns, 5);
  // A reason over the IDL's bound is refused by the writer.
  ack.reason.assign(kMaxAckReason + 1, 'x');
  EXPECT_FALSE(ack_writer->write(ack).ok());
}

TEST(Dds, AnUnknownEnumerationIsRefusedWithItsSenderAndField) {
  auto participant = makeParticipant();
  auto link = connect<PoseMsg>(participant);
  ASSERT_TRUE(link.ok());
  PoseMsg pose;
  pose.vehicle_id = "uav-bad-enum";
  pose.session_id = "flight-9";
  pose.orientation = {0, 0, 0, 1};
  pose.tracking_state = static_cast<TrackingState>(9);
  ASSERT_TRUE(link.writer->write(pose).ok());
  pose.seq = 1;
  pose.tracking_state = TrackingState::kOk;
  pose.source = static_cast<PoseSource>(3);
  ASSERT_TRUE(link.writer->write(pose).ok());
  pose.seq = 2;
  pose.source = PoseSource::kExternal;
  ASSERT_TRUE(link.writer->write(pose).ok());

  std::vector<PoseMsg> got;
  std::vector<RefusedSample> refused;
  const auto deadline = std::chrono::steady_clock::now() + 10s;
  auto mine = [&] {
    return std::count_if(got.begin(), got.end(),
                         [](const PoseMsg& p) { return p.vehicle_id == "uav-bad-enum"; });
  };
  while ((refused.size() < 2 || mine() < 1) && std::chrono::steady_clock::now() < deadline) {
    link.reader->take(got, 500ms, &refused);
  }
  ASSERT_EQ(refused.size(), 2u);
  EXPECT_EQ(mine(), 1);  // the good one after them
  for (const auto& sample : refused) {
    EXPECT_EQ(sample.type, "Pose");
    EXPECT_EQ(sample.vehicle_id, "uav-bad-enum");
    EXPECT_EQ(sample.session_id, "flight-9");
  }
  EXPECT_EQ(refused[0].detail, "tracking_state has unknown value 9");
  EXPECT_EQ(refused[1].detail, "source has unknown value 3");
}

TEST(Dds, WakeReturnsABlockedTakeAtOnce) {
  auto participant = makeParticipant();
  auto reader = Reader<PoseMsg>::create(participant);
  ASSERT_TRUE(reader.ok());
  std::vector<PoseMsg> out;
  const auto start = std::chrono::steady_clock::now();
  std::thread waker([&] {
    std::this_thread::sleep_for(100ms);
    (*reader)->wake();
  });
  (*reader)->take(out, 10s);
  waker.join();
  EXPECT_LT(std::chrono::steady_clock::now() - start, 5s);
  EXPECT_TRUE(out.empty());
}

TEST(Dds, BadConfigFileIsAClearError) {
  auto participant =
      Participant::create({.domain_id = kDomain + 1, .config_file = "/nonexistent.xml"});
  ASSERT_FALSE(participant.ok());
  EXPECT_NE(participant.error().message.find("/nonexistent.xml"), std::string::npos);
}

}  // namespace
}  // namespace stereomap::proto

namespace stereomap::proto {
namespace {

// Partitions route a session's samples (vehiclePartition): vehicle v of session a writes in
// "sm/a/v/v", which reaches the single server's wildcard, the cluster owner's session reader and
// v's own, never another session's or another vehicle's; the server's acknowledgement in v's
// partition reaches v alone.
TEST(Dds, PartitionsRouteASessionsSamples) {
  auto participant = makeParticipant();
  auto wildcard = Reader<PoseMsg>::create(participant, {kEverySessionPartition});
  auto session = Reader<PoseMsg>::create(participant, {sessionPartitions("a")});
  auto own = Reader<PoseMsg>::create(participant, {vehiclePartition("a", "v")});
  auto other = Reader<PoseMsg>::create(participant, {sessionPartitions("b")});
  auto other_vehicle = Reader<PoseMsg>::create(participant, {vehiclePartition("a", "w")});
  auto plain = Reader<PoseMsg>::create(participant);
  ASSERT_TRUE(wildcard && session && own && other && other_vehicle && plain);
  auto vehicle = Writer<PoseMsg>::create(participant, {vehiclePartition("a", "v")});
  ASSERT_TRUE(vehicle);
  ASSERT_TRUE((*vehicle)->waitForReaders(3, 5s));
  std::this_thread::sleep_for(300ms);  // a wrong match would show by now
  EXPECT_EQ((*vehicle)->matchedReaders(), 3) << "wildcard, session and own; not b, w, plain";

  PoseMsg pose;
  pose.vehicle_id = "v";
  pose.session_id = "a";
  pose.orientation = {0, 0, 0, 1};
  ASSERT_TRUE((*vehicle)->write(pose));
  EXPECT_EQ(takeAtLeast(**own, 1).size(), 1u);
  EXPECT_EQ(takeAtLeast(**wildcard, 1).size(), 1u);
  EXPECT_EQ(takeAtLeast(**session, 1).size(), 1u);
  std::vector<PoseMsg> none;
  (*other)->take(none, 200ms);
  (*other_vehicle)->take(none, 0ms);
  (*plain)->take(none, 0ms);
  EXPECT_TRUE(none.empty());

  auto v_acks = Reader<AckMsg>::create(participant, {vehiclePartition("a", "v")});
  auto w_acks = Reader<AckMsg>::create(participant, {vehiclePartition("a", "w")});
  auto server_acks = Writer<AckMsg>::create(participant, {vehiclePartition("a", "v")});
  ASSERT_TRUE(v_acks && w_acks && server_acks);
  EXPECT_TRUE((*server_acks)->waitForReaders(1, 5s));
  std::this_thread::sleep_for(300ms);
  EXPECT_EQ((*server_acks)->matchedReaders(), 1) << "v's reader only";
}

// A reader bound to its writers (the server's) takes a sample only when its writer's partition
// names the sample's own session and vehicle: vehicle v cannot write as w, nor into session b.
TEST(Dds, ABoundReaderRefusesASampleItsWriterMayNotSend) {
  auto participant = makeParticipant();
  auto server = Reader<PoseMsg>::create(participant, {kEverySessionPartition}, true);
  auto vehicle = Writer<PoseMsg>::create(participant, {vehiclePartition("a", "v")});
  ASSERT_TRUE(server && vehicle);
  ASSERT_TRUE((*vehicle)->waitForReaders(1, 5s));
  PoseMsg pose;
  pose.session_id = "a";
  pose.orientation = {0, 0, 0, 1};
  for (const char* as : {"v", "w", "v"}) {
    pose.vehicle_id = as;
    ASSERT_TRUE((*vehicle)->write(pose));
  }
  pose.vehicle_id = "v";
  pose.session_id = "b";
  ASSERT_TRUE((*vehicle)->write(pose));
  std::vector<PoseMsg> taken;
  std::vector<RefusedSample> refused;
  for (int i = 0; i < 50 && taken.size() + refused.size() < 4; ++i) {
    (*server)->take(taken, 100ms, &refused);
  }
  ASSERT_EQ(taken.size(), 2u);
  EXPECT_EQ(taken[0].vehicle_id, "v");
  ASSERT_EQ(refused.size(), 2u);
  for (const auto& sample : refused) {
    EXPECT_EQ(sample.reason, "identity");
    EXPECT_EQ(sample.writer_partition, "sm/a/v/v");
    EXPECT_NE(sample.detail.find("CN=v"), std::string::npos) << sample.detail;
  }
  EXPECT_EQ(refused[0].vehicle_id, "w");
  EXPECT_EQ(refused[1].session_id, "b");
}

// A security folder lacking a file is named before Cyclone sees it.
TEST(Dds, ASecurityFolderLackingAFileIsNamed) {
  const auto dir = std::filesystem::temp_directory_path() / "stereomap-dds-security-test";
  std::filesystem::create_directories(dir);
  auto participant = Participant::create(
      {.domain_id = kDomain, .config_file = STEREOMAP_DDS_CONFIG, .security_dir = dir.string()});
  ASSERT_FALSE(participant.ok());
  EXPECT_NE(participant.error().message.find("identity_ca.pem"), std::string::npos)
      << participant.error().message;
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace stereomap::proto
