// Draco point-cloud codec for CloudFrame payloads: positions quantised to a configurable
// number of bits over the cloud's bounding cube, optional 8-bit intensity. Decoding checks
// everything it reads and returns an Error for a truncated or corrupt payload.
//
// Quantisation bound: every coordinate comes back within range / (2^bits - 1) / 2 of its
// original, where range is the largest side of the cloud's bounding box, plus float rounding
// (maxPositionError).
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include "common/point_cloud.hpp"
#include "common/result.hpp"

namespace stereomap::proto {

struct CloudCodecOptions {
  int quantization_bits = 14;  // 1..30; 14 bits over 10 m ≈ 0.3 mm
  int speed = 5;               // Draco speed 0 (smallest) .. 10 (fastest)
};

common::Result<std::vector<uint8_t>> encodeCloud(const common::PointCloud& cloud,
                                                 const CloudCodecOptions& options = {});

common::Result<common::PointCloud> decodeCloud(std::span<const uint8_t> payload);

// The largest error per coordinate that quantisation may introduce for `cloud`.
double maxPositionError(const common::PointCloud& cloud, int quantization_bits);

}  // namespace stereomap::proto
