#include "server/core/validate.hpp"

#include <algorithm>
#include <cmath>

#include "proto/cloud_codec.hpp"
#include "proto/pose_fields.hpp"

namespace stereomap::core {

namespace {

template <size_t N>
bool allFinite(const std::array<double, N>& values) {
  return std::all_of(values.begin(), values.end(), [](double v) { return std::isfinite(v); });
}

std::optional<Rejection> checkIds(const std::string& vehicle, const std::string& session) {
  if (!isValidId(vehicle)) {
    return Rejection{"bad_id", "vehicle_id '" + vehicle + "' is not 1-64 of [A-Za-z0-9._-]"};
  }
  if (!isValidId(session)) {
    return Rejection{"bad_id", "session_id '" + session + "' is not 1-64 of [A-Za-z0-9._-]"};
  }
  return std::nullopt;
}

// A pose from position + x y z w orientation, or a rejection naming `what`.
std::optional<Rejection> checkPose(const std::array<double, 3>& position,
                                   const std::array<double, 4>& orientation,
                                   const std::string& what, common::Rigid3& out) {
  if (!allFinite(position)) return Rejection{"non_finite", what + " position is not finite"};
  if (!allFinite(orientation)) return Rejection{"non_finite", what + " orientation is not finite"};
  const common::Quat q = proto::quatFromFields(orientation);
  if (!common::isUnitQuaternion(q)) {
    return Rejection{"bad_quaternion", what + " orientation is not a unit quaternion (norm " +
                                           std::to_string(q.norm()) + ")"};
  }
  out = {q.normalized(), common::Vec3(position[0], position[1], position[2])};
  return std::nullopt;
}

}  // namespace

bool isValidId(const std::string& id) {
  if (id.empty() || id.size() > proto::kMaxIdLength || id == "." || id == "..") return false;
  return std::all_of(id.begin(), id.end(), [](char c) {
    return std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '_' || c == '-';
  });
}

std::optional<Rejection> validateCloudFrameFields(const proto::CloudFrameMsg& frame,
                                                  const IngestLimits& limits,
                                                  common::Rigid3& T_map_camera) {
  if (auto bad = checkIds(frame.vehicle_id, frame.session_id)) return bad;
  if (frame.payload.size() > limits.max_payload_bytes) {
    return Rejection{"oversize", "payload of " + std::to_string(frame.payload.size()) +
                                     " bytes exceeds the limit of " +
                                     std::to_string(limits.max_payload_bytes)};
  }
  if (frame.point_count > limits.max_points) {
    return Rejection{"oversize", "point_count " + std::to_string(frame.point_count) +
                                     " exceeds the limit of " + std::to_string(limits.max_points)};
  }
  if (!std::isfinite(frame.max_range) || frame.max_range <= 0 ||
      frame.max_range > limits.max_range_m) {
    return Rejection{"bad_range", "max_range " + std::to_string(frame.max_range) +
                                      " is not in (0, " + std::to_string(limits.max_range_m) + "]"};
  }
  return checkPose(frame.sensor_position, frame.sensor_orientation, "sensor", T_map_camera);
}

std::optional<Rejection> validateCloudFrame(const proto::CloudFrameMsg& frame,
                                            const IngestLimits& limits, ValidCloud& out) {
  if (auto bad = validateCloudFrameFields(frame, limits, out.T_map_camera)) return bad;
  auto cloud = proto::decodeCloud(frame.payload, proto::payloadInfo(frame));
  if (!cloud) {
    const bool miscounted = cloud.error().code == common::ErrorCode::kConflict;
    return Rejection{miscounted ? "point_count_mismatch" : "decode_failed", cloud.error().message};
  }
  out.cloud_camera = std::move(cloud).value();
  if (out.cloud_camera.size() != frame.point_count) {
    return Rejection{"point_count_mismatch",
                     "payload holds " + std::to_string(out.cloud_camera.size()) +
                         " points, point_count says " + std::to_string(frame.point_count)};
  }
  out.max_range_m = frame.max_range;
  return std::nullopt;
}

std::optional<Rejection> validatePose(const proto::PoseMsg& pose, ValidPose& out) {
  if (auto bad = checkIds(pose.vehicle_id, pose.session_id)) return bad;
  if (!allFinite(pose.velocity) || !allFinite(pose.covariance)) {
    return Rejection{"non_finite", "velocity or covariance is not finite"};
  }
  if (auto bad = checkPose(pose.position, pose.orientation, "pose", out.T_map_body)) return bad;
  if (pose.stamp_ns < 0) return Rejection{"bad_stamp", "stamp_ns is negative"};
  out.stamp_ns = pose.stamp_ns;
  return std::nullopt;
}

std::optional<Rejection> validatePoseCorrection(const proto::PoseCorrectionMsg& correction,
                                                std::vector<ValidPose>& out) {
  out.clear();
  if (auto bad = checkIds(correction.vehicle_id, correction.session_id)) return bad;
  if (correction.keyframes.empty()) return Rejection{"empty", "a correction without keyframes"};
  if (correction.keyframes.size() > proto::kMaxCorrectedKeyframes) {
    return Rejection{"oversize", std::to_string(correction.keyframes.size()) + " keyframes"};
  }
  out.reserve(correction.keyframes.size());
  for (size_t i = 0; i < correction.keyframes.size(); ++i) {
    const auto& k = correction.keyframes[i];
    if (k.stamp_ns < 0 || (i > 0 && k.stamp_ns <= correction.keyframes[i - 1].stamp_ns)) {
      out.clear();
      return Rejection{"bad_stamp", "keyframe " + std::to_string(i) +
                                        ": stamps must be non-negative and strictly increasing"};
    }
    ValidPose pose{k.stamp_ns, {}};
    if (auto bad = checkPose(k.position, k.orientation, "keyframe", pose.T_map_body)) {
      out.clear();
      bad->detail = "keyframe " + std::to_string(i) + ": " + bad->detail;
      return bad;
    }
    out.push_back(pose);
  }
  return std::nullopt;
}

std::optional<Rejection> validateVehicleStatus(const proto::VehicleStatusMsg& status) {
  if (auto bad = checkIds(status.vehicle_id, status.session_id)) return bad;
  if (status.stamp_ns < 0) return Rejection{"bad_stamp", "stamp_ns is negative"};
  // Counts go to JSON and to the viewer, whose numbers are exact only below 2^53: a count
  // beyond could not be real anyway.
  constexpr uint64_t kMaxCount = (uint64_t{1} << 53) - 1;
  for (const uint64_t count :
       {status.frames, status.skipped_frames, status.late_frames, status.spool_samples,
        status.spool_bytes, status.given_up, status.held_back}) {
    if (count > kMaxCount) return Rejection{"oversize", "a count beyond 2^53"};
  }
  return std::nullopt;
}

std::optional<Rejection> validateLandingTarget(const proto::LandingTargetMsg& target) {
  if (auto bad = checkIds(target.vehicle_id, target.session_id)) return bad;
  if (target.reason.size() > proto::kMaxLandingReason) {
    return Rejection{"oversize",
                     "landing reason of " + std::to_string(target.reason.size()) + " bytes"};
  }
  // Printable ASCII only: it goes into JSON (which must be UTF-8) and onto operators' screens.
  for (const char c : target.reason) {
    const auto byte = static_cast<unsigned char>(c);
    if (byte < 0x20 || byte > 0x7e) {
      return Rejection{"bad_text", "landing reason with a byte that is not printable ASCII"};
    }
  }
  common::Rigid3 unused;
  if (auto bad =
          checkPose(target.camera_position, target.camera_orientation, "pad in camera", unused)) {
    return bad;
  }
  if (auto bad = checkPose(target.map_position, target.map_orientation, "pad in map", unused)) {
    return bad;
  }
  for (const auto* covariance : {&target.camera_covariance, &target.map_covariance}) {
    for (size_t i = 0; i < covariance->size(); ++i) {
      const double v = (*covariance)[i];
      if (!std::isfinite(v) || (i % 7 == 0 && v < 0)) {
        return Rejection{"non_finite", "landing covariance: not finite or a negative variance"};
      }
    }
  }
  for (const auto* vector : {&target.deck_velocity, &target.deck_angular_rate}) {
    for (const double v : *vector) {
      if (!std::isfinite(v)) return Rejection{"non_finite", "deck motion is not finite"};
    }
  }
  if (!std::isfinite(target.distance) || target.distance < 0 ||
      !std::isfinite(target.bearing_deg) || std::abs(target.bearing_deg) > 360 ||
      !std::isfinite(target.reprojection_px) || target.reprojection_px < 0) {
    return Rejection{"non_finite", "landing distance, bearing or reprojection error out of range"};
  }
  return std::nullopt;
}

std::optional<Rejection> validateSessionEvent(const proto::SessionEventMsg& event) {
  if (auto bad = checkIds(event.vehicle_id, event.session_id)) return bad;
  for (double v : {event.fx, event.fy, event.cx, event.cy, event.baseline, event.resolution_hint}) {
    if (!std::isfinite(v)) return Rejection{"non_finite", "camera model is not finite"};
  }
  return std::nullopt;
}

}  // namespace stereomap::core
