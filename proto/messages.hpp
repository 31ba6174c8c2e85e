// The C++ side of stereomap's DDS topics (proto/idl/stereomap.idl): plain structs that the
// rest of the code uses, so that Cyclone's generated C types never leak past proto/.
// Field meanings and units follow ARCHITECTURE.md.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

namespace stereomap::proto {

// Bounds shared with the IDL (checked again on receipt).
inline constexpr size_t kMaxIdLength = 64;
inline constexpr size_t kMaxPayloadBytes = 8u << 20;

enum class TrackingState : uint8_t { kInit, kOk, kDegraded, kLost };
enum class PoseSource : uint8_t { kGroundTruth, kVisualOdometry, kExternal };
enum class CloudEncoding : uint8_t { kDraco, kRawF32, kQuantZstd };
enum class SessionEventKind : uint8_t { kStarted, kEnded };
// Which frame a vehicle's poses are in (its start event says): the session's, or its own
// (odometry from wherever it started), which the server finds by aligning the vehicle's map.
enum class VehicleFrame : uint8_t { kSession, kOwn };
// A vehicle in its own frame, as the server's acknowledgements tell it.
enum class FrameState : uint8_t { kNone, kAligning, kAligned };
enum class LandingState : uint8_t { kSearching, kTracking, kLost };
enum class LandingMode : uint8_t { kDefault, kPatent };

// Every sample a vehicle must not lose (poses, clouds, session events, corrections) names its
// stream and its seq in it: a vehicle process starts a stream (a random nonzero id, as a Kafka
// producer id) and counts each topic's samples in it from 0, so that a server takes a sample
// exactly once however often it is re-sent (the vehicle's spool, onboard/link/spool.hpp), and
// acknowledges what it journaled per stream (AckMsg); unacked_from: the lowest seq of the
// topic its sender still holds (below it the server has them, or never will: a full spool
// gave them up). Stream 0: a sender without streams,
// whose samples are told apart by seq and stamp as before.
struct PoseMsg {
  std::string vehicle_id;
  std::string session_id;
  uint64_t stream = 0;
  uint64_t seq = 0;
  uint64_t unacked_from = 0;
  int64_t stamp_ns = 0;
  std::array<double, 3> position{};
  std::array<double, 4> orientation{0, 0, 0, 1};  // T_map_body, x y z w
  std::array<double, 3> velocity{};
  std::array<double, 36> covariance{};
  TrackingState tracking_state = TrackingState::kInit;
  PoseSource source = PoseSource::kGroundTruth;
};

struct CloudFrameMsg {
  std::string vehicle_id;
  std::string session_id;
  uint64_t stream = 0;
  uint64_t seq = 0;
  uint64_t unacked_from = 0;
  int64_t stamp_ns = 0;
  std::array<double, 3> sensor_position{};               // T_map_camera translation
  std::array<double, 4> sensor_orientation{0, 0, 0, 1};  // T_map_camera rotation, x y z w
  float max_range = 0;
  uint32_t point_count = 0;
  CloudEncoding encoding = CloudEncoding::kDraco;
  uint8_t quantization_bits = 0;
  bool has_intensity = false;
  std::vector<uint8_t> payload;
};

// A keyframe's corrected pose (T_map_body) at the stamp of a Pose sent earlier.
struct KeyframePoseMsg {
  int64_t stamp_ns = 0;
  std::array<double, 3> position{};
  std::array<double, 4> orientation{0, 0, 0, 1};  // x y z w
};

// A vehicle's pose graph's correction of the poses it has sent: every keyframe so far.
struct PoseCorrectionMsg {
  std::string vehicle_id;
  std::string session_id;
  uint64_t stream = 0;
  uint64_t seq = 0;
  uint64_t unacked_from = 0;
  int64_t stamp_ns = 0;
  std::vector<KeyframePoseMsg> keyframes;
};

inline constexpr size_t kMaxCorrectedKeyframes = 100000;  // the IDL bound

inline constexpr size_t kMaxLandingReason = 200;  // the IDL bound

// The landing pad as a vehicle sees it (see the IDL).
struct LandingTargetMsg {
  std::string vehicle_id;
  std::string session_id;
  uint64_t seq = 0;
  int64_t stamp_ns = 0;
  LandingState state = LandingState::kSearching;
  LandingMode mode = LandingMode::kDefault;
  std::string reason;
  bool has_pose = false;
  std::array<double, 3> camera_position{};
  std::array<double, 4> camera_orientation{0, 0, 0, 1};  // T_camera_pad, x y z w
  std::array<double, 36> camera_covariance{};
  std::array<double, 3> map_position{};
  std::array<double, 4> map_orientation{0, 0, 0, 1};  // T_map_pad
  std::array<double, 36> map_covariance{};
  std::array<double, 3> deck_velocity{};
  std::array<double, 3> deck_angular_rate{};
  double distance = 0;
  double bearing_deg = 0;
  double reprojection_px = 0;
};

struct SessionEventMsg {
  std::string vehicle_id;
  std::string session_id;
  uint64_t stream = 0;
  uint64_t seq = 0;
  uint64_t unacked_from = 0;
  int64_t stamp_ns = 0;
  SessionEventKind kind = SessionEventKind::kStarted;
  uint32_t width = 0;
  uint32_t height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0, baseline = 0;
  double resolution_hint = 0;
  VehicleFrame frame = VehicleFrame::kSession;
};

// Written by the server, never sent on DDS: a vehicle in its own frame was aligned into its
// session's (x_session = T x_own, T = position + orientation), with how well its map fit.
// Journaled so that recovery fuses the vehicle's frames where they were fused.
struct FrameAlignmentMsg {
  std::string vehicle_id;
  std::string session_id;
  uint64_t stream = 0;  // unused (the server's record): 0
  uint64_t seq = 0;
  uint64_t unacked_from = 0;
  int64_t stamp_ns = 0;  // when it was found
  std::array<double, 3> position{};
  std::array<double, 4> orientation{0, 0, 0, 1};  // x y z w
  double overlap = 0;  // share of the vehicle's occupied voxels in the session's map
  double rmse_m = 0;
};

// What a server has journaled of one vehicle's stream in a session, per topic: every sample
// with seq below the count (the highest contiguous seq journaled, plus one; a sample the
// server refused for good counts too). Corrections count the newest journaled (each replaces
// the ones before). Sent by the server a few times a second at most, while it changes.
//
// status kSessionClosed: the server journals nothing more for this session (an operator closed
// it, or opened it read-only from the store); the counts are 0 and `reason` says what
// happened. A vehicle stops sending to it (--on-closed keeps or drops what it holds).
enum class AckStatus : uint8_t { kJournaled, kSessionClosed };
inline constexpr size_t kMaxAckReason = 200;  // the IDL bound
struct AckMsg {
  std::string vehicle_id;
  std::string session_id;
  uint64_t stream = 0;
  int64_t stamp_ns = 0;  // when the server sent it
  uint64_t poses = 0;
  uint64_t clouds = 0;
  uint64_t events = 0;
  uint64_t corrections = 0;
  AckStatus status = AckStatus::kJournaled;
  std::string reason;
  FrameState frame_state = FrameState::kNone;
  std::array<double, 3> frame_position{};  // T_session_own when aligned
  std::array<double, 4> frame_orientation{0, 0, 0, 1};
};

// A vehicle's own counters, once a second while it runs, for the operator (never journaled:
// the newest per vehicle is kept with its session while the session is loaded).
struct VehicleStatusMsg {
  std::string vehicle_id;
  std::string session_id;
  int64_t stamp_ns = 0;
  uint64_t frames = 0;          // taken from the source
  uint64_t skipped_frames = 0;  // a live source's frames skipped to stay live
  uint64_t late_frames = 0;     // taken a period or more after their slot (--skip-late off)
  uint64_t spool_samples = 0;   // held, not acknowledged yet
  uint64_t spool_bytes = 0;
  uint64_t given_up = 0;        // samples the spool gave up (full, or its session closed)
  uint64_t held_back = 0;       // samples not sent because the server closed the session
  bool session_closed = false;  // the server said so (AckStatus::kSessionClosed)
};

}  // namespace stereomap::proto
