// Synthetic inputs shared by tests: a square of points on the plane x = const, as a cloud
// and as a CloudFrame sample (Draco-encoded, sensor at the origin), and a bare pose sample.
#pragma once

#include <string>

#include "common/point_cloud.hpp"
#include "proto/cloud_codec.hpp"
#include "proto/messages.hpp"

namespace stereomap::testing {

// Points (x, y, z) with |y|, |z| <= half_side, `spacing` apart.
inline common::PointCloud planeCloud(double x, double half_side, double spacing) {
  common::PointCloud cloud;
  for (double y = -half_side; y <= half_side; y += spacing) {
    for (double z = -half_side; z <= half_side; z += spacing) cloud.points.emplace_back(x, y, z);
  }
  return cloud;
}

inline proto::CloudFrameMsg planeFrame(const std::string& vehicle, const std::string& session,
                                       uint64_t seq, const common::PointCloud& cloud) {
  proto::CloudFrameMsg frame;
  frame.vehicle_id = vehicle;
  frame.session_id = session;
  frame.seq = seq;
  frame.max_range = 10;
  frame.point_count = static_cast<uint32_t>(cloud.size());
  frame.payload = proto::encodeCloud(cloud).value();
  return frame;
}

// Vehicle "v1"'s frame in `session`: a 1 m square wall at x = wall_x, points 3 cm apart.
inline proto::CloudFrameMsg wallFrame(const std::string& session, double wall_x, uint64_t seq = 0) {
  return planeFrame("v1", session, seq, planeCloud(wall_x, 0.5, 0.03));
}

// Vehicle "v1"'s pose in `session`: at (x, 0, 0), not rotated.
inline proto::PoseMsg poseAt(const std::string& session, double x, int64_t stamp_ns) {
  proto::PoseMsg msg;
  msg.vehicle_id = "v1";
  msg.session_id = session;
  msg.stamp_ns = stamp_ns;
  msg.position = {x, 0, 0};
  return msg;
}

}  // namespace stereomap::testing
