// What a sample costs on the link, to budget and report a vehicle's stream: its CDR
// serialisation (XCDR1: strings with a 4-byte length and a NUL, fields aligned to their size)
// plus the headers of one RTPS message in one UDP datagram (RTPS 20, INFO_TS 12, DATA 24,
// UDP 8, IPv4 20). Large samples are fragmented by DDS into several datagrams, each with
// its headers: counted as one per 1400 bytes.
#pragma once

#include <cstddef>
#include <string>

#include "proto/messages.hpp"

namespace stereomap::proto {

namespace wire_detail {

inline constexpr size_t kHeaders = 20 + 12 + 24 + 8 + 20;
inline constexpr size_t kFragment = 1400;

inline size_t align(size_t offset, size_t to) { return (offset + to - 1) / to * to; }
inline size_t string(size_t offset, const std::string& s) {
  return align(offset, 4) + 4 + s.size() + 1;
}
inline size_t withHeaders(size_t cdr) {
  return cdr + kHeaders * ((cdr + kFragment - 1) / kFragment);
}

}  // namespace wire_detail

inline size_t wireBytes(const PoseMsg& m) {
  using namespace wire_detail;
  size_t n = string(string(4, m.vehicle_id), m.session_id);  // 4: the encapsulation header
  n = align(n, 8) + 4 * 8 + (3 + 4 + 3 + 36) * 8;  // stream, seq, unacked_from, stamp, the doubles
  n += 4 + 4;                                      // two enums
  return withHeaders(n);
}

inline size_t wireBytes(const CloudFrameMsg& m) {
  using namespace wire_detail;
  size_t n = string(string(4, m.vehicle_id), m.session_id);
  n = align(n, 8) + 4 * 8 + (3 + 4) * 8;  // stream, seq, unacked_from, stamp, the sensor's pose
  n += 4 + 4 + 4 + 1 + 1;                 // range, count, encoding, bits, intensity
  n = align(n, 4) + 4 + m.payload.size();
  return withHeaders(n);
}

inline size_t wireBytes(const SessionEventMsg& m) {
  using namespace wire_detail;
  size_t n = string(string(4, m.vehicle_id), m.session_id);
  n = align(n, 8) + 4 * 8 + 4 + 4 + 4;  // stream, seq, unacked_from, stamp, kind, size
  n = align(n, 8) + 6 * 8 + 4;          // the camera model, the resolution hint, the frame
  return withHeaders(n);
}

inline size_t wireBytes(const PoseCorrectionMsg& m) {
  using namespace wire_detail;
  size_t n = string(string(4, m.vehicle_id), m.session_id);
  n = align(n, 8) + 4 * 8 + 4;  // stream, seq, unacked_from, stamp, the keyframes' count
  n = align(n, 8) + m.keyframes.size() * 8 * 8;  // stamp and 7 doubles each
  return withHeaders(n);
}

// A server's record, never sent: what it would take (the variant of journal records has it).
inline size_t wireBytes(const FrameAlignmentMsg& m) {
  using namespace wire_detail;
  size_t n = string(string(4, m.vehicle_id), m.session_id);
  n = align(n, 8) + 4 * 8 + (3 + 4 + 2) * 8;
  return withHeaders(n);
}

inline size_t wireBytes(const LandingTargetMsg& m) {
  using namespace wire_detail;
  size_t n = string(string(4, m.vehicle_id), m.session_id);
  n = align(n, 8) + 2 * 8 + 4 + 4;  // seq, stamp, state, mode
  n = string(n, m.reason) + 1;      // and has_pose
  n = align(n, 8) + (3 + 4 + 36 + 3 + 4 + 36 + 3 + 3 + 3) * 8;
  return withHeaders(n);
}

inline size_t wireBytes(const AckMsg& m) {
  using namespace wire_detail;
  size_t n = string(string(4, m.vehicle_id), m.session_id);
  n = align(n, 8) + 6 * 8 + 4;  // stream, stamp, four counts, status
  n = string(n, m.reason);
  n = align(n, 4) + 4;            // the frame state
  n = align(n, 8) + (3 + 4) * 8;  // T_session_own
  return withHeaders(n);
}

inline size_t wireBytes(const VehicleStatusMsg& m) {
  using namespace wire_detail;
  size_t n = string(string(4, m.vehicle_id), m.session_id);
  n = align(n, 8) + 8 * 8 + 1;  // stamp, seven counts, session_closed
  return withHeaders(n);
}

}  // namespace stereomap::proto
