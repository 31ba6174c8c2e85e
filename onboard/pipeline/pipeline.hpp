// The onboard pipeline: for each stereo frame of a source, compute disparity, turn it into
// a down-sampled cloud in the camera frame, Draco-encode it and publish a CloudFrame (with
// the sensor pose) and a Pose over DDS, paced to a frame rate. Main entry: runPipeline().
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>

#include "common/result.hpp"
#include "common/shutdown.hpp"
#include "onboard/camera/frame_source.hpp"
#include "onboard/stereo/depth.hpp"
#include "proto/cloud_codec.hpp"
#include "proto/dds.hpp"
#include "proto/messages.hpp"

namespace stereomap::pipeline {

struct PipelineOptions {
  std::string vehicle_id = "sim-1";
  std::string session_id = "session";
  double rate_hz = 10.0;  // frames are paced to this rate; 0 = as fast as possible
  stereo::MatcherOptions matcher = stereo::MatcherOptions::fast();
  stereo::CloudOptions cloud;
  proto::CloudCodecOptions codec;
  // How long to wait for a server's readers before the first frame (frames are kept by
  // DDS's durable history either way; this only avoids a silent start).
  std::chrono::milliseconds wait_for_server{3000};
  // Log progress every this many frames (0: never).
  uint64_t progress_every = 50;
};

struct PipelineSummary {
  uint64_t frames = 0;
  uint64_t points = 0;
  uint64_t payload_bytes = 0;
  uint64_t publish_errors = 0;
  uint64_t late_frames = 0;    // frames that started after their slot (the rate was not kept)
  double median_depth_ms = 0;  // disparity + cloud
  double median_encode_ms = 0;
  double median_frame_ms = 0;  // whole frame, source included
  bool stopped = false;        // ended by a stop request rather than the end of the source
};

// The DDS side of the vehicle: one writer per topic.
class VehiclePublisher {
 public:
  static common::Result<std::unique_ptr<VehiclePublisher>> create(
      std::shared_ptr<proto::Participant> participant);
  common::Status publish(const proto::SessionEventMsg& event);
  common::Status publish(const proto::PoseMsg& pose);
  common::Status publish(const proto::CloudFrameMsg& frame);
  bool waitForServer(std::chrono::milliseconds timeout) const;

 private:
  std::unique_ptr<proto::Writer<proto::SessionEventMsg>> events_;
  std::unique_ptr<proto::Writer<proto::PoseMsg>> poses_;
  std::unique_ptr<proto::Writer<proto::CloudFrameMsg>> clouds_;
};

// Messages for one frame (exposed for tests).
proto::PoseMsg makePoseMsg(const PipelineOptions& options, uint64_t seq, int64_t stamp_ns,
                           const common::Rigid3& T_map_body, const common::Vec3& velocity);
common::Result<proto::CloudFrameMsg> makeCloudFrameMsg(const PipelineOptions& options, uint64_t seq,
                                                       int64_t stamp_ns,
                                                       const common::Rigid3& T_map_camera,
                                                       const common::PointCloud& cloud_camera);
proto::SessionEventMsg makeSessionEvent(const PipelineOptions& options,
                                        const camera::StereoCamera& camera,
                                        proto::SessionEventKind kind);

// Runs until the source ends or `shutdown` is requested. With a null publisher nothing is
// sent (depth only). Frames without a ground-truth pose are skipped with a warning until
// visual odometry exists.
PipelineSummary runPipeline(camera::FrameSource& source, VehiclePublisher* publisher,
                            const PipelineOptions& options, const common::Shutdown& shutdown);

}  // namespace stereomap::pipeline
