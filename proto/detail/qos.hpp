// QoS presets for stereomap's topics (see ARCHITECTURE.md, "DDS topics"). Internal to proto:
// the returned dds_qos_t is owned by the caller (dds_delete_qos).
#pragma once

#include <dds/dds.h>

namespace stereomap::proto {

// Reliable, transient-local: a late-joining server learns the live sessions.
dds_qos_t* sessionEventQos();
// Reliable, transient-local, keep-last 1 per session: each correction holds every keyframe,
// so only the newest matters, and a late-joining server still gets it.
dds_qos_t* poseCorrectionQos();
// Reliable, volatile, keep-last 1 per vehicle: only the newest sighting of the pad matters,
// and a stale one is worse than none to a late joiner.
dds_qos_t* landingTargetQos();
// Reliable, volatile, keep-last 1 per vehicle stream: an acknowledgement counts everything
// before it, so only the newest matters.
dds_qos_t* ackQos();
dds_qos_t* vehicleStatusQos();
// Reliable, transient-local, keep-last kPoseHistory: a server restarted within a few seconds
// gets the poses it missed, as it does the clouds.
dds_qos_t* poseQos();
// The same, keep-all on the reader: a backlog of history is never overwritten before it is read.
dds_qos_t* poseReaderQos();
// Reliable, transient-local, keep-last kCloudHistory: a restarted server catches up on the
// most recent frames.
dds_qos_t* cloudQos();

// Reliable, transient-local, keep-all on the reader: a slow reader slows the writer down
// (reliable flow control) instead of losing frames from its own history.
dds_qos_t* cloudReaderQos();

inline constexpr int kCloudHistory = 32;
inline constexpr int kPoseHistory = 256;  // 25 s at 10 Hz; a pose sample is ~0.4 kB

}  // namespace stereomap::proto
