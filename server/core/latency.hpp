// A latency histogram on log-spaced buckets (8 per doubling, 0.1 ms to 2 min): constant
// memory however many samples, quantiles within 9 % of the true value, mergeable across
// sessions. What the server keeps of the lag from a frame's arrival to its tiles' publication.
//
//   LatencyHistogram lag;
//   lag.add(0.012);              // seconds
//   const double p95 = lag.quantile(0.95);
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>

namespace stereomap::core {

class LatencyHistogram {
 public:
  void add(double seconds);
  void merge(const LatencyHistogram& other);
  uint64_t count() const { return count_; }
  double max() const { return max_; }
  // The q-quantile (0..1) in seconds: the upper edge of the bucket it falls in (an upper
  // bound, at most 9 % above); 0 with no samples.
  double quantile(double q) const;

 private:
  static constexpr int kPerDoubling = 8;
  static constexpr double kFirst = 1e-4;      // upper edge of bucket 0
  static constexpr size_t kBuckets = 8 * 21;  // up to 0.1 ms * 2^21: 210 s
  std::array<uint64_t, kBuckets> counts_{};
  uint64_t count_ = 0;
  double max_ = 0;
};

}  // namespace stereomap::core
