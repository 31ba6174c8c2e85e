// Validation of every DDS sample before the server accepts it: identifiers, finite numbers,
// unit quaternions, sizes and a decodable payload. A rejection names a short reason (a
// metric label) and a detail for the log; nothing invalid reaches fusion or storage.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "common/geometry.hpp"
#include "common/point_cloud.hpp"
#include "proto/messages.hpp"

namespace stereomap::core {

struct IngestLimits {
  size_t max_payload_bytes = 4u << 20;  // below the IDL's 8 MiB bound
  uint32_t max_points = 1'000'000;
  double max_range_m = 100.0;
};

struct Rejection {
  std::string reason;  // e.g. "non_finite", "decode_failed", "oversize" (metric label)
  std::string detail;  // for people: what was wrong, naming the field
};

struct ValidCloud {
  common::PointCloud cloud_camera;
  common::Rigid3 T_map_camera;
  double max_range_m = 0;
};

struct ValidPose {
  int64_t stamp_ns = 0;
  common::Rigid3 T_map_body;
};

// Ids become URL parts and directory names: 1-64 of [A-Za-z0-9._-], not "." or "..".
bool isValidId(const std::string& id);

std::optional<Rejection> validateCloudFrame(const proto::CloudFrameMsg& frame,
                                            const IngestLimits& limits, ValidCloud& out);
// Everything validateCloudFrame checks but the payload (not decoded): for a journaled frame
// that a snapshot already holds, which needs counting, not its points.
std::optional<Rejection> validateCloudFrameFields(const proto::CloudFrameMsg& frame,
                                                  const IngestLimits& limits,
                                                  common::Rigid3& T_map_camera);
std::optional<Rejection> validatePose(const proto::PoseMsg& pose, ValidPose& out);
std::optional<Rejection> validateSessionEvent(const proto::SessionEventMsg& event);
// A pose graph's correction: ids, at least one and at most kMaxCorrectedKeyframes keyframes,
// stamps non-negative and strictly increasing, every pose finite with a unit quaternion.
// `out` gets the keyframes (stamp, T_map_body) in order.
std::optional<Rejection> validatePoseCorrection(const proto::PoseCorrectionMsg& correction,
                                                std::vector<ValidPose>& out);

// A landing target: ids, a reason of printable ASCII, every number finite, unit
// quaternions, covariances with a non-negative diagonal, a distance >= 0.
std::optional<Rejection> validateLandingTarget(const proto::LandingTargetMsg& target);
// Ids; a stamp that is not negative; counts below 2^53 (exact in JSON and JavaScript).
std::optional<Rejection> validateVehicleStatus(const proto::VehicleStatusMsg& status);

}  // namespace stereomap::core
