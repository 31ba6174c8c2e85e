#include "server/core/latency.hpp"

#include <algorithm>
#include <cmath>

namespace stereomap::core {

void LatencyHistogram::add(double seconds) {
  if (!(seconds >= 0)) seconds = 0;  // a clock step back (or NaN) counts as no lag
  const double doublings = seconds <= kFirst ? 0.0 : std::log2(seconds / kFirst);
  const auto bucket = static_cast<size_t>(std::ceil(doublings * kPerDoubling));
  ++counts_[std::min(bucket, kBuckets - 1)];
  ++count_;
  max_ = std::max(max_, seconds);
}

void LatencyHistogram::merge(const LatencyHistogram& other) {
  for (size_t i = 0; i < kBuckets; ++i) counts_[i] += other.counts_[i];
  count_ += other.count_;
  max_ = std::max(max_, other.max_);
}

double LatencyHistogram::quantile(double q) const {
  if (count_ == 0) return 0;
  const auto rank = static_cast<uint64_t>(std::ceil(std::clamp(q, 0.0, 1.0) * count_));
  uint64_t seen = 0;
  for (size_t i = 0; i < kBuckets; ++i) {
    seen += counts_[i];
    if (seen >= std::max<uint64_t>(rank, 1)) {
      // The last bucket holds everything longer: its edge is the longest lag seen.
      if (i == kBuckets - 1) return max_;
      return std::min(max_, kFirst * std::exp2(static_cast<double>(i) / kPerDoubling));
    }
  }
  return max_;
}

}  // namespace stereomap::core
