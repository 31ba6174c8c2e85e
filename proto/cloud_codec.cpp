#include "proto/cloud_codec.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <limits>
#include <string>

#include "proto/detail/codecs.hpp"

namespace stereomap::proto {

using common::ErrorCode;
using common::makeError;
using common::PointCloud;
using common::Result;

namespace {

constexpr std::array<std::pair<CloudEncoding, std::string_view>, 3> kNames = {{
    {CloudEncoding::kDraco, "draco"},
    {CloudEncoding::kQuantZstd, "zstd"},
    {CloudEncoding::kRawF32, "raw"},
}};

std::vector<uint8_t> encodeRaw(const PointCloud& cloud) {
  const size_t n = cloud.size();
  std::vector<uint8_t> payload(n * 12 + (cloud.hasIntensity() ? n : 0));
  // Eigen's Vector3f is three packed floats: the points are 12 n contiguous bytes.
  // NOLINTNEXTLINE(bugprone-undefined-memory-manipulation)
  if (n > 0) std::memcpy(payload.data(), cloud.points.data(), n * 12);
  if (cloud.hasIntensity())
    std::copy(cloud.intensity.begin(), cloud.intensity.end(), payload.begin() + n * 12);
  return payload;
}

Result<PointCloud> decodeRaw(std::span<const uint8_t> payload, const CloudPayloadInfo& info) {
  const size_t n = info.point_count;
  const size_t expected = n * 12 + (info.has_intensity ? n : 0);
  if (payload.size() != expected) {
    return makeError(ErrorCode::kCorrupt, "raw payload of " + std::to_string(payload.size()) +
                                              " bytes, expected " + std::to_string(expected));
  }
  PointCloud cloud;
  cloud.points.resize(n);
  // NOLINTNEXTLINE(bugprone-undefined-memory-manipulation): three packed floats each
  if (n > 0) std::memcpy(cloud.points.data(), payload.data(), n * 12);
  if (info.has_intensity) cloud.intensity.assign(payload.begin() + n * 12, payload.end());
  for (const auto& p : cloud.points) {
    if (!p.allFinite()) return makeError(ErrorCode::kCorrupt, "raw payload has a non-finite point");
  }
  return cloud;
}

struct Bounds {
  common::Vec3f lo, hi;
  double range() const { return (hi - lo).maxCoeff(); }
};
Bounds boundsOf(const PointCloud& cloud) {
  Bounds b{cloud.points.front(), cloud.points.front()};
  for (const auto& p : cloud.points) {
    b.lo = b.lo.cwiseMin(p);
    b.hi = b.hi.cwiseMax(p);
  }
  return b;
}

}  // namespace

Result<std::vector<uint8_t>> encodeCloud(const PointCloud& cloud,
                                         const CloudCodecOptions& options) {
  if (options.quantization_bits < 1 || options.quantization_bits > 30) {
    return makeError(ErrorCode::kInvalidArgument, "quantization_bits must be in 1..30, got " +
                                                      std::to_string(options.quantization_bits));
  }
  if (options.draco_speed < 0 || options.draco_speed > 10) {
    return makeError(ErrorCode::kInvalidArgument, "Draco speed must be in 0..10");
  }
  if (options.zstd_level < 1 || options.zstd_level > 19) {
    return makeError(ErrorCode::kInvalidArgument, "zstd level must be in 1..19");
  }
  if (cloud.hasIntensity() && cloud.intensity.size() != cloud.size()) {
    return makeError(ErrorCode::kInvalidArgument, "intensity count differs from point count");
  }
  if (cloud.size() > std::numeric_limits<uint32_t>::max()) {
    return makeError(ErrorCode::kInvalidArgument, "more points than a CloudFrame can count");
  }
  for (const auto& p : cloud.points) {
    if (!p.allFinite())
      return makeError(ErrorCode::kInvalidArgument, "cloud has a non-finite point");
  }
  switch (options.encoding) {
    case CloudEncoding::kDraco:
      return detail::encodeDraco(cloud, options);
    case CloudEncoding::kQuantZstd:
      return detail::encodeQuantZstd(cloud, options);
    case CloudEncoding::kRawF32:
      return encodeRaw(cloud);
  }
  return makeError(ErrorCode::kInvalidArgument, "unknown cloud encoding");
}

Result<PointCloud> decodeCloud(std::span<const uint8_t> payload, const CloudPayloadInfo& info) {
  switch (info.encoding) {
    case CloudEncoding::kDraco:
      return detail::decodeDraco(payload, info);
    case CloudEncoding::kQuantZstd:
      return detail::decodeQuantZstd(payload, info);
    case CloudEncoding::kRawF32:
      return decodeRaw(payload, info);
  }
  return makeError(ErrorCode::kCorrupt, "unknown cloud encoding");
}

int quantizationBitsFor(const PointCloud& cloud, double max_error_m, int max_bits) {
  if (cloud.points.empty() || !(max_error_m > 0)) return max_bits;
  const double range = boundsOf(cloud).range();
  for (int bits = 1; bits < max_bits; ++bits) {
    if (range / ((1 << bits) - 1) / 2.0 <= max_error_m) return bits;
  }
  return max_bits;
}

double maxPositionError(const PointCloud& cloud, int quantization_bits) {
  if (cloud.points.empty()) return 0.0;
  const auto [lo, hi] = boundsOf(cloud);
  const double range = (hi - lo).maxCoeff();
  // Draco quantises and restores in float: besides half a step, two units in the last place
  // of the largest coordinate (2.2 um beyond half a step were seen on KITTI clouds, 80 m out).
  const double largest = std::max(lo.cwiseAbs().maxCoeff(), hi.cwiseAbs().maxCoeff());
  return range / ((1 << quantization_bits) - 1) / 2.0 +
         2.0 * largest * std::numeric_limits<float>::epsilon();
}

std::string_view encodingName(CloudEncoding encoding) {
  for (const auto& [value, name] : kNames) {
    if (value == encoding) return name;
  }
  return "unknown";
}

std::optional<CloudEncoding> parseEncoding(std::string_view name) {
  for (const auto& [value, known] : kNames) {
    if (known == name) return value;
  }
  return std::nullopt;
}

}  // namespace stereomap::proto
