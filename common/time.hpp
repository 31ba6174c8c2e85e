// Wall-clock time as int64 nanoseconds since the Unix epoch (the stamp on every sample), and
// elapsed time for timing work.
#pragma once

#include <chrono>
#include <cstdint>

namespace stereomap::common {

inline int64_t nowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// The monotonic clock as int64 nanoseconds (for ages and intervals, not stamps).
inline int64_t steadyNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

inline double nsToSeconds(int64_t ns) { return static_cast<double>(ns) * 1e-9; }

// Milliseconds elapsed on the monotonic clock since `start` (for timing work, not stamps).
inline double msSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
      .count();
}

}  // namespace stereomap::common
