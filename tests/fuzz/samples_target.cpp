// Fuzz target: every DDS sample the server takes, as it validates it (server/core/validate),
// with every field drawn from the input: ids of any bytes, doubles of any bit pattern (NaN,
// infinities, 1e308), out-of-range enum values, a payload. A sample the validation accepts
// must be safe for what follows it: an accepted cloud is fused into a map (where a value
// out of float's range would be undefined behaviour), an accepted pose is a finite rigid
// motion. Run under UBSan as well as ASan.
#include <cmath>

#include "server/core/validate.hpp"
#include "server/fusion/occupancy_map.hpp"
#include "tests/fuzz/fuzz_input.hpp"

namespace {

using namespace stereomap;
using fuzz::FuzzInput;

template <class Message>
void takeIds(FuzzInput& in, Message& m) {
  m.vehicle_id = in.string(70);
  m.session_id = in.string(70);
}

bool finite(const common::Rigid3& pose) {
  return pose.rotation.coeffs().allFinite() && pose.translation.allFinite() &&
         std::abs(pose.rotation.norm() - 1) < 1e-6;
}

void cloudFrame(FuzzInput& in) {
  proto::CloudFrameMsg m;
  takeIds(in, m);
  m.seq = in.take<uint64_t>();
  m.stamp_ns = in.take<int64_t>();
  in.fill(m.sensor_position);
  in.fill(m.sensor_orientation);
  m.max_range = in.take<float>();
  m.point_count = in.take<uint32_t>() % 2001;
  m.encoding = static_cast<proto::CloudEncoding>(in.byte() % 4);  // 3: not an encoding
  m.quantization_bits = in.byte();
  m.has_intensity = in.byte() & 1;
  m.payload = in.rest();
  core::ValidCloud valid;
  if (core::validateCloudFrame(m, core::IngestLimits{}, valid)) return;
  if (!finite(valid.T_map_camera) || !(valid.max_range_m > 0)) __builtin_trap();
  fusion::OccupancyMap::Options options;  // the server's: the fast path
  options.threads = 1;
  fusion::OccupancyMap map(options);
  map.insertCloud(valid.cloud_camera, valid.T_map_camera, valid.max_range_m);
}

void pose(FuzzInput& in) {
  proto::PoseMsg m;
  takeIds(in, m);
  m.seq = in.take<uint64_t>();
  m.stamp_ns = in.take<int64_t>();
  in.fill(m.position);
  in.fill(m.orientation);
  in.fill(m.velocity);
  in.fill(m.covariance);
  m.tracking_state = static_cast<proto::TrackingState>(in.byte());
  m.source = static_cast<proto::PoseSource>(in.byte());
  core::ValidPose valid;
  if (!core::validatePose(m, valid) && (!finite(valid.T_map_body) || valid.stamp_ns < 0)) {
    __builtin_trap();
  }
}

void sessionEvent(FuzzInput& in) {
  proto::SessionEventMsg m;
  takeIds(in, m);
  m.stamp_ns = in.take<int64_t>();
  m.kind = static_cast<proto::SessionEventKind>(in.byte());
  m.width = in.take<uint32_t>();
  m.height = in.take<uint32_t>();
  for (double* v : {&m.fx, &m.fy, &m.cx, &m.cy, &m.baseline, &m.resolution_hint}) {
    *v = in.take<double>();
  }
  core::validateSessionEvent(m);
}

void poseCorrection(FuzzInput& in) {
  proto::PoseCorrectionMsg m;
  takeIds(in, m);
  m.seq = in.take<uint64_t>();
  m.stamp_ns = in.take<int64_t>();
  while (in.remaining() > 0) {
    proto::KeyframePoseMsg k;
    k.stamp_ns = in.take<int64_t>();
    in.fill(k.position);
    in.fill(k.orientation);
    m.keyframes.push_back(k);
  }
  std::vector<core::ValidPose> valid;
  if (core::validatePoseCorrection(m, valid)) return;
  if (valid.size() != m.keyframes.size()) __builtin_trap();
  for (size_t i = 0; i < valid.size(); ++i) {
    if (!finite(valid[i].T_map_body) || (i > 0 && valid[i].stamp_ns <= valid[i - 1].stamp_ns)) {
      __builtin_trap();
    }
  }
}

void landingTarget(FuzzInput& in) {
  proto::LandingTargetMsg m;
  takeIds(in, m);
  m.seq = in.take<uint64_t>();
  m.stamp_ns = in.take<int64_t>();
  m.state = static_cast<proto::LandingState>(in.byte());
  m.mode = static_cast<proto::LandingMode>(in.byte());
  m.reason = in.string();
  m.has_pose = in.byte() & 1;
  in.fill(m.camera_position);
  in.fill(m.camera_orientation);
  in.fill(m.camera_covariance);
  in.fill(m.map_position);
  in.fill(m.map_orientation);
  in.fill(m.map_covariance);
  in.fill(m.deck_velocity);
  in.fill(m.deck_angular_rate);
  m.distance = in.take<double>();
  m.bearing_deg = in.take<double>();
  m.reprojection_px = in.take<double>();
  core::validateLandingTarget(m);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  FuzzInput in(data, size);
  switch (in.byte() % 5) {
    case 0:
      cloudFrame(in);
      break;
    case 1:
      pose(in);
      break;
    case 2:
      sessionEvent(in);
      break;
    case 3:
      poseCorrection(in);
      break;
    default:
      landingTarget(in);
      break;
  }
  return 0;
}
