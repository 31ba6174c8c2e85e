#include "onboard/pipeline/pipeline.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <variant>
#include <vector>

#include "common/statistics.hpp"
#include "common/time.hpp"
#include "common/url.hpp"
#include "proto/pose_fields.hpp"
#include "proto/wire_size.hpp"

namespace stereomap::pipeline {

using Clock = std::chrono::steady_clock;

namespace {

using common::msSince;

template <typename T>
common::Result<std::unique_ptr<proto::Writer<T>>> makeWriter(
    const std::shared_ptr<proto::Participant>& participant, const std::string& partition) {
  return proto::Writer<T>::create(participant, {partition});
}

}  // namespace

common::Result<std::unique_ptr<VehiclePublisher>> VehiclePublisher::create(
    const std::shared_ptr<proto::Participant>& participant, const std::string& session_id,
    std::unique_ptr<link::Spool> spool, const link::OutboxOptions& outbox) {
  auto publisher = std::unique_ptr<VehiclePublisher>(new VehiclePublisher());
  // The vehicle's own partition: with DDS Security the only one its permissions allow.
  const std::string partition = proto::vehiclePartition(session_id, outbox.vehicle_id);
  auto events = makeWriter<proto::SessionEventMsg>(participant, partition);
  if (!events) return events.error();
  auto poses = makeWriter<proto::PoseMsg>(participant, partition);
  if (!poses) return poses.error();
  auto clouds = makeWriter<proto::CloudFrameMsg>(participant, partition);
  if (!clouds) return clouds.error();
  auto corrections = makeWriter<proto::PoseCorrectionMsg>(participant, partition);
  if (!corrections) return corrections.error();
  auto landing = makeWriter<proto::LandingTargetMsg>(participant, partition);
  if (!landing) return landing.error();
  auto status = makeWriter<proto::VehicleStatusMsg>(participant, partition);
  if (!status) return status.error();
  publisher->status_ = std::move(status).value();
  publisher->session_id_ = session_id;
  publisher->events_ = std::move(events).value();
  publisher->poses_ = std::move(poses).value();
  publisher->clouds_ = std::move(clouds).value();
  publisher->corrections_ = std::move(corrections).value();
  publisher->landing_ = std::move(landing).value();
  if (spool) {
    auto acks = proto::Reader<proto::AckMsg>::create(participant, {partition});
    if (!acks) return acks.error();
    publisher->acks_ = std::move(acks).value();
    publisher->outbox_.emplace(
        std::move(spool), outbox,
        [raw = publisher.get()](const link::SpoolRecord& record) { return raw->write(record); });
  }
  return publisher;
}

common::Status VehiclePublisher::write(const link::SpoolRecord& record) {
  return std::visit(
      [this](const auto& message) -> common::Status {
        using Message = std::decay_t<decltype(message)>;
        if constexpr (std::is_same_v<Message, proto::SessionEventMsg>)
          return events_->write(message);
        if constexpr (std::is_same_v<Message, proto::PoseMsg>) return poses_->write(message);
        if constexpr (std::is_same_v<Message, proto::CloudFrameMsg>) return clouds_->write(message);
        if constexpr (std::is_same_v<Message, proto::PoseCorrectionMsg>) {
          return corrections_->write(message);
        }
        // A server's record (FrameAlignmentMsg): never in a vehicle's spool.
        return common::makeError(common::ErrorCode::kInvalidArgument, "not a vehicle's sample");
      },
      record);
}

using common::steadyNs;

using common::printable;

template <typename Message>
common::Status VehiclePublisher::send(Message& message) {
  if (outbox_) return outbox_->send(message, steadyNs());
  return write(message);
}

common::Status VehiclePublisher::publish(proto::SessionEventMsg& event) {
  auto sent = send(event);
  if (event.kind == proto::SessionEventKind::kStarted) announcement_ = event;  // numbered now
  return sent;
}
common::Status VehiclePublisher::publish(proto::PoseMsg& pose) { return send(pose); }
common::Status VehiclePublisher::publish(proto::CloudFrameMsg& frame) { return send(frame); }
common::Status VehiclePublisher::publish(proto::PoseCorrectionMsg& correction) {
  return send(correction);
}
common::Status VehiclePublisher::publish(const proto::LandingTargetMsg& target) {
  if (outbox_ && outbox_->closed()) return common::Ok{};  // the server takes nothing more
  if (outbox_) outbox_->charge(proto::wireBytes(target), steadyNs());
  return landing_->write(target);
}

void VehiclePublisher::service(std::chrono::milliseconds wait) {
  if (!outbox_) return;
  ack_batch_.clear();
  acks_->take(ack_batch_, wait);
  for (const auto& ack : ack_batch_) {
    if (ack.status == proto::AckStatus::kSessionClosed && ack.session_id == session_id_ &&
        ack.vehicle_id == outbox_->options().vehicle_id) {
      // Only for a stream of ours (this process's, or one its spool holds samples of).
      const auto streams = outbox_->spool().streams();
      const bool ours = ack.stream == outbox_->stream() ||
                        std::find(streams.begin(), streams.end(), ack.stream) != streams.end();
      if (ours && !outbox_->closed()) {
        closed_because_ = printable(ack.reason.empty() ? "the server closed it" : ack.reason);
        const size_t held = outbox_->spool().stats().held;
        const size_t given_up = outbox_->closeSession(session_id_);
        spdlog::warn(
            "session '{}' was closed by the server ({}): this vehicle stops sending to it; {}",
            session_id_, closed_because_,
            outbox_->options().keep_when_closed
                ? fmt::format("the {} samples held and those made from now on stay in the "
                              "spool (--on-closed keep)",
                              held)
                : fmt::format("the {} samples held were given up, and those made from now on "
                              "are not kept (--on-closed drop)",
                              given_up));
      }
      continue;
    }
    takeFrameState(ack);
    outbox_->acknowledge(ack);
  }
  const bool present = serverPresent();
  announceWhileUnserved(present);
  outbox_->resend(steadyNs(), present);
  outbox_->spool().sync();
}

void VehiclePublisher::takeFrameState(const proto::AckMsg& ack) {
  // kNone: a vehicle in the session's frame, or a server that does not say.
  if (ack.frame_state == proto::FrameState::kNone || ack.session_id != session_id_ ||
      ack.vehicle_id != outbox_->options().vehicle_id) {
    return;
  }
  const auto T_session_own = proto::rigidFromFields(ack.frame_position, ack.frame_orientation);
  const bool aligned = ack.frame_state == proto::FrameState::kAligned;
  const bool moved =
      aligned && (T_session_own.translation != T_session_own_.translation ||
                  T_session_own.rotation.coeffs() != T_session_own_.rotation.coeffs());
  if (ack.frame_state == frame_state_ && !moved) return;
  frame_state_ = ack.frame_state;
  if (!aligned) {
    spdlog::info(
        "frame: aligning (the server holds this vehicle's clouds apart until its map overlaps "
        "the session's)");
    return;
  }
  T_session_own_ = T_session_own;
  const auto& t = ack.frame_position;
  const auto& q = ack.frame_orientation;
  spdlog::info(
      "frame: aligned into the session's: t {:.6f} {:.6f} {:.6f} q {:.6f} {:.6f} {:.6f} {:.6f}",
      t[0], t[1], t[2], q[0], q[1], q[2], q[3]);
}

bool VehiclePublisher::serverPresent() const { return poses_->matchedReaders() > 0; }

size_t VehiclePublisher::publishStatus(proto::VehicleStatusMsg status) {
  const auto now = Clock::now();
  if (now - last_status_ < kStatusEvery) return 0;
  if (outbox_ && outbox_->closed()) return 0;  // the server keeps no status of a closed session
  last_status_ = now;
  status.session_id = session_id_;
  status.stamp_ns = common::nowNs();
  if (outbox_) {
    const auto& spool = outbox_->spool().stats();
    status.spool_samples = spool.held;
    status.spool_bytes = spool.held_bytes;
    status.given_up = spool.dropped_clouds + spool.dropped_other + spool.dropped_closed;
    status.held_back = outbox_->stats().held_back;
    status.session_closed = outbox_->closed();
  }
  const size_t bytes = proto::wireBytes(status);
  if (outbox_) outbox_->charge(bytes, steadyNs());
  // Not kept or sent again: the next one carries as much.
  return status_->write(status) ? bytes : 0;
}

void VehiclePublisher::announceWhileUnserved(bool server_present) {
  // In a cluster, a session nobody serves (it ended and left memory while this vehicle was cut
  // off, or its server stopped) is served again when it is announced: its start event, sent
  // again as it was (the same stream and seq, so a server that has it counts a duplicate).
  if (server_present || !announcement_ || outbox_->caughtUp() || outbox_->closed()) return;
  const auto now = Clock::now();
  if (now - last_announced_ < kAnnounceEvery) return;
  last_announced_ = now;
  (void)events_->write(*announcement_);
}

bool VehiclePublisher::waitForServer(std::chrono::milliseconds timeout) const {
  return clouds_->waitForReaders(1, timeout);
}

bool VehiclePublisher::flush(std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  auto left = [&] {
    return std::max(std::chrono::milliseconds(0),
                    std::chrono::duration_cast<std::chrono::milliseconds>(
                        deadline - std::chrono::steady_clock::now()));
  };
  if (outbox_) {
    while (!outbox_->caughtUp() && !outbox_->closed() && left().count() > 0) {
      service(std::min(left(), std::chrono::milliseconds(100)));
    }
    outbox_->spool().sync(/*force=*/true);
    return outbox_->caughtUp();
  }
  const bool clouds = clouds_->waitForAcks(left());
  const bool poses = poses_->waitForAcks(left());
  const bool corrections = corrections_->waitForAcks(left());
  return events_->waitForAcks(left()) && clouds && poses && corrections;
}

// The fields every message of this vehicle starts with.
template <typename Message>
void address(Message& message, const PipelineOptions& options, uint64_t seq, int64_t stamp_ns) {
  message.vehicle_id = options.vehicle_id;
  message.session_id = options.session_id;
  message.seq = seq;
  message.stamp_ns = stamp_ns;
}

proto::PoseMsg makePoseMsg(const PipelineOptions& options, uint64_t seq, int64_t stamp_ns,
                           const common::Rigid3& T_map_body, const common::Vec3& velocity,
                           const odometry::VoEstimate* estimate) {
  proto::PoseMsg pose;
  address(pose, options, seq, stamp_ns);
  proto::fieldsFromRigid(T_map_body, pose.position, pose.orientation);
  pose.velocity = {velocity.x(), velocity.y(), velocity.z()};
  pose.tracking_state = proto::TrackingState::kOk;
  pose.source = proto::PoseSource::kGroundTruth;
  if (estimate != nullptr) {
    pose.source = proto::PoseSource::kVisualOdometry;
    switch (estimate->state) {
      case odometry::TrackingState::kInit:
        pose.tracking_state = proto::TrackingState::kInit;
        break;
      case odometry::TrackingState::kOk:
        pose.tracking_state = proto::TrackingState::kOk;
        break;
      case odometry::TrackingState::kDegraded:
        pose.tracking_state = proto::TrackingState::kDegraded;
        break;
      case odometry::TrackingState::kLost:
        pose.tracking_state = proto::TrackingState::kLost;
        break;
    }
    // Row-major 6x6 over (rotation, translation) in the map frame.
    for (int r = 0; r < 6; ++r) {
      for (int c = 0; c < 6; ++c)
        pose.covariance[static_cast<size_t>(6 * r + c)] = estimate->covariance(r, c);
    }
  }
  return pose;
}

proto::LandingTargetMsg makeLandingTargetMsg(const PipelineOptions& options, uint64_t seq,
                                             int64_t stamp_ns, const landing::LandingReport& seen,
                                             landing::PoseMode mode) {
  proto::LandingTargetMsg target;
  target.vehicle_id = options.vehicle_id;
  target.session_id = options.session_id;
  target.seq = seq;
  target.stamp_ns = stamp_ns;
  target.state = seen.state == landing::TrackState::kTracking ? proto::LandingState::kTracking
                 : seen.state == landing::TrackState::kLost   ? proto::LandingState::kLost
                                                              : proto::LandingState::kSearching;
  target.mode = mode == landing::PoseMode::kPatent ? proto::LandingMode::kPatent
                                                   : proto::LandingMode::kDefault;
  target.reason = seen.reason.substr(0, proto::kMaxLandingReason);
  target.has_pose = seen.has_pose;
  if (seen.has_pose) {
    proto::fieldsFromRigid(seen.pose.T_camera_pad, target.camera_position,
                           target.camera_orientation);
    proto::fieldsFromRigid(seen.T_map_pad, target.map_position, target.map_orientation);
    for (int r = 0; r < 6; ++r) {
      for (int c = 0; c < 6; ++c) {
        target.camera_covariance[static_cast<size_t>(r * 6 + c)] = seen.pose.covariance(r, c);
        target.map_covariance[static_cast<size_t>(r * 6 + c)] = seen.map_covariance(r, c);
      }
    }
    target.distance = seen.bearing.distance_m;
    target.bearing_deg = seen.bearing.bearing_deg;
    target.reprojection_px = seen.pose.rms_px;
  }
  if (seen.deck.valid) {
    for (int i = 0; i < 3; ++i) {
      target.deck_velocity[static_cast<size_t>(i)] = seen.deck.velocity[i];
      target.deck_angular_rate[static_cast<size_t>(i)] = seen.deck.angular_rate[i];
    }
  }
  return target;
}

proto::PoseCorrectionMsg makePoseCorrectionMsg(
    const PipelineOptions& options, uint64_t seq, int64_t stamp_ns,
    const std::vector<posegraph::KeyframePose>& keyframes, const common::Rigid3& anchor,
    const common::Rigid3& T_body_camera) {
  proto::PoseCorrectionMsg correction;
  address(correction, options, seq, stamp_ns);
  const common::Rigid3 T_camera_body = T_body_camera.inverse();
  correction.keyframes.reserve(keyframes.size());
  for (const auto& k : keyframes) {
    proto::KeyframePoseMsg pose;
    pose.stamp_ns = k.stamp_ns;
    proto::fieldsFromRigid(anchor * k.T_world_camera * T_camera_body, pose.position,
                           pose.orientation);
    correction.keyframes.push_back(pose);
  }
  return correction;
}

common::Result<proto::CloudFrameMsg> makeCloudFrameMsg(const PipelineOptions& options,
                                                       const proto::CloudCodecOptions& codec,
                                                       uint64_t seq, int64_t stamp_ns,
                                                       const common::Rigid3& T_map_camera,
                                                       const common::PointCloud& cloud_camera,
                                                       double max_range_m) {
  auto payload = proto::encodeCloud(cloud_camera, codec);
  if (!payload) return payload.error();
  proto::CloudFrameMsg frame;
  address(frame, options, seq, stamp_ns);
  proto::fieldsFromRigid(T_map_camera, frame.sensor_position, frame.sensor_orientation);
  frame.max_range = stereo::farthestPoint(cloud_camera, static_cast<float>(max_range_m)) * 1.001f;
  frame.point_count = static_cast<uint32_t>(cloud_camera.size());
  frame.encoding = codec.encoding;
  frame.quantization_bits = static_cast<uint8_t>(codec.quantization_bits);
  frame.has_intensity = cloud_camera.hasIntensity();
  frame.payload = std::move(payload).value();
  return frame;
}

proto::SessionEventMsg makeSessionEvent(const PipelineOptions& options,
                                        const camera::StereoCamera& camera,
                                        proto::SessionEventKind kind) {
  proto::SessionEventMsg event;
  event.vehicle_id = options.vehicle_id;
  event.session_id = options.session_id;
  event.stamp_ns = common::nowNs();
  event.kind = kind;
  event.width = static_cast<uint32_t>(camera.width);
  event.height = static_cast<uint32_t>(camera.height);
  event.fx = camera.fx;
  event.fy = camera.fy;
  event.cx = camera.cx;
  event.cy = camera.cy;
  event.baseline = camera.baseline;
  // The voxel the clouds are thinned to: a server mapping finer than that gets too few points.
  event.resolution_hint = options.link ? options.link->map_resolution_m : 0;
  event.frame = options.frame;
  return event;
}

namespace {

// One run of the pipeline: the state that lives across frames, and each frame's steps in
// order (pose, correction, landing, pose message, depth, cloud), then the summary.
class PipelineRun {
 public:
  PipelineRun(camera::FrameSource& source, VehiclePublisher* publisher,
              const PipelineOptions& options)
      : source_(source),
        publisher_(publisher),
        options_(options),
        depth_step_(source.camera(), options.stereo) {
    if (options.pose_source == PoseSource::kOdometry) {
      odometry_.emplace(source.camera(), options.odometry);
    }
    if (odometry_ && options.pose_graph) {
      graph_.emplace(source.camera(), options.graph, /*background=*/true);
    }
    if (options.landing) landing_.emplace(source.camera(), *options.landing);
    if (options.link) cloud_link_.emplace(*options.link);
    if (options.depth && depth_step_.range()) {
      summary_.depth_range = depth_step_.describeRange();
      spdlog::info("depth range from the rig: {}", summary_.depth_range);
    }
  }

  // Waits for a server (a while), then says the session started.
  void start() {
    if (publisher_ == nullptr) return;
    if (!publisher_->waitForServer(options_.wait_for_server)) {
      spdlog::warn(
          "no server has subscribed after {} ms; publishing anyway (the last frames "
          "stay available to a server that joins later)",
          options_.wait_for_server.count());
    }
    publish(makeSessionEvent(options_, source_.camera(), proto::SessionEventKind::kStarted),
            "SessionEvent");
  }

  void step(const camera::SourceFrame& frame, Clock::time_point frame_start) {
    FrameReport report{frame.index, frame.stamp_ns};
    report.T_map_body_truth = frame.T_map_body;
    // The left camera's mount; a forward-looking camera when the source does not say.
    const common::Rigid3 T_body_camera = frame.mount();
    std::optional<odometry::VoEstimate> estimate;
    const auto T_source_body = pose(frame, T_body_camera, report, estimate);
    if (!T_source_body) {
      spdlog::warn("frame {} has no ground-truth pose; skipped (use --vo fast)", frame.index);
      return;
    }
    if (options_.frame == proto::VehicleFrame::kOwn && !T_own_source_) {
      T_own_source_ = options_.start_pose * T_source_body->inverse();
    }
    // From here on "map" is the frame published in (published()).
    const common::Rigid3 T_map_body = published(*T_source_body);
    report.T_map_body_odometry = T_map_body;
    report.T_map_body = T_map_body;
    report.T_map_camera = T_map_body * T_body_camera;
    // Before this frame's pose: a correction may name keyframes up to the previous frame.
    sendCorrection(frame.stamp_ns, T_body_camera, /*now=*/false);
    last_T_body_camera_ = T_body_camera;
    last_stamp_ = frame.stamp_ns;
    const common::Vec3 velocity = velocityAt(frame.stamp_ns, T_map_body);
    watchLanding(frame, T_map_body, T_body_camera);
    // The pose goes first, whatever becomes of the cloud.
    auto pose_msg = makePoseMsg(options_, summary_.frames, frame.stamp_ns, T_map_body, velocity,
                                estimate ? &*estimate : nullptr);
    publish(pose_msg, "Pose");
    summary_.wire_bytes += proto::wireBytes(pose_msg);
    if (!first_stamp_) first_stamp_ = frame.stamp_ns;
    summary_.stream_seconds = common::nsToSeconds(frame.stamp_ns - *first_stamp_);
    // A lost frame's pose is a guess: it is published (so that operators see the state) but
    // its cloud is not, and nothing is computed that only feeds the map.
    const bool mapped =
        options_.depth && (!estimate || estimate->state != odometry::TrackingState::kLost);
    if (!mapped) {
      depth_step_.reset();  // no pose to carry depth along
    } else {
      const auto cloud = depthOf(frame, report, estimate);
      const double payload_kib = sendCloud(frame, report, cloud);
      summary_.points += cloud.size();
      if (options_.progress_every != 0 && (summary_.frames + 1) % options_.progress_every == 0) {
        spdlog::info("frame {}: {} points, {:.1f} KiB sent, depth {:.1f} ms", summary_.frames + 1,
                     cloud.size(), payload_kib, depth_ms_.back());
      }
    }
    ++summary_.frames;
    // Acknowledgements, and what an outage left unacknowledged, after the live samples; the
    // vehicle's counters for the operator.
    if (publisher_ != nullptr) {
      publisher_->service();
      proto::VehicleStatusMsg status;
      status.vehicle_id = options_.vehicle_id;
      status.frames = summary_.frames;
      status.skipped_frames = summary_.skipped_frames;
      status.late_frames = summary_.late_frames;
      summary_.wire_bytes += publisher_->publishStatus(std::move(status));
    }
    report.frame_ms = msSince(frame_start);
    frame_ms_.push_back(report.frame_ms);
    if (options_.on_frame) options_.on_frame(report);
  }

  // The graph's last word, the session's end (acknowledged, a while), and the summary.
  PipelineSummary finish() {
    if (graph_ && last_T_body_camera_) {
      graph_->waitUntilCaughtUp();
      sendCorrection(last_stamp_, *last_T_body_camera_, /*now=*/true);
    }
    if (publisher_ != nullptr) {
      publish(makeSessionEvent(options_, source_.camera(), proto::SessionEventKind::kEnded),
              "SessionEvent");
      // Leaving at once would drop what the server has not acknowledged yet (the end event).
      summary_.flushed = publisher_->flush(options_.flush_timeout);
      summary_.closed_by_server = publisher_->closedBecause();
      if (!summary_.flushed && !summary_.closed_by_server.empty()) {
        spdlog::warn("session '{}' was closed by the server ({}): its last samples were not sent",
                     options_.session_id, summary_.closed_by_server);
      } else if (!summary_.flushed) {
        spdlog::warn("the server did not acknowledge the last samples within {} ms{}",
                     options_.flush_timeout.count(),
                     publisher_->outbox() ? "; the spool keeps them for the next run on it"
                                          : "; it learns of the end when the vehicle falls silent");
      }
      summary_.frame_state = publisher_->frameState();
      summary_.T_session_own = publisher_->T_session_own();
      if (const auto* outbox = publisher_->outbox()) {
        summary_.outbox = outbox->stats();
        summary_.spool = outbox->spool().stats();
        summary_.wire_bytes += outbox->stats().resent_bytes;
      }
    }
    if (cloud_link_) summary_.link = cloud_link_->stats();
    summary_.median_depth_ms = common::median(depth_ms_).value_or(0.0);
    summary_.image_noise_sigma = depth_step_.noiseSigma();
    summary_.noisy_images = depth_step_.noisy();
    summary_.median_encode_ms = common::median(encode_ms_).value_or(0.0);
    summary_.median_frame_ms = common::median(frame_ms_).value_or(0.0);
    if (!frame_ms_.empty()) {
      summary_.slowest_frame_ms = *std::max_element(frame_ms_.begin(), frame_ms_.end());
    }
    summary_.median_odometry_ms = common::median(odometry_ms_).value_or(0.0);
    if (graph_) {
      const auto poses = graph_->finish();
      for (size_t i = 0; i < poses.size(); ++i) {
        summary_.corrected_T_map_body.push_back(
            published(*anchor_ * poses[i] * T_body_cameras_[i].inverse()));
      }
      summary_.graph = graph_->stats();
      summary_.keyframe_graph = graph_->keyframeGraph();
    }
    return summary_;
  }

  PipelineSummary& summary() { return summary_; }

 private:
  template <typename Message>
  void publish(Message&& message, const char* what) {
    if (publisher_ == nullptr) return;
    if (auto status = publisher_->publish(message); !status) {
      ++summary_.publish_errors;
      spdlog::warn("could not publish {}: {}", what, status.error().message);
    }
  }

  // A pose in the source's map frame as published: in the vehicle's own frame with
  // VehicleFrame::kOwn (once fixed at the first pose), else as it is. Every map-frame pose the
  // vehicle sends goes through here.
  common::Rigid3 published(const common::Rigid3& T_source_x) const {
    return T_own_source_ ? *T_own_source_ * T_source_x : T_source_x;
  }

  // The body's pose in the source's map frame: the odometry's (anchored at the source's first
  // ground truth), or the source's ground truth; nullopt when there is none.
  std::optional<common::Rigid3> pose(const camera::SourceFrame& frame,
                                     const common::Rigid3& T_body_camera, FrameReport& report,
                                     std::optional<odometry::VoEstimate>& estimate) {
    if (!odometry_) return frame.T_map_body;
    estimate = odometry_->track(frame.left, frame.right);
    odometry_ms_.push_back(estimate->milliseconds);
    if (!anchor_) anchor_ = frame.T_map_camera_truth();
    const common::Rigid3 T_map_body = *anchor_ * estimate->T_world_camera * T_body_camera.inverse();
    // With the graph, the odometry's own poses are still what is published: the graph's
    // corrections go separately (PoseCorrection), and the server applies them to every
    // pose and cloud, earlier and later ones alike. Published poses corrected live would
    // jump whenever the graph moved, which no correction of keyframes could undo between them.
    if (graph_) {
      graph_->follow({frame.stamp_ns, estimate->T_world_camera, estimate->covariance,
                      estimate->keyframe, estimate->state == odometry::TrackingState::kLost,
                      frame.left, frame.right});
      T_body_cameras_.push_back(T_body_camera);
    }
    report.state = estimate->state;
    report.odometry_ms = estimate->milliseconds;
    summary_.lost_frames += estimate->state == odometry::TrackingState::kLost;
    summary_.degraded_frames += estimate->state == odometry::TrackingState::kDegraded;
    summary_.right_offset_px = estimate->right_offset_px;
    summary_.right_gain = estimate->right_gain;
    return T_map_body;
  }

  // Sends the graph's newest correction, at most once per period (or now, at the end); the
  // camera's mount is taken as fixed (the current frame's).
  void sendCorrection(int64_t stamp_ns, const common::Rigid3& T_body_camera, bool now) {
    if (!graph_) return;
    if (auto moved = graph_->takeCorrection(); !moved.empty()) {
      unsent_correction_ = std::move(moved);
    }
    if (unsent_correction_.empty()) return;
    if (!now && last_correction_ && Clock::now() - *last_correction_ < options_.correction_period) {
      return;
    }
    if (publisher_ != nullptr) {
      publish(makePoseCorrectionMsg(options_, summary_.corrections, stamp_ns, unsent_correction_,
                                    published(*anchor_), T_body_camera),
              "PoseCorrection");
      spdlog::info(
          "pose graph: sent the corrected poses of {} keyframes ({} loop closures, {} "
          "tracks joined so far)",
          unsent_correction_.size(), graph_->stats().loops, graph_->stats().joined_tracks);
    }
    ++summary_.corrections;
    unsent_correction_.clear();
    last_correction_ = Clock::now();
  }

  // The body's velocity in the map (the VO paper's eq. 10): a finite difference of the
  // published positions, whichever source gave them.
  common::Vec3 velocityAt(int64_t stamp_ns, const common::Rigid3& T_map_body) {
    common::Vec3 velocity = common::Vec3::Zero();
    if (previous_pose_ && stamp_ns > previous_stamp_) {
      velocity = (T_map_body.translation - previous_pose_->translation) /
                 common::nsToSeconds(stamp_ns - previous_stamp_);
    }
    previous_pose_ = T_map_body;
    previous_stamp_ = stamp_ns;
    return velocity;
  }

  void watchLanding(const camera::SourceFrame& frame, const common::Rigid3& T_map_body,
                    const common::Rigid3& T_body_camera) {
    if (!landing_) return;
    // The world's frame stays the source's: T_world_map of the frame published in.
    common::Rigid3 T_world_map = frame.T_world_map.value_or(common::Rigid3{});
    if (T_own_source_) T_world_map = T_world_map * T_own_source_->inverse();
    const auto& seen = landing_->update(common::nsToSeconds(frame.stamp_ns), frame.left,
                                        frame.right, T_map_body, T_body_camera, T_world_map);
    summary_.landing_tracked += seen.state == landing::TrackState::kTracking;
    summary_.landing_poses += seen.has_pose;
    publish(makeLandingTargetMsg(options_, summary_.frames, frame.stamp_ns, seen,
                                 options_.landing->pose.mode),
            "LandingTarget");
  }

  // The frame's cloud in the camera frame, and the images' noise said when it changes.
  common::PointCloud depthOf(const camera::SourceFrame& frame, const FrameReport& report,
                             const std::optional<odometry::VoEstimate>& estimate) {
    const auto depth_start = Clock::now();
    const int was_level = depth_step_.level();
    auto cloud = depth_step_.compute(frame.left, frame.right, report.T_map_camera,
                                     estimate ? estimate->right_offset_px : 0.0,  // odometry.hpp
                                     frame.raw_noise_sigma);
    depth_ms_.push_back(msSince(depth_start));
    if (depth_step_.level() != was_level || summary_.frames == 0) {
      if (depth_step_.noisy()) {
        spdlog::info(
            "images are noisy (noise sigma {:.1f} grey levels, level {}): depth from smoothed "
            "images, averaged over frames",
            depth_step_.noiseSigma(), depth_step_.level());
      } else {
        spdlog::info("images are clean (noise sigma {:.1f} grey levels): depth frame by frame",
                     depth_step_.noiseSigma());
      }
    }
    return cloud;
  }

  // What of the cloud the link takes (thinned, or nothing when it brings nothing new),
  // encoded and sent; the payload's KiB (0 when nothing went).
  double sendCloud(const camera::SourceFrame& frame, const FrameReport& report,
                   const common::PointCloud& cloud) {
    const auto encode_start = Clock::now();
    std::optional<common::PointCloud> thinned;
    if (cloud_link_) thinned = cloud_link_->prepare(cloud, report.T_map_camera, frame.stamp_ns);
    const common::PointCloud* to_send = cloud_link_ ? (thinned ? &*thinned : nullptr) : &cloud;
    if (to_send == nullptr) return 0;
    proto::CloudCodecOptions codec = options_.codec;
    if (cloud_link_) {
      codec.quantization_bits = cloud_link_->quantizationBits(*to_send, codec.quantization_bits);
    }
    auto cloud_msg = makeCloudFrameMsg(options_, codec, clouds_sent_, frame.stamp_ns,
                                       report.T_map_camera, *to_send, depth_step_.maxRange());
    encode_ms_.push_back(msSince(encode_start));
    if (!cloud_msg) {
      spdlog::error("frame {}: cannot encode the cloud: {}", frame.index,
                    cloud_msg.error().message);
      return 0;
    }
    publish(*cloud_msg, "CloudFrame");
    const size_t bytes = proto::wireBytes(*cloud_msg);
    if (cloud_link_) cloud_link_->sent(frame.stamp_ns, bytes, cloud_msg->payload.size());
    ++clouds_sent_;
    summary_.wire_bytes += bytes;
    summary_.payload_bytes += cloud_msg->payload.size();
    return cloud_msg->payload.size() / 1024.0;
  }

  camera::FrameSource& source_;
  VehiclePublisher* const publisher_;
  const PipelineOptions& options_;
  PipelineSummary summary_;
  stereo::DepthStep depth_step_;
  std::optional<odometry::StereoOdometry> odometry_;
  std::optional<posegraph::GraphFollower> graph_;
  std::optional<landing::LandingWatch> landing_;
  std::optional<link::CloudLink> cloud_link_;
  std::vector<double> depth_ms_, encode_ms_, frame_ms_, odometry_ms_;
  std::vector<common::Rigid3> T_body_cameras_;  // per frame, for the corrected trajectory
  std::optional<common::Rigid3> anchor_;        // T_map_camera of the odometry's world frame
  // T_own_map with VehicleFrame::kOwn, fixed at the first pose (published()).
  std::optional<common::Rigid3> T_own_source_;
  // The graph's newest keyframe poses not yet sent, and when the last were.
  std::vector<posegraph::KeyframePose> unsent_correction_;
  std::optional<Clock::time_point> last_correction_;
  uint64_t clouds_sent_ = 0;  // the clouds' seq: +1 per cloud sent
  std::optional<int64_t> first_stamp_;
  std::optional<common::Rigid3> last_T_body_camera_;
  int64_t last_stamp_ = 0;
  std::optional<common::Rigid3> previous_pose_;
  int64_t previous_stamp_ = 0;
};

}  // namespace

PipelineSummary runPipeline(camera::FrameSource& source, VehiclePublisher* publisher,
                            const PipelineOptions& options, const common::Shutdown& shutdown) {
  PipelineRun run(source, publisher, options);
  run.start();
  // Frame i's slot is start + i * period; a frame begun past the next slot is late.
  const auto start = Clock::now();
  const auto period = options.rate_hz > 0
                          ? std::chrono::duration_cast<Clock::duration>(
                                std::chrono::duration<double>(1.0 / options.rate_hz))
                          : Clock::duration::zero();
  for (uint64_t i = 0;; ++i) {
    const auto slot = start + period * static_cast<long>(i);
    if (shutdown.waitFor(slot - Clock::now())) {
      run.summary().stopped = true;
      break;
    }
    if (period > Clock::duration::zero()) {
      run.summary().most_behind_ms =
          std::max(run.summary().most_behind_ms,
                   std::chrono::duration<double, std::milli>(Clock::now() - slot).count());
    }
    if (Clock::now() - slot > period && period > Clock::duration::zero()) {
      if (source.live() && options.skip_late) {
        // Frames of the slots that passed are not worth taking: the newest one is.
        const auto behind = static_cast<uint64_t>((Clock::now() - slot) / period);
        source.skip(behind);
        i += behind;
        run.summary().skipped_frames += behind;
      } else {
        ++run.summary().late_frames;
      }
    }
    const auto taken = Clock::now();
    auto frame = source.next();
    if (!frame) break;
    // A live source's next() waits for its camera (the simulators render as a camera's own
    // hardware would, see camera::PrefetchSource; the first frame too): the vehicle's work on
    // a frame starts when the frame is in hand. Reading a recording is the vehicle's work.
    const auto frame_start = source.live() ? Clock::now() : taken;
    run.step(*frame, frame_start);
  }
  return run.finish();
}

}  // namespace stereomap::pipeline
