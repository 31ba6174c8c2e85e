// Point-cloud payloads of CloudFrame samples, in three encodings (the IDL's CloudEncoding):
// - Draco: positions quantised over the cloud's bounding cube and entropy coded, kd-tree
//   (reorders points) or sequential;
// - quantised + zstd: the same quantisation grid, the points kept in their order (a thinned
//   cloud comes in image order, so neighbours are close), each coordinate delta coded, then
//   zstd (Debian's libzstd);
// - raw: x y z float triples, then one intensity byte per point.
// Decoding checks everything it reads and returns an Error for a truncated or corrupt payload
// (kCorrupt), or one whose point count differs from its message's (kConflict).
//
// Quantisation bound (Draco and quantised + zstd): every coordinate comes back within
// range / (2^bits - 1) / 2 of its original, where range is the largest side of the cloud's
// bounding box, plus float rounding (maxPositionError).
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <string_view>
#include <vector>

#include "common/point_cloud.hpp"
#include "common/result.hpp"
#include "proto/messages.hpp"

namespace stereomap::proto {

struct CloudCodecOptions {
  CloudEncoding encoding = CloudEncoding::kDraco;  // as CloudFrameMsg's default
  int quantization_bits = 14;                      // 1..30; 14 bits over 10 m ≈ 0.3 mm
  int draco_speed = 10;       // Draco speed 0 (smallest) .. 10 (fastest): 10 on thinned clouds
                              // is as small as 0 and the fastest (docs/BENCHMARKS.md)
  bool draco_kd_tree = true;  // else Draco's sequential coder (keeps the order)
  int zstd_level = 1;         // 1..19
};

// What a payload must hold, from its message: decoders of layouts without a count of their
// own (raw) need it, and the others check it before they allocate. point_count is trusted as
// a bound: the caller limits it (the server's IngestLimits) before decoding.
struct CloudPayloadInfo {
  CloudEncoding encoding = CloudEncoding::kDraco;
  uint32_t point_count = 0;
  bool has_intensity = false;
};

inline CloudPayloadInfo payloadInfo(const CloudFrameMsg& frame) {
  return {frame.encoding, frame.point_count, frame.has_intensity};
}

common::Result<std::vector<uint8_t>> encodeCloud(const common::PointCloud& cloud,
                                                 const CloudCodecOptions& options = {});

common::Result<common::PointCloud> decodeCloud(std::span<const uint8_t> payload,
                                               const CloudPayloadInfo& info);

// The largest error per coordinate that quantisation may introduce for `cloud`.
double maxPositionError(const common::PointCloud& cloud, int quantization_bits);

// The fewest bits (at most max_bits) whose quantisation error stays within max_error_m for
// `cloud` (the half step; float rounding aside).
int quantizationBitsFor(const common::PointCloud& cloud, double max_error_m, int max_bits);

// "draco", "zstd", "raw" (the names of --codec flags).
std::string_view encodingName(CloudEncoding encoding);
std::optional<CloudEncoding> parseEncoding(std::string_view name);

}  // namespace stereomap::proto
