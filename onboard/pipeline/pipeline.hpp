// The onboard pipeline: for each stereo frame of a source, estimate the pose (stereo visual
// odometry by default, or the source's ground truth), compute disparity, turn it into a
// down-sampled cloud in the camera frame, Draco-encode it and publish a CloudFrame (with the
// sensor pose) and a Pose over DDS, paced to a frame rate. Main entry: runPipeline().
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>

#include "common/result.hpp"
#include "common/shutdown.hpp"
#include "onboard/camera/frame_source.hpp"
#include "onboard/landing/landing_watch.hpp"
#include "onboard/link/cloud_link.hpp"
#include "onboard/link/outbox.hpp"
#include "onboard/odometry/odometry.hpp"
#include "onboard/posegraph/graph_follower.hpp"
#include "onboard/stereo/depth_step.hpp"
#include "proto/cloud_codec.hpp"
#include "proto/dds.hpp"
#include "proto/messages.hpp"

namespace stereomap::pipeline {

enum class PoseSource { kOdometry, kGroundTruth };

// One frame's outcome, for progress displays and trajectory files.
struct FrameReport {
  uint64_t index = 0;
  int64_t stamp_ns = 0;
  odometry::TrackingState state = odometry::TrackingState::kOk;
  common::Rigid3 T_map_body;  // as published (the odometry's; the graph's corrections go apart)
  common::Rigid3 T_map_camera;
  common::Rigid3 T_map_body_odometry;  // the odometry's own
  // When the source knows it; in the source's frame whatever PipelineOptions::frame says.
  std::optional<common::Rigid3> T_map_body_truth;
  double odometry_ms = 0;
  double frame_ms = 0;
};

struct PipelineOptions {
  std::string vehicle_id = "sim-1";
  std::string session_id = "session";
  double rate_hz = 10.0;  // frames are paced to this rate; 0 = as fast as possible
  // A live source (FrameSource::live) that falls behind the rate skips to the newest frame;
  // false: every frame is taken, late (tests that count frames on a loaded machine).
  bool skip_late = true;
  // Disparity and cloud, with noisy images' noise kept out (stereo::DepthStep).
  stereo::DepthOptions stereo;
  proto::CloudCodecOptions codec;
  // What of each cloud is sent (onboard/link): thinned to the map's voxels, clouds that bring
  // the map nothing new skipped, a byte budget. nullopt: every cloud whole.
  std::optional<link::CloudLinkOptions> link = link::CloudLinkOptions{};
  // How long to wait for a server's readers before the first frame (frames are kept by
  // DDS's durable history either way; this only avoids a silent start).
  std::chrono::milliseconds wait_for_server{3000};
  // At the end: how long to wait for the server to acknowledge the last samples.
  std::chrono::milliseconds flush_timeout{5000};
  // Log progress every this many frames (0: never).
  uint64_t progress_every = 50;
  PoseSource pose_source = PoseSource::kOdometry;
  odometry::VoOptions odometry;
  bool depth = true;  // false: poses only (odometry runs without the clouds)
  // A pose graph over the odometry's keyframes (loop closures, joins of lost tracks), solved
  // on a worker thread: every keyframe's corrected pose is sent after a solve that found a
  // place and moved some keyframe (a PoseCorrection, at most one per correction_period; the
  // server corrects the poses and clouds it has and gets with it, and fuses its map again);
  // the poses published stay the odometry's. The summary carries every frame's pose through
  // the final graph.
  bool pose_graph = false;
  std::chrono::milliseconds correction_period{1000};
  posegraph::KeyframeGraphOptions graph;
  // Watch for the landing pad (onboard/landing) in every frame and publish what is seen as a
  // LandingTarget: the pad in the camera and the map (through the pose published), the
  // deck's motion, distance and bearing.
  std::optional<landing::LandingWatchOptions> landing;
  std::function<void(const FrameReport&)> on_frame;  // after every frame, if set
  // The frame every map-frame pose is published in (poses, clouds' sensor poses, corrections,
  // landing targets): kSession, the source's map as given (the session's frame, shared by
  // its vehicles); kOwn, the vehicle's own, fixed at its first pose so that this pose is
  // published as start_pose (T_own_map = start_pose * T_map_body_first^-1); the server holds
  // such a vehicle's clouds apart until it has aligned its map into the session's. Ground
  // truth (FrameReport::T_map_body_truth) stays in the source's frame either way.
  proto::VehicleFrame frame = proto::VehicleFrame::kSession;
  common::Rigid3 start_pose;  // T_own_body of the first frame, with kOwn
};

struct PipelineSummary {
  uint64_t frames = 0;
  uint64_t points = 0;         // made by the depth step
  uint64_t payload_bytes = 0;  // of the clouds sent
  // What went on the link (proto::wireBytes: clouds, poses and the rest) over how long (the
  // frames' stamps), and what of the clouds.
  uint64_t wire_bytes = 0;
  double stream_seconds = 0;
  link::CloudLinkStats link;
  uint64_t publish_errors = 0;
  uint64_t late_frames = 0;  // frames that started after their slot (the rate was not kept)
  // A live source (a camera, the sim at a rate) that fell behind skips to the newest frame
  // instead of queueing: frames skipped so.
  uint64_t skipped_frames = 0;
  // With an outbox: what it sent again and what its spool holds and gave up.
  std::optional<link::OutboxStats> outbox;
  std::optional<link::SpoolStats> spool;
  bool flushed = true;           // everything acknowledged at the end
  std::string closed_by_server;  // why the server said the session takes no more ("": it did)
  double median_depth_ms = 0;    // disparity + cloud
  std::string depth_range;       // what the depth step searched and why (RigRange::explain)
  double image_noise_sigma = 0;  // the depth step's last image noise estimate, grey levels
  bool noisy_images = false;     // whether it treated the images as noisy
  double median_encode_ms = 0;
  double median_frame_ms = 0;  // whole frame, source included
  // The slowest frame (a frame slower than the period puts the next behind its slot), and the
  // furthest behind its slot a frame began (a period or more: late).
  double slowest_frame_ms = 0, most_behind_ms = 0;
  bool stopped = false;      // ended by a stop request rather than the end of the source
  uint64_t lost_frames = 0;  // odometry lost: the pose was a guess, no cloud was sent
  uint64_t degraded_frames = 0;
  double median_odometry_ms = 0;
  // The odometry's last estimate of the right image's offset against its calibration (px).
  double right_offset_px = 0;
  double right_gain = 1.0;  // and of the right camera's gain against the left
  // With pose_graph: T_map_body of every frame through the final graph, and what it found.
  std::vector<common::Rigid3> corrected_T_map_body;
  posegraph::FollowerStats graph;
  posegraph::G2oGraph keyframe_graph;  // the final graph, for --graph-out
  uint64_t corrections = 0;  // corrections the graph made (PoseCorrection samples, if publishing)
  // With landing: frames the pad was tracked in, and those with a pose published.
  uint64_t landing_tracked = 0, landing_poses = 0;
  // With VehicleFrame::kOwn: what the server last said of the vehicle's frame (acknowledgements
  // only come with an outbox), and T_session_own once aligned (x_session = T * x_own).
  proto::FrameState frame_state = proto::FrameState::kNone;
  common::Rigid3 T_session_own;
};

// The DDS side of the vehicle: one writer per topic and, with an outbox, the acknowledgements:
// poses, clouds, session events and corrections are then numbered in the vehicle's stream,
// kept in its spool until the server has journaled them, and sent again after an outage
// (onboard/link/outbox.hpp); landing targets, only worth their moment, are sent once.
class VehiclePublisher {
 public:
  // Everything is written, and acknowledgements read, in the vehicle's own DDS partition
  // (proto::vehiclePartition of the session and outbox.vehicle_id, which must be the
  // vehicle_id of every sample: the server refuses the rest). spool: null for samples sent
  // once (DDS's own history covers an outage of a few seconds).
  static common::Result<std::unique_ptr<VehiclePublisher>> create(
      const std::shared_ptr<proto::Participant>& participant, const std::string& session_id,
      std::unique_ptr<link::Spool> spool = nullptr, const link::OutboxOptions& outbox = {});
  // The spooled kinds get their stream, seq and unacked_from filled in.
  common::Status publish(proto::SessionEventMsg& event);
  common::Status publish(proto::PoseMsg& pose);
  common::Status publish(proto::CloudFrameMsg& frame);
  common::Status publish(proto::PoseCorrectionMsg& correction);
  common::Status publish(const proto::LandingTargetMsg& target);
  // Takes the acknowledgements that arrived (waiting up to `wait` for one) and sends again
  // what is due. Once a frame. An answer that the session is closed (AckStatus::
  // kSessionClosed, for this vehicle) is said once in the log, and from then on nothing is
  // sent to it (link::Outbox::closeSession: kept in the spool or given up, as the outbox's
  // keep_when_closed says).
  void service(std::chrono::milliseconds wait = std::chrono::milliseconds(0));
  bool waitForServer(std::chrono::milliseconds timeout) const;
  // Waits until the server acknowledged everything published (the final SessionEvent
  // included), up to `timeout`; false when something is still unacknowledged (with a spool
  // folder, it is kept there for the next run).
  bool flush(std::chrono::milliseconds timeout);
  // Whether a server's readers are matched.
  bool serverPresent() const;
  const link::Outbox* outbox() const { return outbox_ ? &*outbox_ : nullptr; }
  // The vehicle's own counters for the operator (VehicleStatus), at most once a
  // kStatusEvery; the spool's are added here. The bytes it took on the link (0: not due).
  size_t publishStatus(proto::VehicleStatusMsg status);
  static constexpr std::chrono::seconds kStatusEvery{1};
  // Why the server said the session takes no more samples; "" while it takes them.
  const std::string& closedBecause() const { return closed_because_; }
  // What the server's acknowledgements last said of this vehicle's frame (kNone: nothing, as
  // for a vehicle in the session's frame), and T_session_own while kAligned. Each change is
  // said once in the log.
  proto::FrameState frameState() const { return frame_state_; }
  const common::Rigid3& T_session_own() const { return T_session_own_; }

 private:
  common::Status write(const link::SpoolRecord& record);
  template <typename Message>
  common::Status send(Message& message);
  // Says the session started again, every kAnnounceEvery, while samples wait and no server
  // reads them.
  void announceWhileUnserved(bool server_present);
  void takeFrameState(const proto::AckMsg& ack);
  static constexpr std::chrono::seconds kAnnounceEvery{2};

  std::unique_ptr<proto::Writer<proto::SessionEventMsg>> events_;
  std::unique_ptr<proto::Writer<proto::PoseMsg>> poses_;
  std::unique_ptr<proto::Writer<proto::CloudFrameMsg>> clouds_;
  std::unique_ptr<proto::Writer<proto::PoseCorrectionMsg>> corrections_;
  std::unique_ptr<proto::Writer<proto::LandingTargetMsg>> landing_;
  std::unique_ptr<proto::Writer<proto::VehicleStatusMsg>> status_;
  std::unique_ptr<proto::Reader<proto::AckMsg>> acks_;
  std::string session_id_;
  std::string closed_because_;
  proto::FrameState frame_state_ = proto::FrameState::kNone;
  common::Rigid3 T_session_own_;
  std::chrono::steady_clock::time_point last_status_{};
  std::optional<link::Outbox> outbox_;
  std::vector<proto::AckMsg> ack_batch_;
  std::optional<proto::SessionEventMsg> announcement_;  // the start event as first sent
  std::chrono::steady_clock::time_point last_announced_{};
};

// Messages for one frame (exposed for tests).
proto::PoseMsg makePoseMsg(const PipelineOptions& options, uint64_t seq, int64_t stamp_ns,
                           const common::Rigid3& T_map_body, const common::Vec3& velocity,
                           const odometry::VoEstimate* estimate = nullptr);
common::Result<proto::CloudFrameMsg> makeCloudFrameMsg(const PipelineOptions& options,
                                                       const proto::CloudCodecOptions& codec,
                                                       uint64_t seq, int64_t stamp_ns,
                                                       const common::Rigid3& T_map_camera,
                                                       const common::PointCloud& cloud_camera,
                                                       double max_range_m);
// The pose graph's keyframe poses (odometry world frame, left camera) as the server takes
// them: T_map_body by stamp, through `anchor` (T_map_world) and the camera's mount.
proto::PoseCorrectionMsg makePoseCorrectionMsg(
    const PipelineOptions& options, uint64_t seq, int64_t stamp_ns,
    const std::vector<posegraph::KeyframePose>& keyframes, const common::Rigid3& anchor,
    const common::Rigid3& T_body_camera);
// What the landing watch saw in one frame, as the server takes it.
proto::LandingTargetMsg makeLandingTargetMsg(const PipelineOptions& options, uint64_t seq,
                                             int64_t stamp_ns, const landing::LandingReport& seen,
                                             landing::PoseMode mode);
proto::SessionEventMsg makeSessionEvent(const PipelineOptions& options,
                                        const camera::StereoCamera& camera,
                                        proto::SessionEventKind kind);

// Runs until the source ends or `shutdown` is requested. With a null publisher nothing is
// sent. With PoseSource::kGroundTruth, frames without a ground-truth pose are skipped with a
// warning. Odometry poses start at the source's first ground-truth pose when it has one
// (the map frame of a simulator or data set), else at the body frame's origin.
PipelineSummary runPipeline(camera::FrameSource& source, VehiclePublisher* publisher,
                            const PipelineOptions& options, const common::Shutdown& shutdown);

}  // namespace stereomap::pipeline
