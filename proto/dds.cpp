#include "proto/dds.hpp"

#include <dds/dds.h>

#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <map>
#include <mutex>
#include <unordered_map>

#include "proto/detail/qos.hpp"
#include "stereomap.h"

namespace stereomap::proto {

using common::Error;
using common::ErrorCode;
using common::makeError;
using common::Result;
using common::Status;

namespace {

Error ddsError(const std::string& what, dds_return_t rc) {
  return makeError(ErrorCode::kUnavailable, what + ": " + dds_strretcode(-rc));
}

// A Cyclone domain created with an explicit configuration, shared by every Participant of
// this process on that domain id (deleting a domain deletes all its participants).
class DomainHandle {
 public:
  explicit DomainHandle(dds_entity_t domain) : domain_(domain) {}
  ~DomainHandle() {
    if (domain_ > 0) dds_delete(domain_);
  }

 private:
  dds_entity_t domain_;
};

Result<std::shared_ptr<DomainHandle>> acquireDomain(const DdsOptions& options) {
  static std::mutex mutex;
  static std::map<uint32_t, std::weak_ptr<DomainHandle>> domains;
  std::lock_guard lock(mutex);
  if (auto existing = domains[options.domain_id].lock()) return existing;

  std::string config;
  if (!options.config_file.empty()) {
    config = "file://" + options.config_file;
  } else if (const char* uri = std::getenv("CYCLONEDDS_URI"); uri != nullptr && *uri != '\0') {
    config = uri;
  } else {
    config = loopbackConfigXml();
  }
  const dds_entity_t domain = dds_create_domain(options.domain_id, config.c_str());
  if (domain < 0) {
    return ddsError("cannot create DDS domain " + std::to_string(options.domain_id) +
                        " with configuration '" +
                        (options.config_file.empty() ? std::string("default") : config) + "'",
                    domain);
  }
  auto handle = std::make_shared<DomainHandle>(domain);
  domains[options.domain_id] = handle;
  return handle;
}

// --- conversion between our structs and the generated C types -------------------------

Status copyId(const std::string& value, char (&out)[kMaxIdLength + 1], const char* field) {
  if (value.size() > kMaxIdLength) {
    return makeError(ErrorCode::kTooLarge, std::string(field) + " is longer than " +
                                               std::to_string(kMaxIdLength) + " characters");
  }
  std::memset(out, 0, sizeof(out));
  std::memcpy(out, value.data(), value.size());
  return common::Ok{};
}

// A bounded IDL string (string<N>: char[N + 1]) from a std::string; kTooLarge beyond N.
template <size_t N>
Status copyText(const std::string& value, char (&out)[N], const char* field) {
  if (value.size() > N - 1) {
    return makeError(ErrorCode::kTooLarge,
                     std::string(field) + " longer than " + std::to_string(N - 1) + " bytes");
  }
  std::memcpy(out, value.data(), value.size());
  out[value.size()] = '\0';
  return common::Ok{};
}

std::string readId(const char (&in)[kMaxIdLength + 1]) {
  return std::string(in, strnlen(in, kMaxIdLength));
}

template <typename E>
Result<E> checkedEnum(uint32_t value, uint32_t count, const char* field) {
  if (value >= count) {
    return makeError(ErrorCode::kInvalidArgument,
                     std::string(field) + " has unknown value " + std::to_string(value));
  }
  return static_cast<E>(value);
}

template <typename T>
struct Topic;

template <>
struct Topic<PoseMsg> {
  using C = stereomap_msg_Pose;
  static const dds_topic_descriptor_t* descriptor() { return &stereomap_msg_Pose_desc; }
  static constexpr const char* kName = "stereomap_Pose";
  static dds_qos_t* qos() { return poseQos(); }
  static dds_qos_t* readerQos() { return poseReaderQos(); }

  static Status toC(const PoseMsg& m, C& c) {
    if (auto s = copyId(m.vehicle_id, c.vehicle_id, "vehicle_id"); !s) return s;
    if (auto s = copyId(m.session_id, c.session_id, "session_id"); !s) return s;
    c.seq = m.seq;
    c.stream = m.stream;
    c.unacked_from = m.unacked_from;
    c.stamp_ns = m.stamp_ns;
    std::copy(m.position.begin(), m.position.end(), c.position);
    std::copy(m.orientation.begin(), m.orientation.end(), c.orientation);
    std::copy(m.velocity.begin(), m.velocity.end(), c.velocity);
    std::copy(m.covariance.begin(), m.covariance.end(), c.covariance);
    c.tracking_state = static_cast<uint32_t>(m.tracking_state);
    c.source = static_cast<uint32_t>(m.source);
    return common::Ok{};
  }
  static Result<PoseMsg> fromC(const C& c) {
    PoseMsg m;
    m.vehicle_id = readId(c.vehicle_id);
    m.session_id = readId(c.session_id);
    m.seq = c.seq;
    m.stream = c.stream;
    m.unacked_from = c.unacked_from;
    m.stamp_ns = c.stamp_ns;
    std::copy(std::begin(c.position), std::end(c.position), m.position.begin());
    std::copy(std::begin(c.orientation), std::end(c.orientation), m.orientation.begin());
    std::copy(std::begin(c.velocity), std::end(c.velocity), m.velocity.begin());
    std::copy(std::begin(c.covariance), std::end(c.covariance), m.covariance.begin());
    auto state = checkedEnum<TrackingState>(c.tracking_state, 4, "tracking_state");
    if (!state) return state.error();
    auto source = checkedEnum<PoseSource>(c.source, 3, "source");
    if (!source) return source.error();
    m.tracking_state = *state;
    m.source = *source;
    return m;
  }
};

template <>
struct Topic<CloudFrameMsg> {
  using C = stereomap_msg_CloudFrame;
  static const dds_topic_descriptor_t* descriptor() { return &stereomap_msg_CloudFrame_desc; }
  static constexpr const char* kName = "stereomap_CloudFrame";
  static dds_qos_t* qos() { return cloudQos(); }
  static dds_qos_t* readerQos() { return cloudReaderQos(); }

  // The payload is borrowed from `m` (not copied): dds_write serialises before returning.
  static Status toC(const CloudFrameMsg& m, C& c) {
    if (auto s = copyId(m.vehicle_id, c.vehicle_id, "vehicle_id"); !s) return s;
    if (auto s = copyId(m.session_id, c.session_id, "session_id"); !s) return s;
    if (m.payload.size() > kMaxPayloadBytes) {
      return makeError(ErrorCode::kTooLarge, "payload of " + std::to_string(m.payload.size()) +
                                                 " bytes exceeds the IDL bound of " +
                                                 std::to_string(kMaxPayloadBytes));
    }
    c.seq = m.seq;
    c.stream = m.stream;
    c.unacked_from = m.unacked_from;
    c.stamp_ns = m.stamp_ns;
    std::copy(m.sensor_position.begin(), m.sensor_position.end(), c.sensor_position);
    std::copy(m.sensor_orientation.begin(), m.sensor_orientation.end(), c.sensor_orientation);
    c.max_range = m.max_range;
    c.point_count = m.point_count;
    c.encoding = static_cast<uint32_t>(m.encoding);
    c.quantization_bits = m.quantization_bits;
    c.has_intensity = m.has_intensity;
    c.payload._maximum = c.payload._length = static_cast<uint32_t>(m.payload.size());
    c.payload._buffer = const_cast<uint8_t*>(m.payload.data());
    c.payload._release = false;
    return common::Ok{};
  }
  static Result<CloudFrameMsg> fromC(const C& c) {
    CloudFrameMsg m;
    m.vehicle_id = readId(c.vehicle_id);
    m.session_id = readId(c.session_id);
    m.seq = c.seq;
    m.stream = c.stream;
    m.unacked_from = c.unacked_from;
    m.stamp_ns = c.stamp_ns;
    std::copy(std::begin(c.sensor_position), std::end(c.sensor_position),
              m.sensor_position.begin());
    std::copy(std::begin(c.sensor_orientation), std::end(c.sensor_orientation),
              m.sensor_orientation.begin());
    m.max_range = c.max_range;
    m.point_count = c.point_count;
    auto encoding = checkedEnum<CloudEncoding>(c.encoding, 3, "encoding");
    if (!encoding) return encoding.error();
    m.encoding = *encoding;
    m.quantization_bits = c.quantization_bits;
    m.has_intensity = c.has_intensity;
    m.payload.assign(c.payload._buffer, c.payload._buffer + c.payload._length);
    return m;
  }
};

template <>
struct Topic<PoseCorrectionMsg> {
  using C = stereomap_msg_PoseCorrection;
  static const dds_topic_descriptor_t* descriptor() { return &stereomap_msg_PoseCorrection_desc; }
  static constexpr const char* kName = "stereomap_PoseCorrection";
  static dds_qos_t* qos() { return poseCorrectionQos(); }
  static dds_qos_t* readerQos() { return poseCorrectionQos(); }

  // The keyframes are copied into a buffer that lives as long as the message being written.
  static Status toC(const PoseCorrectionMsg& m, C& c) {
    if (auto s = copyId(m.vehicle_id, c.vehicle_id, "vehicle_id"); !s) return s;
    if (auto s = copyId(m.session_id, c.session_id, "session_id"); !s) return s;
    if (m.keyframes.size() > kMaxCorrectedKeyframes) {
      return makeError(ErrorCode::kTooLarge, std::to_string(m.keyframes.size()) +
                                                 " keyframes exceed the IDL bound of " +
                                                 std::to_string(kMaxCorrectedKeyframes));
    }
    c.seq = m.seq;
    c.stream = m.stream;
    c.unacked_from = m.unacked_from;
    c.stamp_ns = m.stamp_ns;
    thread_local std::vector<stereomap_msg_KeyframePose> buffer;
    buffer.resize(m.keyframes.size());
    for (size_t i = 0; i < m.keyframes.size(); ++i) {
      buffer[i].stamp_ns = m.keyframes[i].stamp_ns;
      std::copy(m.keyframes[i].position.begin(), m.keyframes[i].position.end(), buffer[i].position);
      std::copy(m.keyframes[i].orientation.begin(), m.keyframes[i].orientation.end(),
                buffer[i].orientation);
    }
    c.keyframes._maximum = c.keyframes._length = static_cast<uint32_t>(buffer.size());
    c.keyframes._buffer = buffer.data();
    c.keyframes._release = false;
    return common::Ok{};
  }
  static Result<PoseCorrectionMsg> fromC(const C& c) {
    PoseCorrectionMsg m;
    m.vehicle_id = readId(c.vehicle_id);
    m.session_id = readId(c.session_id);
    m.seq = c.seq;
    m.stream = c.stream;
    m.unacked_from = c.unacked_from;
    m.stamp_ns = c.stamp_ns;
    m.keyframes.resize(c.keyframes._length);
    for (uint32_t i = 0; i < c.keyframes._length; ++i) {
      const auto& k = c.keyframes._buffer[i];
      m.keyframes[i].stamp_ns = k.stamp_ns;
      std::copy(std::begin(k.position), std::end(k.position), m.keyframes[i].position.begin());
      std::copy(std::begin(k.orientation), std::end(k.orientation),
                m.keyframes[i].orientation.begin());
    }
    return m;
  }
};

template <>
struct Topic<LandingTargetMsg> {
  using C = stereomap_msg_LandingTarget;
  static const dds_topic_descriptor_t* descriptor() { return &stereomap_msg_LandingTarget_desc; }
  static constexpr const char* kName = "stereomap_LandingTarget";
  static dds_qos_t* qos() { return landingTargetQos(); }
  static dds_qos_t* readerQos() { return landingTargetQos(); }

  static Status toC(const LandingTargetMsg& m, C& c) {
    if (auto s = copyId(m.vehicle_id, c.vehicle_id, "vehicle_id"); !s) return s;
    if (auto s = copyId(m.session_id, c.session_id, "session_id"); !s) return s;
    if (auto s = copyText(m.reason, c.reason, "landing reason"); !s) return s;
    c.seq = m.seq;
    c.stamp_ns = m.stamp_ns;
    c.state = static_cast<uint32_t>(m.state);
    c.mode = static_cast<uint32_t>(m.mode);
    c.has_pose = m.has_pose;
    std::copy(m.camera_position.begin(), m.camera_position.end(), c.camera_position);
    std::copy(m.camera_orientation.begin(), m.camera_orientation.end(), c.camera_orientation);
    std::copy(m.camera_covariance.begin(), m.camera_covariance.end(), c.camera_covariance);
    std::copy(m.map_position.begin(), m.map_position.end(), c.map_position);
    std::copy(m.map_orientation.begin(), m.map_orientation.end(), c.map_orientation);
    std::copy(m.map_covariance.begin(), m.map_covariance.end(), c.map_covariance);
    std::copy(m.deck_velocity.begin(), m.deck_velocity.end(), c.deck_velocity);
    std::copy(m.deck_angular_rate.begin(), m.deck_angular_rate.end(), c.deck_angular_rate);
    c.distance = m.distance;
    c.bearing_deg = m.bearing_deg;
    c.reprojection_px = m.reprojection_px;
    return common::Ok{};
  }
  static Result<LandingTargetMsg> fromC(const C& c) {
    auto state = checkedEnum<LandingState>(c.state, 3, "state");
    if (!state) return state.error();
    auto mode = checkedEnum<LandingMode>(c.mode, 2, "mode");
    if (!mode) return mode.error();
    LandingTargetMsg m;
    m.vehicle_id = readId(c.vehicle_id);
    m.session_id = readId(c.session_id);
    m.seq = c.seq;
    m.stamp_ns = c.stamp_ns;
    m.state = *state;
    m.mode = *mode;
    m.reason.assign(c.reason, strnlen(c.reason, kMaxLandingReason));
    m.has_pose = c.has_pose;
    std::copy(std::begin(c.camera_position), std::end(c.camera_position),
              m.camera_position.begin());
    std::copy(std::begin(c.camera_orientation), std::end(c.camera_orientation),
              m.camera_orientation.begin());
    std::copy(std::begin(c.camera_covariance), std::end(c.camera_covariance),
              m.camera_covariance.begin());
    std::copy(std::begin(c.map_position), std::end(c.map_position), m.map_position.begin());
    std::copy(std::begin(c.map_orientation), std::end(c.map_orientation),
              m.map_orientation.begin());
    std::copy(std::begin(c.map_covariance), std::end(c.map_covariance), m.map_covariance.begin());
    std::copy(std::begin(c.deck_velocity), std::end(c.deck_velocity), m.deck_velocity.begin());
    std::copy(std::begin(c.deck_angular_rate), std::end(c.deck_angular_rate),
              m.deck_angular_rate.begin());
    m.distance = c.distance;
    m.bearing_deg = c.bearing_deg;
    m.reprojection_px = c.reprojection_px;
    return m;
  }
};

template <>
struct Topic<SessionEventMsg> {
  using C = stereomap_msg_SessionEvent;
  static const dds_topic_descriptor_t* descriptor() { return &stereomap_msg_SessionEvent_desc; }
  static constexpr const char* kName = "stereomap_SessionEvent";
  static dds_qos_t* qos() { return sessionEventQos(); }
  static dds_qos_t* readerQos() { return sessionEventQos(); }

  static Status toC(const SessionEventMsg& m, C& c) {
    if (auto s = copyId(m.vehicle_id, c.vehicle_id, "vehicle_id"); !s) return s;
    if (auto s = copyId(m.session_id, c.session_id, "session_id"); !s) return s;
    c.stream = m.stream;
    c.unacked_from = m.unacked_from;
    c.seq = m.seq;
    c.stamp_ns = m.stamp_ns;
    c.kind = static_cast<uint32_t>(m.kind);
    c.width = m.width;
    c.height = m.height;
    c.fx = m.fx;
    c.fy = m.fy;
    c.cx = m.cx;
    c.cy = m.cy;
    c.baseline = m.baseline;
    c.resolution_hint = m.resolution_hint;
    c.frame = static_cast<uint32_t>(m.frame);
    return common::Ok{};
  }
  static Result<SessionEventMsg> fromC(const C& c) {
    SessionEventMsg m;
    m.vehicle_id = readId(c.vehicle_id);
    m.session_id = readId(c.session_id);
    m.stream = c.stream;
    m.unacked_from = c.unacked_from;
    m.seq = c.seq;
    m.stamp_ns = c.stamp_ns;
    auto kind = checkedEnum<SessionEventKind>(c.kind, 2, "kind");
    if (!kind) return kind.error();
    m.kind = *kind;
    m.width = c.width;
    m.height = c.height;
    m.fx = c.fx;
    m.fy = c.fy;
    m.cx = c.cx;
    m.cy = c.cy;
    m.baseline = c.baseline;
    m.resolution_hint = c.resolution_hint;
    auto frame = checkedEnum<VehicleFrame>(c.frame, 2, "frame");
    if (!frame) return frame.error();
    m.frame = *frame;
    return m;
  }
};

template <>
struct Topic<AckMsg> {
  using C = stereomap_msg_Ack;
  static const dds_topic_descriptor_t* descriptor() { return &stereomap_msg_Ack_desc; }
  static constexpr const char* kName = "stereomap_Ack";
  static dds_qos_t* qos() { return ackQos(); }
  static dds_qos_t* readerQos() { return ackQos(); }

  static Status toC(const AckMsg& m, C& c) {
    if (auto s = copyId(m.vehicle_id, c.vehicle_id, "vehicle_id"); !s) return s;
    if (auto s = copyId(m.session_id, c.session_id, "session_id"); !s) return s;
    c.stream = m.stream;
    c.stamp_ns = m.stamp_ns;
    c.poses = m.poses;
    c.clouds = m.clouds;
    c.events = m.events;
    c.corrections = m.corrections;
    c.status = static_cast<uint32_t>(m.status);
    if (auto s = copyText(m.reason, c.reason, "ack reason"); !s) return s;
    c.frame_state = static_cast<uint32_t>(m.frame_state);
    std::copy(m.frame_position.begin(), m.frame_position.end(), c.frame_position);
    std::copy(m.frame_orientation.begin(), m.frame_orientation.end(), c.frame_orientation);
    return common::Ok{};
  }
  static Result<AckMsg> fromC(const C& c) {
    auto status = checkedEnum<AckStatus>(c.status, 2, "status");
    if (!status) return status.error();
    AckMsg m;
    m.status = *status;
    m.reason.assign(c.reason, strnlen(c.reason, kMaxAckReason));
    m.vehicle_id = readId(c.vehicle_id);
    m.session_id = readId(c.session_id);
    m.stream = c.stream;
    m.stamp_ns = c.stamp_ns;
    m.poses = c.poses;
    m.clouds = c.clouds;
    m.events = c.events;
    m.corrections = c.corrections;
    auto frame_state = checkedEnum<FrameState>(c.frame_state, 3, "frame_state");
    if (!frame_state) return frame_state.error();
    m.frame_state = *frame_state;
    std::copy(std::begin(c.frame_position), std::end(c.frame_position), m.frame_position.begin());
    std::copy(std::begin(c.frame_orientation), std::end(c.frame_orientation),
              m.frame_orientation.begin());
    return m;
  }
};

template <>
struct Topic<VehicleStatusMsg> {
  using C = stereomap_msg_VehicleStatus;
  static const dds_topic_descriptor_t* descriptor() { return &stereomap_msg_VehicleStatus_desc; }
  static constexpr const char* kName = "stereomap_VehicleStatus";
  static dds_qos_t* qos() { return vehicleStatusQos(); }
  static dds_qos_t* readerQos() { return vehicleStatusQos(); }

  static Status toC(const VehicleStatusMsg& m, C& c) {
    if (auto s = copyId(m.vehicle_id, c.vehicle_id, "vehicle_id"); !s) return s;
    if (auto s = copyId(m.session_id, c.session_id, "session_id"); !s) return s;
    c.stamp_ns = m.stamp_ns;
    c.frames = m.frames;
    c.skipped_frames = m.skipped_frames;
    c.late_frames = m.late_frames;
    c.spool_samples = m.spool_samples;
    c.spool_bytes = m.spool_bytes;
    c.given_up = m.given_up;
    c.held_back = m.held_back;
    c.session_closed = m.session_closed;
    return common::Ok{};
  }
  static Result<VehicleStatusMsg> fromC(const C& c) {
    VehicleStatusMsg m;
    m.vehicle_id = readId(c.vehicle_id);
    m.session_id = readId(c.session_id);
    m.stamp_ns = c.stamp_ns;
    m.frames = c.frames;
    m.skipped_frames = c.skipped_frames;
    m.late_frames = c.late_frames;
    m.spool_samples = c.spool_samples;
    m.spool_bytes = c.spool_bytes;
    m.given_up = c.given_up;
    m.held_back = c.held_back;
    m.session_closed = c.session_closed;
    return m;
  }
};

struct QosDeleter {
  void operator()(dds_qos_t* qos) const { dds_delete_qos(qos); }
};
using QosPtr = std::unique_ptr<dds_qos_t, QosDeleter>;

// A writer or reader made on the participant gets an implicit publisher or subscriber with
// its QoS: the partition set here is theirs.
void setPartitions(dds_qos_t* qos, const std::vector<std::string>& partitions) {
  if (partitions.empty()) return;
  std::vector<const char*> names;
  for (const auto& name : partitions) names.push_back(name.c_str());
  dds_qset_partition(qos, static_cast<uint32_t>(names.size()), names.data());
}

template <typename T>
Result<dds_entity_t> createTopic(dds_entity_t participant) {
  const dds_entity_t topic =
      dds_create_topic(participant, Topic<T>::descriptor(), Topic<T>::kName, nullptr, nullptr);
  if (topic < 0) return ddsError(std::string("cannot create topic ") + Topic<T>::kName, topic);
  return topic;
}

// Who a writer in `partition` is: with DDS Security only the certificate whose common name is
// V may write in "sm/<session>/v/V" (stereomap-certs' permissions).
std::string writerIdentity(const std::string& partition) {
  const auto at = partition.rfind("/v/");
  if (partition.rfind("sm/", 0) != 0 || at == std::string::npos ||
      partition.find(',') != std::string::npos) {
    return "";
  }
  return ", certificate CN=" + partition.substr(at + 3) + " when secured";
}

// The IDL type's name ("Pose"): topic names are "stereomap_" and it.
template <typename T>
std::string topicType() {
  return std::string(Topic<T>::kName).substr(std::strlen("stereomap_"));
}

// Waits on `waitset` until `done()` or the deadline; the waitset wakes on status changes.
template <typename Done>
bool waitUntil(dds_entity_t waitset, std::chrono::milliseconds timeout, Done done) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (!done()) {
    const auto left = deadline - std::chrono::steady_clock::now();
    if (left <= std::chrono::nanoseconds::zero()) return false;
    dds_waitset_wait(waitset, nullptr, 0,
                     std::chrono::duration_cast<std::chrono::nanoseconds>(left).count());
  }
  return true;
}

// Files of a security folder (stereomap-certs): Cyclone's property, the file, required.
struct SecurityFile {
  const char* property;
  const char* file;
  bool required;
};
constexpr SecurityFile kSecurityFiles[] = {
    {"dds.sec.auth.identity_ca", "identity_ca.pem", true},
    {"dds.sec.auth.identity_certificate", "identity.pem", true},
    {"dds.sec.auth.private_key", "identity.key", true},
    {"dds.sec.access.permissions_ca", "permissions_ca.pem", true},
    {"dds.sec.access.governance", "governance.p7s", true},
    {"dds.sec.access.permissions", "permissions.p7s", true},
    // Cyclone's own name for it, not dds.sec.auth.crl (dds_security_api_defs.h).
    {"org.eclipse.cyclonedds.sec.auth.crl", "crl.pem", false},
};

// A participant QoS carrying the DDS Security plugins and the identity in `dir` (checked).
// Given as QoS, not XML, so one process can hold participants of several identities.
dds_qos_t* securityQos(const std::string& dir) {
  dds_qos_t* qos = dds_create_qos();
  const std::pair<const char*, const char*> libraries[] = {
      {"dds.sec.auth.library.path", "dds_security_auth"},
      {"dds.sec.auth.library.init", "init_authentication"},
      {"dds.sec.auth.library.finalize", "finalize_authentication"},
      {"dds.sec.crypto.library.path", "dds_security_crypto"},
      {"dds.sec.crypto.library.init", "init_crypto"},
      {"dds.sec.crypto.library.finalize", "finalize_crypto"},
      {"dds.sec.access.library.path", "dds_security_ac"},
      {"dds.sec.access.library.init", "init_access_control"},
      {"dds.sec.access.library.finalize", "finalize_access_control"},
  };
  for (const auto& [name, value] : libraries) dds_qset_prop(qos, name, value);
  const auto absolute = std::filesystem::absolute(dir);
  for (const auto& file : kSecurityFiles) {
    const auto path = absolute / file.file;
    if (!file.required && !std::filesystem::exists(path)) continue;
    dds_qset_prop(qos, file.property, ("file:" + path.string()).c_str());
  }
  return qos;
}

}  // namespace

Status checkSecurityDir(const std::string& dir) {
  std::error_code error;
  if (!std::filesystem::is_directory(dir, error)) {
    return makeError(ErrorCode::kNotFound, "security folder '" + dir +
                                               "' does not exist (make one with stereomap-certs)");
  }
  for (const auto& file : kSecurityFiles) {
    const auto path = std::filesystem::path(dir) / file.file;
    if (file.required && !std::filesystem::is_regular_file(path, error)) {
      return makeError(ErrorCode::kNotFound, "security folder '" + dir + "' lacks " + file.file +
                                                 " (stereomap-certs server|vehicle makes it)");
    }
  }
  return common::Ok{};
}

// --- Participant ------------------------------------------------------------------------

struct Participant::Impl {
  std::shared_ptr<DomainHandle> domain;
  dds_entity_t participant = 0;
  ~Impl() {
    if (participant > 0) dds_delete(participant);
  }
};

Participant::Participant(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Participant::~Participant() = default;
int32_t Participant::handle() const { return impl_->participant; }

Result<std::shared_ptr<Participant>> Participant::create(const DdsOptions& options) {
  auto impl = std::make_unique<Impl>();
  auto domain = acquireDomain(options);
  if (!domain) return domain.error();
  impl->domain = *domain;
  QosPtr qos;
  if (!options.security_dir.empty()) {
    if (auto checked = checkSecurityDir(options.security_dir); !checked) return checked.error();
    if (options.domain_id > kMaxSecureDomain) {
      return makeError(ErrorCode::kInvalidArgument, "DDS Security's governance covers domains 0-" +
                                                        std::to_string(kMaxSecureDomain) +
                                                        " only (Cyclone's parser): not " +
                                                        std::to_string(options.domain_id));
    }
    qos.reset(securityQos(options.security_dir));
  }
  impl->participant = dds_create_participant(options.domain_id, qos.get(), nullptr);
  if (impl->participant < 0) {
    const dds_return_t rc = impl->participant;
    impl->participant = 0;
    return ddsError("cannot create DDS participant on domain " + std::to_string(options.domain_id) +
                        (options.security_dir.empty()
                             ? std::string()
                             : " with the identity in " + options.security_dir +
                                   " (expired, revoked, or not signed by the deployment's CAs? "
                                   "Cyclone's log says which)"),
                    rc);
  }
  return std::shared_ptr<Participant>(new Participant(std::move(impl)));
}

// --- Writer -----------------------------------------------------------------------------

template <typename T>
struct Writer<T>::Impl {
  std::shared_ptr<Participant> participant;
  dds_entity_t writer = 0;
  dds_entity_t waitset = 0;
  ~Impl() {
    if (waitset > 0) dds_delete(waitset);
    if (writer > 0) dds_delete(writer);
  }
};

template <typename T>
Writer<T>::Writer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
template <typename T>
Writer<T>::~Writer() = default;

template <typename T>
Result<std::unique_ptr<Writer<T>>> Writer<T>::create(
    const std::shared_ptr<Participant>& participant, const std::vector<std::string>& partitions) {
  auto impl = std::make_unique<Impl>();
  impl->participant = participant;
  auto topic = createTopic<T>(participant->handle());
  if (!topic) return topic.error();
  QosPtr qos(Topic<T>::qos());
  setPartitions(qos.get(), partitions);
  impl->writer = dds_create_writer(participant->handle(), *topic, qos.get(), nullptr);
  if (impl->writer < 0) {
    const dds_return_t rc = impl->writer;
    impl->writer = 0;
    return ddsError(std::string("cannot create writer for ") + Topic<T>::kName, rc);
  }
  dds_set_status_mask(impl->writer, DDS_PUBLICATION_MATCHED_STATUS);
  impl->waitset = dds_create_waitset(participant->handle());
  dds_waitset_attach(impl->waitset, impl->writer, impl->writer);
  return std::unique_ptr<Writer>(new Writer(std::move(impl)));
}

template <typename T>
Status Writer<T>::write(const T& message) {
  typename Topic<T>::C sample{};
  if (auto status = Topic<T>::toC(message, sample); !status) return status;
  const dds_return_t rc = dds_write(impl_->writer, &sample);
  if (rc != DDS_RETCODE_OK) return ddsError(std::string("write on ") + Topic<T>::kName, rc);
  return common::Ok{};
}

template <typename T>
bool Writer<T>::waitForAcks(std::chrono::milliseconds timeout) const {
  return dds_wait_for_acks(impl_->writer, DDS_MSECS(timeout.count())) == DDS_RETCODE_OK;
}

template <typename T>
int Writer<T>::matchedReaders() const {
  dds_publication_matched_status_t status{};
  dds_get_publication_matched_status(impl_->writer, &status);
  return static_cast<int>(status.current_count);
}

template <typename T>
bool Writer<T>::waitForReaders(int count, std::chrono::milliseconds timeout) const {
  return waitUntil(impl_->waitset, timeout, [&] { return matchedReaders() >= count; });
}

// --- Reader -----------------------------------------------------------------------------

template <typename T>
struct Reader<T>::Impl {
  std::shared_ptr<Participant> participant;
  dds_entity_t reader = 0;
  dds_entity_t waitset = 0;
  dds_entity_t guard = 0;
  bool bind_to_writer = false;
  // The partition(s) each matched writer wrote in, by publication handle (bind_to_writer).
  std::unordered_map<dds_instance_handle_t, std::string> writer_partitions;
  const std::string& writerPartition(dds_instance_handle_t writer);
  ~Impl() {
    if (waitset > 0) dds_delete(waitset);
    if (guard > 0) dds_delete(guard);
    if (reader > 0) dds_delete(reader);
  }
};

// "" for a writer no longer matched (or in no partition), else its partitions joined by ','
// (never a valid vehiclePartition when more than one).
template <typename T>
const std::string& Reader<T>::Impl::writerPartition(dds_instance_handle_t writer) {
  if (auto found = writer_partitions.find(writer); found != writer_partitions.end()) {
    return found->second;
  }
  // Bounded: writers come and go over a server's life; a miss costs one lookup.
  if (writer_partitions.size() >= 4096) writer_partitions.clear();
  std::string joined;
  if (dds_builtintopic_endpoint_t* endpoint = dds_get_matched_publication_data(reader, writer)) {
    uint32_t count = 0;
    char** names = nullptr;
    if (endpoint->qos != nullptr && dds_qget_partition(endpoint->qos, &count, &names)) {
      for (uint32_t i = 0; i < count; ++i) {
        if (i > 0) joined += ',';
        joined += names[i];
        dds_free(names[i]);
      }
      dds_free(names);
    }
    dds_builtintopic_free_endpoint(endpoint);
  } else {
    static const std::string kUnknown;
    return kUnknown;  // not cached: it may match later
  }
  return writer_partitions.emplace(writer, std::move(joined)).first->second;
}

template <typename T>
Reader<T>::Reader(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
template <typename T>
Reader<T>::~Reader() = default;

template <typename T>
Result<std::unique_ptr<Reader<T>>> Reader<T>::create(
    const std::shared_ptr<Participant>& participant, const std::vector<std::string>& partitions,
    bool bind_to_writer) {
  auto impl = std::make_unique<Impl>();
  impl->participant = participant;
  impl->bind_to_writer = bind_to_writer;
  auto topic = createTopic<T>(participant->handle());
  if (!topic) return topic.error();
  QosPtr qos(Topic<T>::readerQos());
  setPartitions(qos.get(), partitions);
  impl->reader = dds_create_reader(participant->handle(), *topic, qos.get(), nullptr);
  if (impl->reader < 0) {
    const dds_return_t rc = impl->reader;
    impl->reader = 0;
    return ddsError(std::string("cannot create reader for ") + Topic<T>::kName, rc);
  }
  impl->waitset = dds_create_waitset(participant->handle());
  impl->guard = dds_create_guardcondition(participant->handle());
  const dds_entity_t condition = dds_create_readcondition(impl->reader, DDS_ANY_STATE);
  dds_waitset_attach(impl->waitset, condition, impl->reader);
  dds_waitset_attach(impl->waitset, impl->guard, impl->guard);
  return std::unique_ptr<Reader>(new Reader(std::move(impl)));
}

template <typename T>
size_t Reader<T>::take(std::vector<T>& out, std::chrono::milliseconds timeout,
                       std::vector<RefusedSample>* refused) {
  dds_waitset_wait(impl_->waitset, nullptr, 0,
                   std::chrono::duration_cast<std::chrono::nanoseconds>(timeout).count());
  bool woken = false;
  dds_take_guardcondition(impl_->guard, &woken);

  constexpr size_t kBatch = 16;
  size_t appended = 0;
  for (;;) {
    void* samples[kBatch] = {nullptr};
    dds_sample_info_t infos[kBatch];
    const dds_return_t n = dds_take(impl_->reader, samples, infos, kBatch, kBatch);
    if (n <= 0) break;
    for (dds_return_t i = 0; i < n; ++i) {
      if (!infos[i].valid_data) continue;
      // Cyclone has already checked the IDL bounds (strings, sequences); the enumerations are
      // plain integers on the wire (stereomap.idl), checked here.
      const auto& c = *static_cast<const typename Topic<T>::C*>(samples[i]);
      if (impl_->bind_to_writer) {
        const std::string& written_in = impl_->writerPartition(infos[i].publication_handle);
        const std::string vehicle = readId(c.vehicle_id);
        const std::string session = readId(c.session_id);
        if (written_in != vehiclePartition(session, vehicle)) {
          if (refused != nullptr) {
            refused->push_back({topicType<T>(), vehicle, session,
                                "written as vehicle '" + vehicle + "' of session '" + session +
                                    "' by a writer in partition '" + written_in + "'" +
                                    writerIdentity(written_in) +
                                    " (a vehicle writes only in sm/<session>/v/<its id>)",
                                "identity", written_in});
          }
          continue;
        }
      }
      auto message = Topic<T>::fromC(c);
      if (message) {
        out.push_back(std::move(message).value());
        ++appended;
      } else if (refused != nullptr) {
        refused->push_back(
            {topicType<T>(), readId(c.vehicle_id), readId(c.session_id), message.error().message});
      }
    }
    dds_return_loan(impl_->reader, samples, n);
  }
  return appended;
}

template <typename T>
void Reader<T>::wake() {
  dds_set_guardcondition(impl_->guard, true);
}

template <typename T>
int Reader<T>::matchedWriters() const {
  dds_subscription_matched_status_t status{};
  dds_get_subscription_matched_status(impl_->reader, &status);
  return static_cast<int>(status.current_count);
}

template class Writer<PoseMsg>;
template class Writer<CloudFrameMsg>;
template class Writer<SessionEventMsg>;
template class Writer<PoseCorrectionMsg>;
template class Writer<LandingTargetMsg>;
template class Writer<AckMsg>;
template class Writer<VehicleStatusMsg>;
template class Reader<PoseMsg>;
template class Reader<CloudFrameMsg>;
template class Reader<SessionEventMsg>;
template class Reader<PoseCorrectionMsg>;
template class Reader<LandingTargetMsg>;
template class Reader<AckMsg>;
template class Reader<VehicleStatusMsg>;

std::string vehiclePartition(const std::string& session_id, const std::string& vehicle_id) {
  return "sm/" + session_id + "/v/" + vehicle_id;
}

std::string sessionPartitions(const std::string& session_id) { return "sm/" + session_id + "/v/*"; }

const char* loopbackConfigXml() {
  return R"(<CycloneDDS><Domain Id="any"><General>
<Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>
<AllowMulticast>false</AllowMulticast>
<MaxMessageSize>65500B</MaxMessageSize><FragmentSize>65000B</FragmentSize></General>
<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>64</MaxAutoParticipantIndex>
<Peers><Peer address="127.0.0.1"/></Peers></Discovery>
<Internal><SocketReceiveBufferSize min="4MB"/></Internal></Domain></CycloneDDS>)";
}

}  // namespace stereomap::proto
